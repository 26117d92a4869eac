"""Invariants over every registered task: API conformance, determinism, pickling, scenes."""

from __future__ import annotations

import gc
import pickle
import weakref

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import saferace  # noqa: F401  - registers the tasks
from saferace.envs import views
from saferace.errors import SafeRaceError
from saferace.eval.filters import FilterConfig, apply_filter
from saferace.names import FILTER_KINDS, TRAFFIC_TASK_IDS
from saferace.registry import TASKS
from saferace.track import Track, builtin_track_names

TASK_IDS = sorted(TASKS)


def assert_same(a, b) -> None:
    """Observations and infos equal to the bit."""
    if isinstance(a, tuple | list):
        assert len(a) == len(b)
        for item_a, item_b in zip(a, b, strict=True):
            assert_same(item_a, item_b)
    elif isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_same(a[key], b[key])
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b)
    else:
        assert a == b


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_env_checker(task_id: str):
    env = gym.make(task_id, track="lab", render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    env.close()


@pytest.mark.parametrize("kind", [kind for kind in FILTER_KINDS if kind != "none"])
@pytest.mark.parametrize("task_id", TASK_IDS)
def test_env_checker_passes_behind_every_filter_family(task_id: str, kind: str):
    """What Stable-Baselines3 users check before they train: the wrapped task is a valid
    gymnasium env, its info (the filter's decision) the same for the same seed and actions."""
    env = apply_filter(gym.make(task_id, track="lab", image_size=(32, 32)), FilterConfig(kind))
    check_env(env, skip_render_check=True)
    env.close()


def test_closing_or_dropping_one_env_leaves_anothers_frames_intact():
    """Each env renders in a GL context of its own, and MuJoCo frees a renderer's
    framebuffer by its GL name in whichever context is current: an env closed, or collected
    unclosed, while another's context was current deleted that env's framebuffer (its
    frames garbage from then on; the env checker caught it as two different first steps)."""

    def make() -> gym.Env:
        return gym.make(TASK_IDS[0], track="lab", image_size=(32, 32))

    kept, closed, dropped = make(), make(), make()
    closed.reset(seed=0)
    dropped.reset(seed=0)
    before = kept.reset(seed=0)[0]["image"]  # kept's context is the current one
    closed.close()
    assert np.array_equal(kept.reset(seed=0)[0]["image"], before)
    dropped_views = weakref.ref(dropped.unwrapped._views)
    del dropped
    gc.collect()
    assert dropped_views() is None  # collected: its renderers are queued to close
    assert np.array_equal(kept.reset(seed=0)[0]["image"], before)
    assert not views._DROPPED  # and closed, at the render's start
    kept.close()


def test_a_filters_record_keeps_its_clock_times_only_when_asked():
    env = apply_filter(gym.make(TASK_IDS[0], track="lab", image_size=(32, 32)), FilterConfig("cbf"))
    env.reset(seed=0)
    untimed = env.step(np.zeros(2))[-1]["safety"]
    timed_env = apply_filter(
        gym.make(TASK_IDS[0], track="lab", image_size=(32, 32)), FilterConfig("cbf"), timed=True
    )
    timed_env.reset(seed=0)
    timed = timed_env.step(np.zeros(2))[-1]["safety"]
    assert untimed["solve_time_s"] == untimed["filter_time_s"] == 0.0
    assert 0.0 < timed["solve_time_s"] <= timed["filter_time_s"]
    env.close()
    timed_env.close()


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_same_seed_same_episode(task_id: str):
    envs = [gym.make(task_id, track="technical", random_start=True) for _ in range(2)]
    actions = gym.spaces.Box(envs[0].action_space.low, envs[0].action_space.high, seed=3)
    resets = [env.reset(seed=7) for env in envs]
    assert_same(resets[0], resets[1])
    for _ in range(200):
        action = actions.sample() * np.array([0.3, 1.0], np.float32)
        results = [env.step(action) for env in envs]
        assert_same(results[0], results[1])
        if results[0][2] or results[0][3]:
            assert_same(envs[0].reset(), envs[1].reset())
    for env in envs:
        env.close()


def test_different_seeds_differ_with_random_start():
    env = gym.make("saferace/CenterLine-v0", track="lab", random_start=True)
    starts = {round(env.reset(seed=seed)[1]["s_m"], 6) for seed in range(5)}
    assert len(starts) == 5
    env.close()


#: Opponents whose drivers a pickle restores to the bit (the expert's QP warm start is not).
RESTORABLE_OPPONENTS = [
    "pure-pursuit:gap_m=2",
    "lane-changer:gap_m=5",
    "blocker:gap_m=8",
    "braking",
]


def pickled_and_stepped(task_id: str, **kwargs):
    """An env stepped 20 times and its pickled clone, both stepped 30 more: their results."""
    env = gym.make(task_id, track="varying", **kwargs).unwrapped
    env.reset(seed=1)
    for _ in range(20):
        env.step(np.array([0.05, 1.0]))
    clone = pickle.loads(pickle.dumps(env))
    results = []
    for step in range(30):
        action = np.array([0.1 * np.sin(step / 5.0), 0.5])
        results.append((env.step(action), clone.step(action)))
    env.close()
    clone.close()
    return results


@pytest.mark.parametrize("task_id", TASK_IDS)
def test_pickle_round_trip_continues_identically(task_id: str):
    kwargs = {"opponents": RESTORABLE_OPPONENTS} if task_id in TRAFFIC_TASK_IDS.values() else {}
    for original, clone in pickled_and_stepped(task_id, **kwargs):
        assert_same(original, clone)


@pytest.mark.parametrize("opponent", ["expert:gap_m=2", "racer:gap_m=-0.7"])
def test_pickled_mpc_opponent_continues_to_the_solvers_tolerance(opponent: str):
    results = pickled_and_stepped("saferace/Overtake-v0", opponents=[opponent])
    for original, clone in results:
        opponents = zip(original[4]["opponents"], clone[4]["opponents"], strict=True)
        cars = [(original[4], clone[4]), *opponents]
        for mine, theirs in cars:
            assert np.hypot(mine["x_m"] - theirs["x_m"], mine["y_m"] - theirs["y_m"]) < 0.01


def test_a_pickled_racer_remembers_the_cars_it_saw():
    env = gym.make("saferace/Overtake-v0", track="varying", opponents=["racer:gap_m=-0.7"])
    env.unwrapped.reset(seed=1)
    for _ in range(20):
        env.unwrapped.step(np.array([0.05, 1.0]))
    racer = env.unwrapped.traffic.cars[0].policy
    assert racer._histories["car0"]  # the ego ahead, within its reach
    twin = pickle.loads(pickle.dumps(env.unwrapped)).traffic.cars[0].policy
    assert list(twin._histories["car0"]) == list(racer._histories["car0"])
    assert (twin._sides, twin._given_up) == (racer._sides, racer._given_up)


@pytest.mark.parametrize("track", [*builtin_track_names(), "unseen"])
def test_scene_runs_ten_seconds_of_random_actions_without_warnings(track: str, unseen_track_csv):
    env = gym.make(
        "saferace/CenterLine-v0", track=str(unseen_track_csv) if track == "unseen" else track
    )
    base = env.unwrapped
    env.reset(seed=0)
    env.action_space.seed(0)
    steps = round(10.0 / base.control_dt_s)
    warnings = 0
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            warnings += sum(w.number for w in base.data.warning)  # a reset zeroes them
            env.reset()
    warnings += sum(w.number for w in base.data.warning)
    assert warnings == 0
    env.close()


@pytest.mark.parametrize("track", builtin_track_names())
def test_boundary_lines_visible_left_and_right_at_the_start(track: str):
    env = gym.make("saferace/CenterLine-v0", track=track)
    observation, _ = env.reset(seed=0)
    image = observation["image"]
    white = np.all(image > 200, axis=2)
    white[: image.shape[0] // 3] = False  # sky and far field
    columns = np.flatnonzero(white.any(axis=0))
    center = image.shape[1] / 2
    assert (columns < center).any() and (columns > center).any()
    env.close()


def test_stereo_gives_two_different_views_with_lines():
    env = gym.make("saferace/CenterLine-v0", track="oval", stereo=True)
    observation, _ = env.reset(seed=0)
    image = observation["image"]
    assert image.shape == (64, 64, 6)
    left, right = image[..., :3], image[..., 3:]
    assert np.mean(np.abs(left.astype(int) - right.astype(int))) > 1.0
    for view in (left, right):
        assert np.all(view > 200, axis=2)[20:].sum() > 20
    env.close()


def test_observation_and_info_are_consistent():
    env = gym.make("saferace/RacingLine-v0", track="technical", image_size=(48, 80))
    observation, info = env.reset(seed=0)
    assert observation["image"].shape == (48, 80, 3)
    assert info["v_x_mps"] == pytest.approx(info["ref_speed_mps"], rel=1e-3)
    assert info["deviation_m"] == pytest.approx(0.0, abs=1e-6)
    _, reward, _, _, info = env.step(np.array([0.0, 0.0]))
    assert reward == pytest.approx(info["reward_progress"] + info["reward_deviation"])
    assert info["reward_progress"] == pytest.approx(info["progress_m"])
    assert observation["velocity"].dtype == np.float32
    env.close()


def test_car_leaving_the_lane_costs_then_terminates():
    env = gym.make("saferace/CenterLine-v0", track="oval")
    env.reset(seed=0)
    costs, terminated, info = [], False, {}
    while not terminated:
        _, _, terminated, truncated, info = env.step(np.array([0.36, 0.0]))
        costs.append(info["cost"])
        assert not truncated
    half = 0.15
    assert info["e_y_m"] - half > info["w_left_m"]  # the whole car is out on the left
    assert costs[0] == 0.0 and costs[-1] == 1.0
    env.close()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(image_size=(4, 64)), "image_size"),
        (dict(control_hz=0.5), "control_hz"),
        (dict(max_laps=0), "max_laps"),
        (dict(track="nowhere"), "unknown track"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, message):
    with pytest.raises(SafeRaceError, match=message):
        gym.make("saferace/CenterLine-v0", **kwargs)


def test_unsupported_render_mode_is_rejected():
    from saferace.envs.racing_env import CenterLineEnv

    with pytest.raises(SafeRaceError, match="render_mode"):
        CenterLineEnv(track="oval", render_mode="human")


def test_bad_actions_raise():
    env = gym.make("saferace/CenterLine-v0", track="lab")
    env.reset(seed=0)
    with pytest.raises(SafeRaceError, match="finite"):
        env.step(np.array([np.nan, 0.0]))
    with pytest.raises(SafeRaceError, match="steer_rad, accel_mps2"):
        env.step(np.array([0.1, 0.2, 0.3]))
    env.close()


def test_gym_make_with_module_prefix_imports_saferace():
    import subprocess
    import sys

    code = (
        "import gymnasium as gym\n"
        "env = gym.make('saferace:saferace/CenterLine-v0', track='oval')\n"
        "print(env.spec.id)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert result.stdout.strip() == "saferace/CenterLine-v0"


@pytest.mark.parametrize("track", builtin_track_names())
def test_every_model_element_is_named(track: str):
    import mujoco

    from saferace.envs.scene import build_model
    from saferace.track import Track

    model = build_model(Track.load(track))
    kinds = {
        mujoco.mjtObj.mjOBJ_BODY: model.nbody,
        mujoco.mjtObj.mjOBJ_JOINT: model.njnt,
        mujoco.mjtObj.mjOBJ_GEOM: model.ngeom,
        mujoco.mjtObj.mjOBJ_CAMERA: model.ncam,
        mujoco.mjtObj.mjOBJ_ACTUATOR: model.nu,
        mujoco.mjtObj.mjOBJ_SENSOR: model.nsensor,
        mujoco.mjtObj.mjOBJ_LIGHT: model.nlight,
        mujoco.mjtObj.mjOBJ_SITE: model.nsite,
    }
    for kind, count in kinds.items():
        names = [mujoco.mj_id2name(model, kind, i) for i in range(count)]
        unnamed = [
            i
            for i, name in enumerate(names)
            if not name and not (kind == mujoco.mjtObj.mjOBJ_BODY and i == 0)
        ]
        assert not unnamed, f"unnamed {kind.name}: {unnamed}"
    assert {model.camera(i).name for i in range(model.ncam)} == {
        "front_camera",
        "stereo_left",
        "stereo_right",
        "chase_camera",
    }


def test_only_the_four_tyres_touch_the_ground():
    env = gym.make("saferace/CenterLine-v0", track="oval")
    model, data = env.unwrapped.model, env.unwrapped.data
    tyres = {f"{wheel}_tyre" for wheel in ("front_left", "front_right", "rear_left", "rear_right")}

    def touching() -> set[str]:
        return {model.geom(data.contact[i].geom2).name for i in range(data.ncon)}

    env.reset(seed=0, options={"start_speed_mps": 0.0})
    for _ in range(10):
        env.step(np.array([0.0, 0.0]))
    assert touching() == tyres  # at rest, all four
    for step in range(60):
        env.step(np.array([0.3 * np.sin(step / 4.0), 2.0]))
        assert touching() <= tyres  # driving, never anything else
    env.close()


def test_envs_on_one_geometry_share_its_reference_lines():
    """A racing line is computed once per track geometry in a process, not once per env."""
    first = gym.make("saferace/RacingLine-v0", track="oval")
    again = gym.make("saferace/RacingLine-v0", track=Track.load("oval"))
    other = gym.make("saferace/RacingLine-v0", track="lab")
    center = gym.make("saferace/CenterLine-v0", track="oval")
    assert first.unwrapped.reference is again.unwrapped.reference
    assert other.unwrapped.reference is not first.unwrapped.reference
    assert center.unwrapped.reference.name == "center"
    for env in (first, again, other, center):
        env.close()


def test_the_wheels_follow_the_steering_target_with_the_servos_lag():
    env = gym.make("saferace/CenterLine-v0", track="oval", image_size=(16, 16))
    _, info = env.reset(seed=0)
    assert info["steer_angle_rad"] == pytest.approx(0.0, abs=1e-6)
    angles = []
    for _ in range(6):
        _, _, _, _, info = env.step(np.array([0.2, 0.0]))
        angles.append(info["steer_angle_rad"])
    env.close()
    assert info["steer_rad"] == pytest.approx(0.2)
    assert 0.05 < angles[0] < 0.17  # a control step is about one time constant of the servo
    assert angles[-1] == pytest.approx(0.2, abs=0.01)
