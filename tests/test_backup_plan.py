"""The filter's backup plan (saferace.safety.cbf.backup): its clearance on a plain lane, the
action it sends instead, and a chicane where the lane barriers alone let the expert out."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig
from saferace.eval.runner import make_task_env, run_episode
from saferace.safety.cbf import backup
from saferace.safety.cbf.backup import BACKUP_BRAKE_MPS2, BackupPlan, PlanState
from saferace.safety.cbf.filter import SafetyFilter
from saferace.track import Track
from saferace.track.raceline import center_line

WHEELBASE_M, HALF_WIDTH_M = 0.33, 0.2


def write_chicane(path: Path, peak_radpm: float = 0.85, span_m: float = 3.0) -> Path:
    """A closed track of two 60 m straights and two 6 m turns, each straight with a jog at
    its middle: the centre line turns ``peak_radpm`` one way over ``span_m``, then back (a
    lateral step of about 3 m in a 2.2 m lane, like Monza's first chicane as the F1TENTH
    file gives it)."""
    step_m = 0.05

    def straight() -> np.ndarray:
        s = np.arange(0.0, 60.0, step_m)
        kappa = np.zeros_like(s)
        for start, sign in ((30.0 - span_m, 1.0), (30.0, -1.0)):
            inside = (s >= start) & (s < start + span_m)
            phase = 2.0 * np.pi * (s[inside] - start) / span_m
            kappa[inside] = sign * peak_radpm * 0.5 * (1.0 - np.cos(phase))
        return kappa

    turn = np.full(int(np.pi * 6.0 / step_m), 1.0 / 6.0)
    heading = np.cumsum(np.concatenate([straight(), turn, straight(), turn])) * step_m
    x, y = np.cumsum(np.cos(heading)) * step_m, np.cumsum(np.sin(heading)) * step_m
    share = np.arange(len(x)) / len(x)  # close the loop's few millimetres of error
    x -= share * (x[-1] + np.cos(heading[-1]) * step_m)
    y -= share * (y[-1] + np.sin(heading[-1]) * step_m)
    rows = [f"{a:.4f}, {b:.4f}, 1.1, 1.1" for a, b in zip(x[::4], y[::4], strict=True)]
    path.write_text("# x_m, y_m, w_tr_right_m, w_tr_left_m\n" + "\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="module")
def plan() -> BackupPlan:
    track = Track.load("oval")
    return BackupPlan(track, center_line(track), WHEELBASE_M, 0.05, 0.35, HALF_WIDTH_M, 0.05)


def test_a_car_on_the_centre_line_keeps_its_room_and_one_heading_out_fast_does_not(plan):
    slow = PlanState(s_m=1.0, e_y_m=0.0, e_psi_rad=0.0, v_mps=1.0, steer_rad=0.0)
    room = plan.clearance(slow, None, 0.0)
    right, left = Track.load("oval").widths(np.array([1.0]))
    assert room == pytest.approx(min(left[0], right[0]) - HALF_WIDTH_M, abs=0.05)
    assert plan.clearance(slow, None, 0.3) == pytest.approx(room - 0.3, abs=1e-9)
    heading_out = PlanState(s_m=1.0, e_y_m=0.3, e_psi_rad=math.pi / 4, v_mps=6.0, steer_rad=0.0)
    assert plan.clearance(heading_out, None, 0.0) < 0.0


def test_the_backup_steps_in_only_where_the_action_keeps_less_room(plan):
    cruising = PlanState(s_m=1.0, e_y_m=0.0, e_psi_rad=0.0, v_mps=3.0, steer_rad=0.0)
    assert plan.instead(cruising, np.array([0.0, 0.5]), 0.0) is None
    drifting = PlanState(s_m=1.0, e_y_m=0.4, e_psi_rad=0.25, v_mps=4.0, steer_rad=0.0)
    worse = np.array([0.3, 2.0])  # turning further out and speeding up
    assert plan.clearance(drifting, (0.3, 2.0), 0.0) < plan.clearance(drifting, None, 0.0)
    backup = plan.instead(drifting, worse, 0.0)
    assert backup is not None
    assert backup[0] < 0.0 and -BACKUP_BRAKE_MPS2 <= backup[1] < 0.0  # back in, braking


def test_braking_in_a_turn_at_the_grip_is_refused_for_the_backup(plan):
    """A hard turn at speed with full braking spins this car: its plan does not model that,
    so the backup (braking within the friction circle) is sent instead."""
    cornering = PlanState(s_m=1.0, e_y_m=0.0, e_psi_rad=0.0, v_mps=6.0, steer_rad=0.1)
    assert plan.instead(cornering, np.array([0.1, -4.0]), 0.0) is not None
    assert plan.instead(cornering, np.array([0.1, 0.0]), 0.0) is None
    assert plan.brake_mps2(6.0, 0.1) < plan.brake_mps2(6.0, 0.0) == BACKUP_BRAKE_MPS2


@pytest.mark.parametrize("backup", [False, True])
def test_the_expert_leaves_a_chicane_behind_the_barriers_alone_and_not_with_the_backup(
    tmp_path: Path, backup: bool
):
    """The default filter's barriers push the expert off its racing line before the jog,
    and at 7 m/s the tyres cannot follow the jog from there: it leaves. With the backup
    plan it brakes in time and laps inside."""
    track = write_chicane(tmp_path / "chicane.csv")
    env = make_task_env("RacingLine", str(track), 1, FilterConfig(kind="cbf"), 0)
    wrapper = env
    while not isinstance(wrapper, SafetyFilter):
        wrapper = wrapper.env
    if not backup:
        wrapper.backup = None
    try:
        result = run_episode(env, make_agent("expert", env, seed=0), seed=0)
    finally:
        env.close()
    outside_s = result.summary["time_outside_lane_s"]
    if backup:
        assert outside_s == 0.0 and result.summary["laps_completed"] == 1
    else:
        assert outside_s > 0.0


def test_the_plan_turns_no_tighter_than_the_grip_whatever_the_wheels_ask(plan):
    """At 6 m/s a hard lock and the steering at 7 m/s^2 of grip turn the car alike in the
    plan: the kinematic bicycle would turn tighter, the tyres slide instead."""
    at_grip = math.atan(7.0 * WHEELBASE_M / 6.0**2)
    room = [
        plan.clearance(PlanState(1.0, 0.0, 0.5, 6.0, -steer), (-steer, 0.0), 0.0)
        for steer in (0.35, at_grip)
    ]
    assert room[0] == pytest.approx(room[1], abs=0.05)


def test_two_plan_steps_a_period_follow_a_chicane_as_forty_do(tmp_path, monkeypatch):
    """At 6.5 m/s a plan step covers 16 cm, and the chicane's curvature swings across 3 m:
    read where the step starts, the lane turns late in the plan, which then claims room the
    car does not have (13 cm at the jog). Read mid-step, the plan keeps within 6 cm of a
    fine one."""
    track = Track.load(str(write_chicane(tmp_path / "chicane.csv")))

    def room(substeps: int, s_m: float) -> float:
        monkeypatch.setattr(backup, "SUBSTEPS", substeps)
        plan = BackupPlan(track, center_line(track), WHEELBASE_M, 0.05, 0.35, HALF_WIDTH_M, 0.05)
        return plan.clearance(PlanState(s_m, 0.0, 0.0, 6.5, 0.0), (0.0, 0.0), 0.0)

    errors_m = [abs(room(2, s_m) - room(40, s_m)) for s_m in (24.0, 25.0, 26.0, 27.0, 28.0)]
    assert max(errors_m) < 0.06
