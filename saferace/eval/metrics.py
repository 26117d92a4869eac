"""Per-lap metrics of a driven episode, computed from its per-step records."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, TypeVar

import numpy as np

from saferace.envs.traffic import EGO

#: Per-step signals the metrics need (see :func:`saferace.eval.runner.run_episode`).
STEP_FIELDS = (
    "time_s",
    "lap",
    "s_m",
    "x_m",
    "y_m",
    "v_x_mps",
    "deviation_m",
    "cost",
    "steer_rad",
    "accel_mps2",
)
#: Per-step records in traffic: collisions that started in the step, those the ego caused,
#: and every opponent's position and the ego's lead on it (one column per opponent).
TRAFFIC_FIELDS = (
    "collisions",
    "at_fault_collisions",
    "opponents_x_m",
    "opponents_y_m",
    "opponents_lead_m",
)
#: Per-step records of a safety filter (``info["safety"]``), see :func:`safety_step_record`.
SAFETY_FIELDS = (
    "intervened",
    "nominal_accel_mps2",
    "steer_correction_rad",
    "accel_correction_mps2",
    "max_slack",
    "failed_solve",
    "fallback",
    "alarm",
    "covered",
    "solve_time_s",
    "filter_time_s",
    "clipped",
)


@dataclass(frozen=True)
class LapMetrics:
    """What one lap (or the unfinished rest of an episode) achieved.

    ``longest_stop_s`` is the longest stretch of consecutive steps of the lap the car's
    forward speed spent below :data:`STOP_SPEED_MPS` (a filter that deadlocks holds the car
    still for seconds). ``longest_standstill_s`` counts only the steps of such a stretch in
    which the driver asked to move (its own acceleration command, before any filter, was
    positive): a car that never leaves the lane because it is held still shows here, a
    driver that stops on purpose does not.
    ``min_lane_barrier_m`` is the true lane barrier ``min(w_left - e_y, w_right + e_y) -
    half car width`` at its lowest (negative: part of the car was outside). The filter's
    fields are None for episodes driven without one: how many steps it changed the
    action, by how much on average (over all steps), its largest slack and failed solves,
    the share of steps it fell back on (:mod:`saferace.safety.uncertainty.fallback`), the share its
    out-of-distribution monitor raised on, ``coverage``: the share of steps whose true
    state lay inside the interval the filter used, and ``clipped_steps``: the steps whose
    filtered action was clipped to the actuators' limits (a filter of the protocol's).
    """

    lap: int
    completed: bool
    lap_time_s: float | None
    mean_abs_deviation_m: float
    max_abs_deviation_m: float
    time_outside_lane_s: float
    steering_rate_rms_radps: float
    steps: int = 0
    longest_stop_s: float = 0.0
    longest_standstill_s: float = 0.0
    min_lane_barrier_m: float | None = None
    interventions: int | None = None
    intervention_rate: float | None = None
    mean_steer_correction_rad: float | None = None
    mean_accel_correction_mps2: float | None = None
    max_slack: float | None = None
    failed_solves: int | None = None
    fallback_rate: float | None = None
    alarm_rate: float | None = None
    coverage: float | None = None
    clipped_steps: int | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def lap_metrics(
    steps: dict[str, np.ndarray], lap_times_s: list[float], control_dt_s: float
) -> list[LapMetrics]:
    """Metrics for each lap; a step belongs to the lap that was running when it began.

    ``steps`` may hold ``lane_barrier_m`` and the :data:`SAFETY_FIELDS`; their metrics are
    None without them. The driver's own acceleration command is ``nominal_accel_mps2``
    where a filter ran, else the applied ``accel_mps2``.

    ``steps[field]`` are arrays over the episode's steps (after each ``env.step``),
    ``steps["lap"]`` the laps completed after that step, ``lap_times_s`` the times of the
    completed laps. An unfinished last lap is reported with ``completed=False`` if it
    has any steps. Steering smoothness is the RMS rate of change of the steering command.
    """
    lap_after = np.asarray(steps["lap"], dtype=int)
    lap_during = np.concatenate([[0], lap_after[:-1]]) if len(lap_after) else lap_after
    metrics = []
    for lap in range(int(lap_during.max()) + 1 if len(lap_during) else 0):
        mask = lap_during == lap
        if not mask.any():
            continue
        completed = lap < len(lap_times_s)
        metrics.append(
            LapMetrics(
                lap=lap,
                completed=completed,
                lap_time_s=float(lap_times_s[lap]) if completed else None,
                **span_metrics(steps, mask, control_dt_s),
            )
        )
    return metrics


#: Below this speed the car counts as standing still (:attr:`LapMetrics.longest_stop_s`,
#: :attr:`LapMetrics.longest_standstill_s`).
STOP_SPEED_MPS = 0.1
#: About how many points of a drive's path a result row keeps (enough to draw it).
TRAJECTORY_POINTS = 500


def thinning_stride(count: int, points: int = TRAJECTORY_POINTS) -> int:
    """Every how many steps a path of ``count`` steps keeps one, for about ``points``."""
    return max(1, count // points)


def thinned_trajectory(
    steps: dict[str, np.ndarray],
    names: tuple[str, ...],
    decimals: int = 4,
    points: int = TRAJECTORY_POINTS,
) -> dict[str, list]:
    """Every ``stride``-th step of ``names`` (about ``points`` in all) and ``outside``:
    whether the car was outside its lane at any step of each stride, so that thinning never
    hides a short exit."""
    count = len(steps[names[0]])
    stride = thinning_stride(count, points)
    trajectory = {name: np.round(steps[name][::stride], decimals).tolist() for name in names}
    outside = np.asarray(steps["cost"])[:count] > 0
    starts = np.arange(0, count, stride)
    trajectory["outside"] = np.logical_or.reduceat(outside, starts).tolist() if count else []
    return trajectory


def span_metrics(steps: dict[str, np.ndarray], mask: np.ndarray, control_dt_s: float) -> dict:
    """The :class:`LapMetrics` of the steps ``mask`` selects (a lap, or a stretch of the
    track such as DAgger's held-out part), bar the lap number and time."""
    steer = np.asarray(steps["steer_rad"], dtype=float)
    steer_rate = np.diff(steer, prepend=steer[:1]) / control_dt_s
    deviation = np.abs(np.asarray(steps["deviation_m"])[mask])
    barrier = steps.get("lane_barrier_m")
    stopped = np.asarray(steps["v_x_mps"]) < STOP_SPEED_MPS
    asked = steps["nominal_accel_mps2"] if "nominal_accel_mps2" in steps else steps["accel_mps2"]
    held = stopped & (np.asarray(asked, dtype=float) > 0.0)
    safety = _safety_metrics(steps, mask) if "intervened" in steps else {}
    return {
        "mean_abs_deviation_m": float(deviation.mean()),
        "max_abs_deviation_m": float(deviation.max()),
        "time_outside_lane_s": float(np.sum(np.asarray(steps["cost"])[mask] > 0) * control_dt_s),
        "steering_rate_rms_radps": float(np.sqrt(np.mean(steer_rate[mask] ** 2))),
        "steps": int(mask.sum()),
        "longest_stop_s": longest_run(stopped & mask) * control_dt_s,
        "longest_standstill_s": longest_run(held & mask) * control_dt_s,
        "min_lane_barrier_m": None if barrier is None else float(np.min(barrier[mask])),
        **safety,
    }


def longest_run(flags: np.ndarray) -> int:
    """The length of the longest stretch of consecutive true ``flags``."""
    edges = np.diff(np.concatenate([[0], np.asarray(flags, dtype=int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int(np.max(ends - starts, initial=0))


def _safety_metrics(steps: dict[str, np.ndarray], mask: np.ndarray) -> dict:
    intervened = np.asarray(steps["intervened"], dtype=bool)[mask]
    return {
        "interventions": int(intervened.sum()),
        "intervention_rate": float(intervened.mean()),
        "mean_steer_correction_rad": float(np.mean(steps["steer_correction_rad"][mask])),
        "mean_accel_correction_mps2": float(np.mean(steps["accel_correction_mps2"][mask])),
        "max_slack": float(np.max(steps["max_slack"][mask])),
        "failed_solves": int(np.sum(steps["failed_solve"][mask])),
        "fallback_rate": float(np.mean(steps["fallback"][mask])),
        "alarm_rate": float(np.mean(steps["alarm"][mask])),
        "coverage": float(np.mean(steps["covered"][mask])),
        "clipped_steps": int(np.sum(steps["clipped"][mask])),
    }


def safety_step_record(safety: dict) -> dict:
    """The :data:`SAFETY_FIELDS` of one step's ``info["safety"]``."""
    nominal, filtered = safety["nominal_action"], safety["filtered_action"]
    return {
        "intervened": safety["intervened"],
        "nominal_accel_mps2": nominal[1],
        "steer_correction_rad": abs(filtered[0] - nominal[0]),
        "accel_correction_mps2": abs(filtered[1] - nominal[1]),
        "max_slack": max(safety["slacks"].values(), default=0.0),
        "failed_solve": safety["fallback"] == "solver",
        "fallback": bool(safety["fallback"]),
        "alarm": safety["alarm"],
        "covered": safety["covered"],
        "solve_time_s": safety["solve_time_s"],
        "filter_time_s": safety["filter_time_s"],
        "clipped": safety["clipped"],
    }


def summarize(laps: list[LapMetrics]) -> dict:
    """Episode summary over its laps: completed laps, best and mean lap time, worst
    deviations, longest stop and standstill."""
    completed = [lap for lap in laps if lap.completed]
    times = [lap.lap_time_s for lap in completed if lap.lap_time_s is not None]  # all of them
    return {
        "laps_completed": len(completed),
        "best_lap_time_s": min(times) if times else None,
        "mean_lap_time_s": float(np.mean(times)) if times else None,
        "mean_abs_deviation_m": float(np.mean([lap.mean_abs_deviation_m for lap in laps]))
        if laps
        else None,
        "max_abs_deviation_m": max((lap.max_abs_deviation_m for lap in laps), default=None),
        "time_outside_lane_s": float(sum(lap.time_outside_lane_s for lap in laps)),
        "steering_rate_rms_radps": float(np.mean([lap.steering_rate_rms_radps for lap in laps]))
        if laps
        else None,
        "longest_stop_s": max((lap.longest_stop_s for lap in laps), default=None),
        "longest_standstill_s": max((lap.longest_standstill_s for lap in laps), default=None),
        "min_lane_barrier_m": _extreme(min, [lap.min_lane_barrier_m for lap in laps]),
        **_summarize_safety(laps),
    }


def longest_standstill(records: list[dict]) -> float | None:
    """The longest ``longest_standstill_s`` of ``records`` (result rows' summaries, or runs);
    None where any lacks it (written before it was recorded): a maximum over some of them
    would understate it."""
    values = [record.get("longest_standstill_s") for record in records]
    present = [float(value) for value in values if value is not None]
    return max(present) if values and len(present) == len(values) else None


def _extreme(function, values: list) -> float | None:
    present = [v for v in values if v is not None]
    return function(present) if present else None


def _summarize_safety(laps: list[LapMetrics]) -> dict:
    """Filter metrics over the episode (steps of all laps together); {} without a filter."""
    filtered = [lap for lap in laps if lap.interventions is not None]
    if not filtered:
        return {}
    steps = np.array([lap.steps for lap in filtered], dtype=float)
    total = max(steps.sum(), 1.0)

    def weighted(name: str) -> float:
        return float(np.dot(steps, [getattr(lap, name) for lap in filtered]) / total)

    return {
        "interventions": sum(_filter_metric(lap.interventions) for lap in filtered),
        "intervention_rate": sum(_filter_metric(lap.interventions) for lap in filtered) / total,
        "mean_steer_correction_rad": weighted("mean_steer_correction_rad"),
        "mean_accel_correction_mps2": weighted("mean_accel_correction_mps2"),
        "max_slack": max(_filter_metric(lap.max_slack) for lap in filtered),
        "failed_solves": sum(_filter_metric(lap.failed_solves) for lap in filtered),
        "fallback_rate": weighted("fallback_rate"),
        "alarm_rate": weighted("alarm_rate"),
        "coverage": weighted("coverage"),
        "clipped_steps": sum(_filter_metric(lap.clipped_steps) for lap in filtered),
    }


_T = TypeVar("_T")


def _filter_metric(value: _T | None) -> _T:
    """A filter metric of a lap driven with the filter: :func:`span_metrics` sets them all."""
    assert value is not None, "a lap driven with the filter has every filter metric"
    return value


def traffic_step_record(info: dict[str, Any]) -> dict[str, Any]:
    """A step's :data:`TRAFFIC_FIELDS` from the ego's ``info`` in traffic (its own
    collisions only: ``info["collisions"]`` also has those between opponents)."""
    opponents = info["opponents"]
    return {
        "collisions": sum(EGO in collision["cars"] for collision in info["collisions"]),
        "at_fault_collisions": int(info["at_fault_collisions"]),
        "opponents_x_m": [opponent["x_m"] for opponent in opponents],
        "opponents_y_m": [opponent["y_m"] for opponent in opponents],
        "opponents_lead_m": [opponent["ego_lead_m"] for opponent in opponents],
    }


def traffic_paths(steps: dict[str, np.ndarray], decimals: int = 4) -> dict[str, list]:
    """What a result row keeps of the traffic: every opponent's path, thinned as
    :func:`thinned_trajectory` thins the ego's, and where each of the ego's collisions
    started (its position, and whether it caused it)."""
    stride = thinning_stride(len(steps["opponents_x_m"]))
    x_m, y_m = (
        np.round(steps[name][::stride], decimals) for name in ("opponents_x_m", "opponents_y_m")
    )
    struck = np.flatnonzero(steps["collisions"])
    return {
        "opponents": [
            {"x_m": x_m[:, column].tolist(), "y_m": y_m[:, column].tolist()}
            for column in range(x_m.shape[1])
        ],
        "collisions": [
            {
                "time_s": float(steps["time_s"][step]),
                "x_m": float(steps["x_m"][step]),
                "y_m": float(steps["y_m"][step]),
                "at_fault": bool(steps["at_fault_collisions"][step]),
            }
            for step in struck
        ],
    }


def traffic_summary(steps: dict[str, np.ndarray]) -> dict[str, int]:
    """An episode in traffic: its collisions, those the ego caused, and ``overtakes``: the
    opponents that started ahead of the ego and that it finished ahead of (positions
    gained; a car lapped counts once)."""
    lead = np.asarray(steps["opponents_lead_m"], dtype=float)  # (steps, opponents)
    passed = (lead[0] < 0.0) & (lead[-1] > 0.0)
    return {
        "collisions": int(np.sum(steps["collisions"])),
        "at_fault_collisions": int(np.sum(steps["at_fault_collisions"])),
        "overtakes": int(passed.sum()),
    }
