"""Racing in traffic: scenes with several cars, collisions and fault, opponents that drive,
the Overtake task and the PettingZoo parallel env."""

from __future__ import annotations

import math
from collections import deque

import gymnasium as gym
import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import saferace  # noqa: F401  - registers the tasks
from saferace.agents.mpc import MPCExpert
from saferace.agents.pure_pursuit import PurePursuit, PurePursuitSettings
from saferace.agents.traffic_expert import (
    FOLLOW_BRAKING_MPS2,
    FOLLOW_GAP_M,
    HISTORY_S,
    MOVE_OVER_SLOPE,
    PREDICTION_MARGIN_M,
    NearOpponent,
    TrafficExpert,
    following_speed_mps,
    passing_side,
)
from saferace.envs.collisions import CarMotion, attribute_fault
from saferace.envs.reference_lines import reference_line
from saferace.envs.traffic import OpponentSpec, opponent_specs
from saferace.errors import SafeRaceError
from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig, apply_filter
from saferace.multi import parallel_env
from saferace.names import RC10_BUMPER_HALF_EXTENTS_M
from saferace.safety.cbf.filter import GAIN_PRESETS, SafetyFilter
from saferace.safety.models import MIN_SPEED_MPS, param_values
from saferace.safety.traffic.car_barriers import (
    CAR_GAINS,
    CAR_ROW_WEIGHT,
    car_rows,
    opponent_predictions,
)
from saferace.safety.vehicle_params import load_params
from saferace.track import Track

STRAIGHT_TRACK = "technical"  # straight from s = 0 to 12 m, lane 1 m wide
BRAKE = np.array([0.0, -4.0])


def drive(env, ego_action, opponent_actions=None, steps=60):
    """Step with fixed actions (the opponents' for ``external`` ones); every collision."""
    collisions, infos = [], []
    for _ in range(steps):
        if opponent_actions is not None:
            env.unwrapped.traffic.set_external_actions(opponent_actions)
        _, _, terminated, _, info = env.step(ego_action)
        collisions += info["collisions"]
        infos.append(info)
        if terminated:
            break
    return collisions, infos


def external(gap_m: float, offset_m: float = 0.0, speed_factor: float = 1.0) -> OpponentSpec:
    return OpponentSpec("external", gap_m=gap_m, start_offset_m=offset_m, speed_factor=speed_factor)


def test_a_rear_end_is_reported_once_and_is_the_following_cars_fault():
    env = gym.make(
        "saferace/CenterLine-v0", track=STRAIGHT_TRACK, opponents=[external(1.5, 0.0, 0.5)]
    )
    env.reset(seed=0, options={"start_speed_mps": 2.5})
    collisions, _ = drive(env, np.array([0.0, 1.0]), {"car1": BRAKE})
    assert len(collisions) == 1, collisions  # pushing on keeps it one collision
    (collision,) = collisions
    assert set(collision["cars"]) == {"car0", "car1"}
    assert collision["at_fault"] == "car0" and collision["kind"] == "rear-end"
    assert collision["relative_speed_mps"] > 1.0
    assert 0.0 < collision["time_s"] < 3.0

    behind = gym.make("saferace/CenterLine-v0", track=STRAIGHT_TRACK, opponents=[external(-1.5)])
    behind.reset(seed=0, options={"start_speed_mps": 1.0, "start_s_m": 5.0})
    collisions, _ = drive(behind, BRAKE, {"car1": np.array([0.0, 3.0])})
    assert [c["at_fault"] for c in collisions] == ["car1"]
    assert collisions[0]["kind"] == "rear-end"


@pytest.mark.parametrize("swiper", ["car0", "car1"])
def test_a_side_swipe_is_the_fault_of_the_car_that_moved_across(swiper: str):
    env = gym.make("saferace/CenterLine-v0", track=STRAIGHT_TRACK, opponents=[external(0.0, 0.34)])
    env.reset(seed=0, options={"start_speed_mps": 2.0})
    hold = np.array([0.0, 0.0])
    ego = np.array([0.12, 0.0]) if swiper == "car0" else hold  # left, into car1
    other = np.array([-0.12, 0.0]) if swiper == "car1" else hold  # right, into car0
    collisions, _ = drive(env, ego, {"car1": other}, steps=30)
    assert [c["at_fault"] for c in collisions] == [swiper]
    assert collisions[0]["kind"] == "side"


def test_fault_rule_on_given_motions():
    ahead = np.array([1.0, 0.0])
    behind_fast = CarMotion(np.array([0.0, 0.0]), np.array([3.0, 0.0]))
    ahead_slow = CarMotion(np.array([0.46, 0.05]), np.array([1.0, 0.0]))
    assert attribute_fault(behind_fast, ahead_slow, ahead) == (0, "rear-end")
    assert attribute_fault(ahead_slow, behind_fast, ahead) == (1, "rear-end")
    west_behind = CarMotion(np.array([0.46, 0.05]), np.array([-3.0, 0.0]))
    west_ahead = CarMotion(np.zeros(2), np.array([-1.0, 0.0]))
    assert attribute_fault(west_ahead, west_behind, -ahead) == (1, "rear-end")
    backing = CarMotion(ahead_slow.position_m, np.array([-1.0, 0.0]))
    stopped = CarMotion(behind_fast.position_m, np.zeros(2))
    assert attribute_fault(stopped, backing, ahead) == (1, "rear-end")
    left_still = CarMotion(np.array([0.1, 0.32]), np.array([2.0, 0.0]))
    right_moving_left = CarMotion(np.array([0.0, 0.0]), np.array([2.0, 0.4]))
    assert attribute_fault(left_still, right_moving_left, ahead) == (1, "side")
    assert attribute_fault(right_moving_left, left_still, ahead) == (0, "side")


def ego_states(infos):
    return np.array(
        [[i["x_m"], i["y_m"], i["yaw_rad"], i["v_x_mps"], i["steer_angle_rad"]] for i in infos]
    )


def test_a_far_away_second_car_leaves_the_first_cars_motion_unchanged():
    runs = []
    for opponents in ([], ["pure-pursuit:gap_m=28,speed_factor=0.7,lateral_offset_m=0"]):
        env = gym.make("saferace/RacingLine-v0", track=STRAIGHT_TRACK, opponents=opponents)
        observation, info = env.reset(seed=0)
        driver = PurePursuit.for_env(env)
        infos = []
        for _ in range(200):
            observation, _, _, _, info = env.step(driver.act(observation, info))
            infos.append(info)
        runs.append(infos)
    np.testing.assert_array_equal(ego_states(runs[0]), ego_states(runs[1]))
    gaps = [info["opponents"][0]["gap_m"] for info in runs[1]]
    assert min(abs(gap) for gap in gaps) > 10.0
    assert runs[1][-1]["opponents"][0]["s_m"] != runs[1][0]["opponents"][0]["s_m"]  # it drove


def opponent_alone(track: str, opponent: str, steps: int = 180) -> list[dict]:
    """The opponent's states over ``steps`` steps, ahead of an ego car at rest at the start."""
    env = gym.make("saferace/CenterLine-v0", track=track, opponents=[opponent])
    env.reset(seed=4, options={"start_speed_mps": 0.0})
    _, infos = drive(env, np.zeros(2), steps=steps)
    assert len(infos) == steps
    assert not any(info["collisions"] for info in infos)
    return [info["opponents"][0] for info in infos]


@pytest.mark.parametrize("track", ["technical", "varying"])
@pytest.mark.parametrize(
    "opponent", ["expert", "racer", "pure-pursuit", "lane-changer", "blocker", "braking"]
)
def test_every_opponent_policy_drives_inside_its_lane(track: str, opponent: str):
    states = opponent_alone(track, f"{opponent}:lateral_offset_m=0.25")
    assert not any(state["outside_lane"] for state in states)
    assert states[-1]["progress_m"] > 10.0


def test_the_opponents_drive_as_they_say():
    track = Track.load(STRAIGHT_TRACK)
    expert = opponent_alone(STRAIGHT_TRACK, "expert:speed_factor=0.8")
    racing = reference_line(track, "racing")
    speeds = np.array([state["speed_mps"] for state in expert[60:]])
    wanted = 0.8 * racing.speed_at(np.array([state["s_m"] for state in expert[60:]]))
    assert np.mean(speeds) == pytest.approx(np.mean(wanted), rel=0.15)
    pursuit = opponent_alone(STRAIGHT_TRACK, "pure-pursuit:lateral_offset_m=-0.2")
    on_straights = [
        state["e_y_m"]
        for state in pursuit[40:]
        if abs(track.centerline.curvature_scalar(state["s_m"])) < 0.05
    ]
    assert np.median(on_straights) == pytest.approx(-0.2, abs=0.05)
    changer = np.array([state["e_y_m"] for state in opponent_alone(STRAIGHT_TRACK, "lane-changer")])
    assert changer.max() > 0.15 and changer.min() < -0.15  # both lanes
    blocker = opponent_alone(STRAIGHT_TRACK, "blocker:lateral_offset_m=0.25")
    turn_here = [track.centerline.curvature_scalar(state["s_m"]) for state in blocker]
    inside = [
        np.sign(state["e_y_m"]) == np.sign(kappa)
        for state, kappa in zip(blocker, turn_here, strict=True)
        if abs(kappa) > 0.3 and abs(state["e_y_m"]) > 0.05
    ]
    assert len(inside) > 20 and np.mean(inside) > 0.8
    braking = [state["speed_mps"] for state in opponent_alone(STRAIGHT_TRACK, "braking")]
    assert max(braking) > 1.5 and min(braking[40:]) < 0.5 * max(braking)


def test_the_blocker_covers_the_line_of_a_car_close_behind():
    env = gym.make(
        "saferace/CenterLine-v0",
        track=STRAIGHT_TRACK,
        opponents=["blocker:gap_m=1.5,lateral_offset_m=0.3,speed_factor=0.6"],
    )
    driver = PurePursuit.for_env(env)
    observation, info = env.reset(seed=0)
    offsets = []
    for _ in range(40):  # the ego holds 0.2 m left of the centre line, 1-2 m behind
        action = driver.act(observation, info)
        action[0] += 0.8 * (0.2 - info["e_y_m"])
        observation, _, _, _, info = env.step(action)
        offsets.append(info["opponents"][0]["e_y_m"])
    assert offsets[-1] > 0.1


def held_alongside(policy: str) -> tuple[list[dict], list[float]]:
    """The collisions, and the lateral distances between the cars in the left turn at the
    straight's end (where the racing line crosses to the left, from s = 15 m), while the
    ego holds 0.15 m left of the centre line 0.2 m behind a ``policy`` opponent on the
    racing line."""
    env = gym.make(
        "saferace/CenterLine-v0",
        track=STRAIGHT_TRACK,
        opponents=[f"{policy}:gap_m=0.3,start_offset_m=-0.35,speed_factor=0.7"],
    )
    driver = PurePursuit.for_env(env)
    observation, info = env.reset(seed=0, options={"start_s_m": 8.0, "start_speed_mps": 3.0})
    collisions, apart_m = [], []
    for _ in range(45):
        (opponent,) = info["opponents"]
        action = driver.act(observation, info)
        action[0] += 0.8 * (0.15 - info["e_y_m"])
        action[1] = 3.0 * (opponent["gap_m"] - 0.2) + 2.0 * (
            opponent["speed_mps"] - info["v_x_mps"]
        )
        observation, _, _, _, info = env.step(action)
        collisions += info["collisions"]
        if info["s_m"] > 15.0:
            apart_m.append(info["e_y_m"] - info["opponents"][0]["e_y_m"])
    assert len(apart_m) > 10
    return collisions, apart_m


def test_the_racer_leaves_room_to_a_car_alongside_where_the_expert_does_not():
    collisions, apart_m = held_alongside("racer")
    assert collisions == [] and min(apart_m) > 0.37  # bumpers 0.31 m wide
    collisions, apart_m = held_alongside("expert")  # blind: turns in across the ego
    assert [collision["at_fault"] for collision in collisions] == ["car1"]


def test_behind_a_car_that_leaves_room_a_pass_needs_room_only_until_alongside():
    rooms = {}
    for leaves_room in (False, True):
        expert = traffic_expert_on_the_straight()
        racing = expert.racing_line
        # at 2 m/s on the racing line, which crosses to the left into the turn after s = 15 m
        for s in np.linspace(14.5, 15.5, round(HISTORY_S / expert.settings.dt_s)):
            expert.remember(NearOpponent("car1", s, float(racing.offset_at(s)), 2.0, leaves_room))
        opponent = NearOpponent("car1", 15.5, float(racing.offset_at(15.5)), 2.0, leaves_room)
        expert._ego_speed_mps = 3.0
        rooms[leaves_room] = expert.pass_rooms(opponent, 14.7)  # 0.8 m behind
    # on the left the car crosses into the ego's line before it is level, not before it is
    # alongside; on the right, the lane's edge, there is no room either way
    assert rooms[False][0] < 0.0 < rooms[True][0]
    assert rooms[False][1] == rooms[True][1] < 0.0


def test_every_driver_is_told_which_cars_leave_room():
    env = gym.make("saferace/RacingLine-v0", track=STRAIGHT_TRACK, opponents=["racer", "expert"])
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(2))
    assert [opponent["leaves_room"] for opponent in info["opponents"]] == [True, False]
    seen_by_car2 = env.unwrapped.traffic.cars[1].state["cars"]
    assert {car["name"]: car["leaves_room"] for car in seen_by_car2} == {
        "car0": False,
        "car1": True,
    }


def test_the_expert_passes_a_racer_where_it_follows_the_blind_expert():
    def lead_after_a_lap(policy: str) -> float:
        env = gym.make(
            "saferace/Overtake-v0",
            track="oval",
            opponents=[f"{policy}:gap_m=2,speed_factor=0.8"],
            max_laps=1,
            terminate_on_collision=False,
        )
        expert = make_agent("expert", env)
        observation, info = env.reset(seed=0)
        done = False
        while not done:
            observation, _, terminated, truncated, info = env.step(expert.act(observation, info))
            assert not info["collisions"]
            done = terminated or truncated
        return info["opponents"][0]["ego_lead_m"]

    assert lead_after_a_lap("racer") > 0.5  # passed, on the inside of a turn
    assert -3.0 < lead_after_a_lap("expert") < 0.0  # followed: its line leaves no room


def test_overtake_task_penalises_and_ends_on_an_at_fault_collision():
    env = gym.make("saferace/Overtake-v0", track=STRAIGHT_TRACK)
    _, info = env.reset(seed=0)
    (opponent,) = info["opponents"]
    assert opponent["policy"] == "expert" and opponent["gap_m"] == pytest.approx(2.0, abs=0.05)
    rammer = PurePursuit.for_env(env, PurePursuitSettings(speed_scale=1.5, max_speed_mps=8.0))
    observation, rewards, terminated = None, [], False
    for _ in range(200):
        observation, reward, terminated, _, info = env.step(rammer.act(observation, info))
        rewards.append(reward)
        if terminated:
            break
    assert terminated and info["at_fault_collisions"] == 1
    assert rewards[-1] < -9.0 and info["reward_collision"] == -10.0

    lenient = gym.make("saferace/Overtake-v0", track=STRAIGHT_TRACK, terminate_on_collision=False)
    _, info = lenient.reset(seed=0)
    collisions = 0
    for _ in range(len(rewards) + 20):
        _, _, terminated, _, info = lenient.step(rammer.act(None, info))
        collisions += info["at_fault_collisions"]
        assert not terminated
    assert collisions >= 1


def red_pixels(image: np.ndarray) -> int:
    r, g, b = (image[..., k].astype(int) for k in range(3))
    return int(np.sum((r > 150) & (g < 80) & (b < 80)))


def test_every_car_sees_the_others_but_not_itself():
    env = parallel_env(cars=2, track=STRAIGHT_TRACK, start_gaps_m=[-1.2], image_size=(64, 96))
    observations, _ = env.reset(seed=0, options={"start_s_m": 4.0})
    assert red_pixels(observations["car1"]["image"]) > 10  # car0's red body ahead
    assert red_pixels(observations["car0"]["image"]) == 0  # its own body hidden
    with_opponent, alone = (
        gym.make(
            "saferace/CenterLine-v0", track=STRAIGHT_TRACK, image_size=(64, 96), opponents=opponents
        ).reset(seed=0, options={"start_s_m": 4.0})[0]["image"]
        for opponents in ([external(1.2)], [])
    )
    assert blue_pixels(with_opponent) - blue_pixels(alone) > 15  # its blue body ahead


def blue_pixels(image: np.ndarray) -> int:
    """Pixels of the first opponent's blue body (the sky is too pale, roadside boxes too few)."""
    r, g, b = (image[..., k].astype(int) for k in range(3))
    return int(np.sum((b - r > 100) & (g < 150)))


def test_stereo_and_chase_views_show_the_opponent():
    views = []
    for opponents in ([external(1.2)], []):
        env = gym.make(
            "saferace/RacingLine-v0",
            track=STRAIGHT_TRACK,
            stereo=True,
            render_mode="rgb_array",
            opponents=opponents,
        )
        image = env.reset(seed=0, options={"start_s_m": 4.0})[0]["image"]
        views.append((image[..., :3], image[..., 3:], env.render()))
    for with_opponent, alone in zip(*views, strict=True):
        assert blue_pixels(with_opponent) - blue_pixels(alone) > 10


def test_randomised_looks_vary_the_opponents_colours():
    env = gym.make(
        "saferace/RacingLine-v0", track="lab", randomize="strong", opponents=["external:gap_m=2"]
    )
    model = env.unwrapped.model
    shell = model.geom("car1/shell").id
    colours = []
    for seed in range(3):
        env.reset(seed=seed)
        colours.append(model.geom_rgba[shell].copy())
    assert np.ptp(np.array(colours)[:, :3], axis=0).max() > 0.05
    assert model.geom_rgba[model.geom("shell").id][0] == pytest.approx(0.8)  # the ego stays red


def test_pettingzoo_parallel_api():
    parallel_api_test(parallel_env(cars=3, track="oval", max_steps=80), num_cycles=100)


def test_every_car_in_pettingzoo_reports_the_tasks_terms():
    env = parallel_env(cars=2, track="oval", collision_penalty=3.0)
    env.reset(seed=0)
    for _ in range(10):  # straight on, still on the oval's straight
        _, rewards, _, _, infos = env.step({agent: np.array([0.0, 1.0]) for agent in env.agents})
    terms = ("reward_progress", "reward_deviation", "reward_collision")
    for agent in ("car0", "car1"):
        info = infos[agent]
        assert {"lap", "cost", "at_fault_collisions", "collisions", *terms} <= set(info)
        assert rewards[agent] == pytest.approx(sum(info[term] for term in terms))
        assert info["reward_progress"] > 0.05  # both drove on
    env.close()


def two_car_race(seed: int) -> list[tuple]:
    """Two cars from a random start (drawn from ``seed``), driven by the same random actions."""
    env = parallel_env(cars=2, track=STRAIGHT_TRACK, random_start=True)
    env.reset(seed=seed)
    rng = np.random.default_rng(0)
    trace = []
    for _ in range(40):
        actions = {
            agent: rng.uniform([-0.1, -1.0], [0.1, 2.0]).astype(np.float32) for agent in env.agents
        }
        observations, rewards, _, _, infos = env.step(actions)
        trace += [
            (
                agent,
                infos[agent]["x_m"],
                infos[agent]["y_m"],
                rewards[agent],
                observations[agent]["image"].tobytes(),
            )
            for agent in sorted(infos)
        ]
    return trace


def test_two_cars_driven_through_pettingzoo_are_deterministic_per_seed():
    assert two_car_race(3) == two_car_race(3)
    assert two_car_race(3) != two_car_race(4)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("kart", "unknown opponent policy"),
        ("expert:speed=2", "unknown opponent field"),
        ("expert:gap_m=far", "are numbers"),
        ("expert:speed_factor=3", "speed_factor"),
        ("expert:gap_m", "POLICY"),
        (42, "OpponentSpec, a dict or a string"),
    ],
)
def test_bad_opponents_raise_clear_errors(value, message: str):
    with pytest.raises(SafeRaceError, match=message):
        opponent_specs([value])


def test_opponents_start_three_metres_apart_unless_told():
    specs = opponent_specs(["blocker", {"policy": "braking", "gap_m": -2}, "expert"])
    assert [spec.gap_m for spec in specs] == [3.0, -2.0, 9.0]


def braking_ahead(filtered: bool, opponent_noise_m: float = 0.0):
    """The ego at 3 m/s, full throttle, 1.5 m behind a car braking as hard as it can."""
    env = gym.make("saferace/CenterLine-v0", track=STRAIGHT_TRACK, opponents=[external(1.5)])
    if filtered:
        env = SafetyFilter(env, opponent_noise_m=opponent_noise_m, **GAIN_PRESETS["grip"])
    env.reset(seed=0, options={"start_speed_mps": 3.0})
    return drive(env, np.array([0.0, 4.0]), {"car1": BRAKE}, steps=40)


@pytest.mark.parametrize("opponent_noise_m", [0.0, 0.05])
def test_the_car_barrier_brakes_for_a_car_braking_hard_ahead(opponent_noise_m: float):
    unfiltered, _ = braking_ahead(filtered=False)
    assert [c["at_fault"] for c in unfiltered] == ["car0"]
    collisions, infos = braking_ahead(filtered=True, opponent_noise_m=opponent_noise_m)
    assert collisions == []
    decisions = [info["safety"] for info in infos]
    assert min(decision["filtered_action"][1] for decision in decisions) < -3.0  # braked
    assert any(decision["fallback"] == "car" for decision in decisions)  # braked in the lane
    assert min(decision["barriers"]["car1"] for decision in decisions) > 0.0
    assert not any(info["outside_lane"] for info in infos)


def test_the_opponent_noise_asked_of_the_filter_config_widens_and_blurs_the_car_barrier():
    """1.5 m behind a car, first step: the barrier's value is the same on every seed for a
    filter that sees the opponents as they are; with 5 cm of noise (set through the filter
    config, as every command does) the prediction differs per seed and the widened ellipse
    leaves less room on every one."""
    env = gym.make("saferace/CenterLine-v0", track=STRAIGHT_TRACK, opponents=[external(1.5)])
    first_values = {}
    for noise_m in (0.0, 0.05):
        config = FilterConfig(kind="cbf", gains="grip", opponent_noise_m=noise_m)
        filtered = apply_filter(env, config, seed=0)
        values = []
        for seed in range(6):
            filtered.reset(seed=seed, options={"start_speed_mps": 3.0})
            info = filtered.step(np.array([0.0, 4.0]))[-1]
            values.append(info["safety"]["barriers"]["car1"])
        first_values[noise_m] = np.array(values)
    exact, noisy = first_values[0.0], first_values[0.05]
    assert np.ptp(exact) == 0.0 and np.ptp(noisy) > 0.1, noisy  # the predictions are noisy
    assert noisy.max() < 0.8 * exact[0], (noisy, exact[0])  # and the semi-axes widened
    env.close()


def test_the_car_barrier_steers_away_from_a_car_alongside():
    env = SafetyFilter(
        gym.make("saferace/CenterLine-v0", track=STRAIGHT_TRACK, opponents=[external(0.0, 0.4)]),
        **GAIN_PRESETS["grip"],
    )
    env.reset(seed=0, options={"start_speed_mps": 2.0})
    collisions, infos = drive(env, np.array([0.2, 0.0]), {"car1": np.zeros(2)}, steps=30)
    assert collisions == []
    first = infos[0]["safety"]
    # Alone, the lane barrier lets 0.15 rad of the 0.2 through; beside the car the car barrier
    # turns the car away to the right, without braking or handing over to a fallback.
    assert first["filtered_action"][0] < 0.0, first["filtered_action"]
    assert first["filtered_action"][1] > -1.0 and first["fallback"] == "", first


def test_opponent_predictions_wrap_the_lap_and_take_the_speed_along_the_track():
    track = Track.load(STRAIGHT_TRACK)
    opponent = {"s_m": 0.5, "e_y_m": 0.1, "e_psi_rad": 0.3, "speed_mps": 2.0}
    ((ds, e_y_o, v_o),) = opponent_predictions([opponent], track, track.length_m - 0.5)
    assert ds == pytest.approx(-1.0) and e_y_o == 0.1
    assert v_o == pytest.approx(2.0 * np.cos(0.3), rel=1e-3)  # on the straight
    noisy = opponent_predictions([opponent] * 200, track, 0.0, 0.05, np.random.default_rng(0))
    assert np.std([p[0] for p in noisy]) == pytest.approx(0.05, rel=0.2)
    again = opponent_predictions([opponent] * 200, track, 0.0, 0.05, np.random.default_rng(0))
    assert again == noisy  # drawn from the generator given: the same per seed


def test_an_opponent_in_a_bend_moves_along_the_track_at_its_own_curvature():
    """Mid-bend on lab, 0.1 m inside and 0.3 rad to its lane at 2 m/s, seen from the
    straight: its arc length grows at ``2 cos 0.3 / (1 - kappa 0.1)``, the curvature its
    own, not the ego's."""
    track = Track.load("lab")
    grid = np.linspace(0.0, track.length_m, 400, endpoint=False)
    curvatures = np.array([track.centerline.curvature_scalar(s) for s in grid])
    s_o, ego_s = (
        float(grid[np.argmax(np.abs(curvatures))]),
        float(grid[np.argmin(np.abs(curvatures))]),
    )
    kappa = track.centerline.curvature_scalar(s_o)
    assert abs(kappa) > 0.5 and abs(track.centerline.curvature_scalar(ego_s)) < 0.05
    opponent = {"s_m": s_o, "e_y_m": 0.1, "e_psi_rad": 0.3, "speed_mps": 2.0}
    ((_, _, v_o),) = opponent_predictions([opponent], track, ego_s)
    assert v_o == pytest.approx(2.0 * np.cos(0.3) / (1.0 - kappa * 0.1), rel=1e-9)
    assert abs(v_o - 2.0 * np.cos(0.3)) > 0.05


def test_the_car_rows_brake_for_a_car_ahead_in_line_and_vanish_far_away():
    params = param_values(load_params())
    state = np.array([0.0, 0.0, 3.0, 0.0])

    def accel_bounds(prediction: tuple[float, float, float]) -> list[float]:
        """The acceleration bound of each of the opponent's rows (superellipse, following)."""
        a, b, _ = car_rows("kinematic", params, state, 0.0, np.zeros(2), [prediction], CAR_GAINS)
        assert a[0, 1] > 0.0 and list(a[1]) == [0.0, CAR_ROW_WEIGHT]
        return list(b / a[:, 1])

    ellipse, follow = accel_bounds((-2.0, 0.0, 1.0))  # 2 m behind, closing at 2 m/s
    assert ellipse < -3.0 and follow < -2.0
    _, stopped = accel_bounds((-1.1, 0.0, 0.0))  # too close to stop: brake as hard as it may
    assert stopped < -3.5
    _, beside = accel_bounds((-1.1, 0.7, 0.0))  # in the next line over: pass it
    assert beside > 10.0
    ellipse, follow = accel_bounds((-20.0, 0.0, 1.0))  # far: any acceleration the car has
    assert ellipse > 4.0 and follow > 4.0


@pytest.mark.parametrize("side", [-0.25, 0.25])
def test_the_expert_in_traffic_passes_a_slow_car_on_the_side_with_room(side: float):
    env = gym.make(
        "saferace/RacingLine-v0",
        track=STRAIGHT_TRACK,
        opponents=[f"pure-pursuit:gap_m=2,speed_factor=0.5,lateral_offset_m={side}"],
    )
    expert = make_agent("expert", env)
    assert isinstance(expert, TrafficExpert)
    observation, info = env.reset(seed=0)
    offsets = []
    for _ in range(60):
        observation, _, terminated, _, info = env.step(expert.act(observation, info))
        assert not terminated and not info["collisions"] and not info["outside_lane"]
        (opponent,) = info["opponents"]
        if abs(opponent["gap_m"]) < 0.3:  # alongside
            offsets.append(info["e_y_m"] - opponent["e_y_m"])
    assert opponent["gap_m"] < -1.0  # passed
    assert offsets and np.sign(np.mean(offsets)) == -np.sign(side)  # on the other side


def test_the_expert_in_traffic_follows_where_the_lane_has_no_room():
    env = gym.make(
        "saferace/RacingLine-v0",
        track=STRAIGHT_TRACK,
        opponents=["pure-pursuit:gap_m=2,speed_factor=0.5,lateral_offset_m=0"],
    )
    expert = make_agent("expert", env)
    observation, info = env.reset(seed=0)
    for _ in range(80):
        observation, _, _, _, info = env.step(expert.act(observation, info))
        assert not info["collisions"]
    (opponent,) = info["opponents"]
    assert 0.6 < opponent["gap_m"] < 2.0  # behind it, at about the following gap
    assert abs(info["v_x_mps"] - opponent["speed_mps"]) < 0.5


def test_the_expert_in_traffic_stops_behind_a_stopped_car_and_goes_on_when_it_does():
    env = gym.make(
        "saferace/RacingLine-v0", track=STRAIGHT_TRACK, opponents=[external(2.0, 0.0, 0.5)]
    )
    expert = make_agent("expert", env)
    observation, info = env.reset(seed=0, options={"start_speed_mps": 2.0})
    speeds, gaps = [], []
    for step in range(120):
        env.unwrapped.traffic.set_external_actions(
            {"car1": BRAKE if step < 60 else np.array([0.0, 1.0])}
        )
        observation, _, terminated, _, info = env.step(expert.act(observation, info))
        assert not terminated and not info["collisions"]
        speeds.append(info["v_x_mps"])
        gaps.append(info["opponents"][0]["gap_m"])
    assert min(speeds[40:60]) < 0.1 and min(gaps) > 0.6  # stopped behind it, not against it
    assert speeds[-1] > 1.0  # and went on when it did


def test_the_following_speed_stops_behind_a_car_braking_as_hard():
    opponent = NearOpponent("car1", 0.0, 0.0, 3.0)
    for gap in (FOLLOW_GAP_M, 1.5, 4.0):
        speed = following_speed_mps(gap, opponent)
        stopping_m = speed**2 / (2.0 * FOLLOW_BRAKING_MPS2)
        opponent_stopping_m = 3.0**2 / (2.0 * FOLLOW_BRAKING_MPS2)
        assert stopping_m == pytest.approx(opponent_stopping_m + gap - FOLLOW_GAP_M)
    assert following_speed_mps(0.5, opponent) < 3.0  # closer: slower than it, to drop back
    assert following_speed_mps(0.1, NearOpponent("car1", 0.0, 0.0, 0.0)) == 0.0


def traffic_expert_on_the_straight() -> TrafficExpert:
    """A traffic expert on the straight's lane, 1 m wide, with an opponent it drives beside."""
    env = gym.make("saferace/RacingLine-v0", track=STRAIGHT_TRACK, opponents=["external"])
    expert = make_agent("expert", env)
    assert isinstance(expert, TrafficExpert)
    env.close()
    return expert


def expert_bounds(gap_m: float, ego_e_y_m: float, opponent_e_y_m: float, speed_mps: float = 3.0):
    """How far the traffic expert's plan moves the lane's bounds, which side it passes
    on, each stage's speed cap and the lower bounds, on a straight at ``speed_mps`` with an
    opponent ``gap_m`` ahead at 1 m/s that has kept its line for a second."""
    expert = traffic_expert_on_the_straight()
    horizon, dt = expert.settings.horizon, expert.settings.dt_s
    plan_speed_mps = max(speed_mps, MIN_SPEED_MPS)  # as the MPC raises a plan's speeds
    s_stage = 2.0 + plan_speed_mps * dt * np.arange(horizon + 1)  # from s = 2 m
    opponent = NearOpponent("car1", 2.0 + gap_m, opponent_e_y_m, 1.0)
    for _ in range(round(HISTORY_S / dt)):
        expert.remember(opponent)
    expert._ego_e_y, expert._ego_speed_mps = ego_e_y_m, speed_mps
    expert._passes = [plan := expert.plan_for(opponent, 2.0)]
    side = plan.side
    alone = MPCExpert._lane_bounds(expert, s_stage, None)
    upper, lower = expert._lane_bounds(s_stage, None)
    caps = expert._speed_caps_mps(s_stage[1:], None)
    return (upper - alone[0], lower - alone[1]), side, caps, lower


def test_alongside_the_expert_never_crosses_the_opponents_nose():
    # behind, the ego on the right with no room there: it passes on the left, moving over
    # no steeper than MOVE_OVER_SLOPE, held at the following speed until its bound clears the car
    (moved_upper, moved_lower), side, caps, lower = expert_bounds(1.5, -0.2, -0.12, 4.0)
    assert side == 1 and not moved_upper.any() and lower.max() > 0.15  # 0.35 m over
    reachable = -0.2 + MOVE_OVER_SLOPE * 4.0 * 0.05 * np.arange(1, len(lower) + 1)
    assert (lower <= reachable + 1e-9).all()
    *_, lower_at_rest = expert_bounds(1.5, -0.2, -0.12, speed_mps=0.0)
    assert lower_at_rest.max() <= -0.2 + 1e-9  # a car at rest is not asked to move sideways
    assert np.isfinite(caps[0]) and np.isinf(caps[-1])
    # alongside, crossing to the left would cut across the car: it keeps to its own side,
    # too narrow as it is, and drops back behind the car
    (moved_upper, moved_lower), side, caps, _ = expert_bounds(0.4, -0.2, -0.12)
    assert side == -1 and not moved_lower.any() and moved_upper.min() < -0.1
    assert caps[0] < 1.0  # slower than the car: it drops back
    # alongside and ahead, it keeps to its side and never brakes for a car behind it
    (moved_upper, moved_lower), side, caps, _ = expert_bounds(-0.4, -0.2, -0.12)
    assert side == -1 and not moved_lower.any() and np.isinf(caps).all()


def test_the_expert_predicts_an_opponent_on_the_line_it_has_kept():
    expert = traffic_expert_on_the_straight()
    racing = expert.racing_line
    ahead = np.array([20.0, 30.0, 40.0])  # into the turns, where the racing line moves over
    # a second along s = 29-30 m, where the racing line moves 0.3 m across the lane
    s_values = 29.0 + np.linspace(0.0, 1.0, round(HISTORY_S / expert.settings.dt_s))
    on_racing = [NearOpponent("car1", s, float(racing.offset_at(s)) + 0.1, 1.0) for s in s_values]
    for opponent in on_racing:
        expert.remember(opponent)
    low, high = expert.predicted_band(on_racing[-1], ahead)
    np.testing.assert_allclose(low, racing.offset_at(ahead) + 0.1 - PREDICTION_MARGIN_M)
    np.testing.assert_allclose(high - low, 2.0 * PREDICTION_MARGIN_M)
    expert = traffic_expert_on_the_straight()
    steady = [NearOpponent("car1", s, 0.25, 1.0) for s in s_values]
    expert.remember(steady[0])  # a short history: between its line and the racing line's shape
    along_racing = racing.offset_at(ahead) + 0.25 - racing.offset_at(s_values[0])
    low, high = expert.predicted_band(steady[0], ahead)
    np.testing.assert_allclose(low, np.minimum(0.25, along_racing) - PREDICTION_MARGIN_M)
    np.testing.assert_allclose(high, np.maximum(0.25, along_racing) + PREDICTION_MARGIN_M)
    for opponent in steady:
        expert.remember(opponent)  # its offset from the centre line kept: on that line
    low, high = expert.predicted_band(steady[-1], ahead)
    np.testing.assert_allclose(low, 0.25 - PREDICTION_MARGIN_M)


def test_the_expert_forgets_an_opponent_out_of_reach():
    env = gym.make("saferace/RacingLine-v0", track=STRAIGHT_TRACK, opponents=[external(20.0)])
    expert = make_agent("expert", env)
    assert isinstance(expert, TrafficExpert)
    observation, info = env.reset(seed=0)
    expert._histories["car1"] = deque([(0.3, 0.3)] * 20, maxlen=20)  # from a lap before
    expert._sides["car1"] = 1
    info = {**info, "time_s": 1.0}  # not an episode's start
    expert.act(observation, info)  # car1 is 20 m ahead: out of reach
    assert "car1" not in expert._histories and "car1" not in expert._sides


def test_the_passing_side_is_the_ego_cars_own_if_it_has_room():
    assert passing_side(0.1, left_room_m=0.05, right_room_m=0.2) == 1
    assert passing_side(-0.1, left_room_m=0.05, right_room_m=0.2) == -1
    assert passing_side(0.1, left_room_m=-0.01, right_room_m=0.2) == -1
    assert passing_side(0.1, left_room_m=-0.01, right_room_m=-0.2) == 0


def test_a_car_at_rest_does_not_creep_into_a_car_stopped_ahead():
    env = SafetyFilter(
        gym.make(
            "saferace/CenterLine-v0",
            track=STRAIGHT_TRACK,
            opponents=[OpponentSpec("external", gap_m=0.6, speed_factor=0.01)],
        ),
        **GAIN_PRESETS["grip"],
    )
    env.reset(seed=0, options={"start_speed_mps": 0.0, "start_s_m": 3.0})
    collisions, infos = drive(env, np.array([0.0, 2.0]), {"car1": BRAKE}, steps=40)
    assert collisions == []
    assert infos[-1]["opponents"][0]["gap_m"] > 0.45  # the bumpers' length: never touched


def test_a_look_mounts_every_cars_onboard_cameras_alike():
    env = parallel_env(cars=2, track="lab", randomize="strong")
    model = env.env.model
    cameras = [model.camera(name).id for name in ("front_camera", "car1/front_camera")]
    built = model.cam_pos[cameras].copy(), model.cam_fovy[cameras].copy()
    env.reset(seed=3)
    moved = model.cam_pos[cameras] - built[0]
    assert np.abs(moved[0]).max() > 1e-4  # the look raised the ego's camera
    np.testing.assert_allclose(moved[1], moved[0])  # and car1's alike
    np.testing.assert_allclose(model.cam_fovy[cameras][1], model.cam_fovy[cameras][0])
    assert model.cam_fovy[cameras][0] != built[1][0]


def test_the_bumper_constants_are_the_models():
    model = gym.make("saferace/RacingLine-v0", track="lab").unwrapped.model
    np.testing.assert_allclose(model.geom("bumper").size[:2], RC10_BUMPER_HALF_EXTENTS_M)


def test_the_car_barriers_geometry_and_following_bound_in_numbers_worked_by_hand():
    from saferace.safety.traffic import car_barriers as cb

    length, width = RC10_BUMPER_HALF_EXTENTS_M
    for axis, half in ((cb.SEMI_AXIS_S_M, length), (cb.SEMI_AXIS_Y_M, width)):
        assert axis > 2.0 * half + cb.CAR_MARGIN_M - 1e-12  # wider than the two bumpers
    corner = ((2 * length) / (cb.SEMI_AXIS_S_M - cb.CAR_MARGIN_M)) ** cb.POWER + (
        (2 * width) / (cb.SEMI_AXIS_Y_M - cb.CAR_MARGIN_M)
    ) ** cb.POWER
    assert corner == pytest.approx(1.0)  # the bumpers' rectangle's corner on the curve
    params = param_values(load_params())
    state = np.array([0.0, 0.0, 2.0, 0.0])

    def h_at(ds: float, dy: float) -> tuple[float, float]:
        prediction = (ds, -dy, 1.0)
        _, _, h = car_rows("kinematic", params, state, 0.0, np.zeros(2), [prediction], CAR_GAINS)
        return float(h[0]), float(h[1])

    assert h_at(-cb.SEMI_AXIS_S_M, 0.0)[0] == pytest.approx(0.0, abs=1e-12)  # on the curve
    assert h_at(-2.0 * cb.SEMI_AXIS_S_M, 0.0)[0] == pytest.approx(2.0**cb.POWER - 1.0)
    assert h_at(0.0, cb.SEMI_AXIS_Y_M)[0] == pytest.approx(0.0, abs=1e-12)
    # following: 3 m behind a car at 1 m/s, the ego at 2 m/s along the track
    gap = 3.0 - cb.FOLLOW_GAP_M
    h_follow = gap - 0.5 * (2.0**2 / cb.EGO_BRAKE_MPS2 - 1.0**2 / cb.OPPONENT_ACCEL_MPS2)
    assert h_at(-3.0, 0.0)[1] == pytest.approx(h_follow)
    bound, h = cb._follow_row(-3.0, 0.0, 1.0, 2.0)
    assert h == pytest.approx(h_follow)
    assert bound == pytest.approx(cb.EGO_BRAKE_MPS2 * (cb.FOLLOW_GAIN * h_follow / 2.0 - 1.0))
    assert cb._follow_row(-3.0, cb.FOLLOW_WIDTH_M, 1.0, 2.0)[0] == cb.UNBOUNDED_ACCEL_MPS2
    assert cb._follow_row(3.0, 0.0, 1.0, 2.0)[0] == cb.UNBOUNDED_ACCEL_MPS2  # a car behind
    close = cb.FOLLOW_GAP_M + 0.01  # 1 cm past the standstill gap, both cars at rest
    standing = cb._follow_row(-close, 0.0, -1.0, 0.0)  # no speed counts below zero
    assert standing[1] == pytest.approx(0.01)
    assert standing[0] == pytest.approx(cb.EGO_BRAKE_MPS2 * (cb.FOLLOW_GAIN * 0.01 / 0.1 - 1.0))
    assert cb.along_track_mps(2.0, 0.0, 0.5, 0.4) == pytest.approx(2.5)  # inside a bend
    assert cb.along_track_mps(2.0, math.pi / 3, 0.0, 0.3) == pytest.approx(1.0)
    assert cb.along_track_mps(2.0, 0.0, 0.5, 3.0) == pytest.approx(20.0)  # stretch floor 0.1


def test_the_car_rows_of_two_opponents_are_each_cars_own_in_order():
    params = param_values(load_params())
    state = np.array([0.0, 0.0, 3.0, 0.0])
    near, far = (-2.0, 0.0, 1.0), (-20.0, 0.0, 1.0)
    one = [
        car_rows("kinematic", params, state, 0.0, np.zeros(2), [p], CAR_GAINS) for p in (near, far)
    ]
    a, b, h = car_rows("kinematic", params, state, 0.0, np.zeros(2), [near, far], CAR_GAINS)
    np.testing.assert_allclose(a, np.vstack([one[0][0], one[1][0]]))
    np.testing.assert_allclose(b, np.concatenate([one[0][1], one[1][1]]))
    np.testing.assert_allclose(h, np.concatenate([one[0][2], one[1][2]]))
    assert b[1] / CAR_ROW_WEIGHT < 0.0 < b[3]  # brake for the near car, not the far one


def test_the_car_barrier_assumes_hard_braking_only_of_a_moving_car_ahead_in_line():
    from saferace.safety.traffic import car_barriers as cb

    params = param_values(load_params())
    state = np.array([0.1, 0.05, 3.0, 0.0])  # 10 cm left, heading 0.05 rad
    axes = (cb.SEMI_AXIS_S_M, cb.SEMI_AXIS_Y_M)
    condition = cb._car_function("kinematic")

    def row_bound(prediction: tuple[float, float, float]) -> float:
        _, b, _ = car_rows("kinematic", params, state, 0.0, np.zeros(2), [prediction], CAR_GAINS)
        return float(b[0]) / CAR_ROW_WEIGHT

    def assuming(prediction: tuple[float, float, float], accel_mps2: float) -> float:
        ego = (*state, 0.0, 0.0, 0.0, *params)
        return float(condition(*ego, *prediction, accel_mps2, *axes, *CAR_GAINS)[0])

    in_line = (-1.5, 0.1, 2.0)
    beside = (-1.5, 0.1 - 1.01 * cb.SEMI_AXIS_Y_M, 2.0)  # just off its line, to the right
    for prediction, braking in (
        (in_line, True),
        ((-1.5, 0.1 - 0.99 * cb.SEMI_AXIS_Y_M, 2.0), True),  # still within the line
        (beside, False),
        ((1.5, 0.1, 2.0), False),  # behind the ego
        ((0.5, 0.1, 2.0), False),  # half a metre behind, overlapping
        ((-1.5, 0.1, 0.0), False),  # at rest: it cannot brake
        ((-1.5, 0.1, 0.5), True),  # slow, but still able to
    ):
        expected = assuming(prediction, -cb.OPPONENT_ACCEL_MPS2 if braking else 0.0)
        assert row_bound(prediction) == pytest.approx(expected), prediction
    assert assuming(in_line, -cb.OPPONENT_ACCEL_MPS2) != pytest.approx(assuming(in_line, 0.0))
    _, _, h = car_rows(
        "kinematic", params, state, 0.0, np.zeros(2), [(-axes[0], 0.1, 2.0)], CAR_GAINS
    )
    assert h[0] == pytest.approx(0.0, abs=1e-12)  # the ego's own offset, not its heading
