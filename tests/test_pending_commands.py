"""Actuators that apply commands late: the delay told from the yaw rate on recorded drives,
the lane states a late command meets carried by hand, and a car kept in its lane behind
the filter where, certified on the present state, it left it."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig
from saferace.eval.runner import make_task_env, max_steps_for, run_episode
from saferace.faults.wrapper import SensorFaults
from saferace.safety.uncertainty import pending_commands
from saferace.safety.uncertainty.estimate import StateEstimate
from saferace.safety.uncertainty.pending_commands import PendingCommands

CONTROL_DT_S = 0.05
WHEELBASE_M = 0.33
MAX_STEER_RATE_RADPS = 6.0  # the rc10's servo (saferace.envs.drivetrain)


def robust_filter_env(track: str, faults: list[str], seconds: float) -> gym.Env:
    """``track`` with ``faults`` behind the robust filter fed the true state."""
    safety = FilterConfig(kind="cbf", uncertainty="robust", gains="tuned-grip", map_curvature=True)
    return make_task_env(
        "CenterLine", track, 1, safety, 0, max_steps=max_steps_for(seconds), faults=faults
    )


@pytest.mark.parametrize(
    ("track", "delay", "steps"),
    [
        ("oval", "delay:steps=3", 3),
        ("technical", "delay:steps=2", 2),
        ("lab", "delay:start=100,steps=3", 0),
    ],
)
def test_behind_the_filter_the_delay_and_the_offset_are_told_from_the_yaw_rate(
    track: str, delay: str, steps: int
):
    env = robust_filter_env(track, ["steering:offset=0.03", delay], seconds=8.0)
    run_episode(env, make_agent("expert", env, seed=0), seed=0)
    judge = env.steering_trim  # type: ignore[attr-defined]
    env.close()
    assert judge.max_delay_steps == 3 - (track == "technical")  # the declared bound
    assert judge.delay_steps == steps
    assert judge.estimate_rad == pytest.approx(0.03, abs=0.006)


def estimate(lower: list[float], upper: list[float]) -> StateEstimate:
    mean = 0.5 * (np.array(lower) + np.array(upper))
    return StateEstimate(
        samples=mean[None], mean=mean, std=np.zeros(3), lower=np.array(lower),
        upper=np.array(upper), monitor_score=0.0, alarm=False, map_curvature=None,
        bounded=True, stale=False,
    )  # fmt: skip


def test_a_box_is_carried_through_the_commands_in_the_pipe_worked_by_hand():
    pipe = PendingCommands(2, CONTROL_DT_S, WHEELBASE_M, curvature_at=lambda s_m: 0.0)
    steer_rad = 0.1
    pipe.record(steer_rad, 2.0)
    pipe.record(steer_rad, 2.0)
    box = estimate([-0.1, 0.0, 0.0], [0.1, 0.0, 0.0])
    met, velocity, s_m = pipe.meet(box, np.array([4.0, 0.0, 0.0]), 10.0, delay_steps=2)
    yaw_rate = math.tan(steer_rad) / WHEELBASE_M  # per m/s
    e_psi_1 = 4.0 * yaw_rate * CONTROL_DT_S  # the heading after the first command
    e_y = 4.1 * math.sin(e_psi_1) * CONTROL_DT_S  # the second step's sideways drift, at 4.1 m/s
    assert met.lower[:2] == pytest.approx([-0.1 + e_y, e_psi_1 + 4.1 * yaw_rate * CONTROL_DT_S])
    assert met.upper[0] == pytest.approx(0.1 + e_y)
    assert velocity[0] == pytest.approx(4.2)
    assert s_m == pytest.approx(10.0 + (4.0 + 4.1 * math.cos(e_psi_1)) * CONTROL_DT_S)
    hull, _, s_now = pipe.meet(box, np.array([4.0, 0.0, 0.0]), 10.0, delay_steps=0)
    assert hull.lower[0] == -0.1 and hull.upper[0] == pytest.approx(0.1 + e_y)  # every delay
    assert s_now == 10.0  # where the judged delay, none, leaves it


def test_without_a_declared_delay_nothing_is_carried():
    env = gym.make("saferace/CenterLine-v0", track="lab", image_size=(16, 16))
    pipe = PendingCommands.of_task(env, CONTROL_DT_S, WHEELBASE_M)
    pipe.record(0.3, 4.0)
    box = estimate([-0.1, -0.1, 0.5], [0.1, 0.1, 0.5])
    assert pipe.meet(box, np.array([4.0, 0.0, 0.0]), 3.0, delay_steps=3)[0] is box
    faulty = SensorFaults(env, ["delay:severity=2"])
    assert PendingCommands.of_task(faulty, CONTROL_DT_S, WHEELBASE_M).max_delay_steps == 2
    env.close()


def outside_s(monkeypatch: pytest.MonkeyPatch, declared: bool) -> float:
    """Seconds outside the lane of the expert on oval, its actuators 150 ms late from 3 s,
    behind the robust filter fed the true state (declaring the delay, or not)."""
    if not declared:
        real = PendingCommands.of_task.__func__  # type: ignore[attr-defined]
        monkeypatch.setattr(
            pending_commands.PendingCommands, "of_task",
            classmethod(lambda cls, env, dt, wheelbase: real(cls, env.unwrapped, dt, wheelbase)),
        )  # fmt: skip
    env = robust_filter_env("oval", ["delay:start=3,steps=3"], seconds=20.0)
    result = run_episode(env, make_agent("expert", env, seed=0), seed=0)
    env.close()
    return result.summary["time_outside_lane_s"]


def test_the_filter_meets_late_commands_where_they_land(monkeypatch: pytest.MonkeyPatch):
    assert outside_s(monkeypatch, declared=True) == 0.0
    assert outside_s(monkeypatch, declared=False) > 0.1  # certified on the present state
