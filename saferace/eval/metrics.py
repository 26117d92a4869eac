"""Per-lap metrics of a driven episode, computed from its per-step records."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

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


@dataclass(frozen=True)
class LapMetrics:
    """What one lap (or the unfinished rest of an episode) achieved."""

    lap: int
    completed: bool
    lap_time_s: float | None
    mean_abs_deviation_m: float
    max_abs_deviation_m: float
    time_outside_lane_s: float
    steering_rate_rms_radps: float

    def as_dict(self) -> dict:
        return asdict(self)


def lap_metrics(
    steps: dict[str, np.ndarray], lap_times_s: list[float], control_dt_s: float
) -> list[LapMetrics]:
    """Metrics for each lap; a step belongs to the lap that was running when it began.

    ``steps[field]`` are arrays over the episode's steps (after each ``env.step``),
    ``steps["lap"]`` the laps completed after that step, ``lap_times_s`` the times of the
    completed laps. An unfinished last lap is reported with ``completed=False`` if it
    has any steps. Steering smoothness is the RMS rate of change of the steering command.
    """
    lap_after = np.asarray(steps["lap"], dtype=int)
    lap_during = np.concatenate([[0], lap_after[:-1]]) if len(lap_after) else lap_after
    steer = np.asarray(steps["steer_rad"], dtype=float)
    steer_rate = np.diff(steer, prepend=steer[:1]) / control_dt_s if len(steer) else steer
    metrics = []
    for lap in range(int(lap_during.max()) + 1 if len(lap_during) else 0):
        mask = lap_during == lap
        if not mask.any():
            continue
        deviation = np.abs(np.asarray(steps["deviation_m"])[mask])
        completed = lap < len(lap_times_s)
        metrics.append(
            LapMetrics(
                lap=lap,
                completed=completed,
                lap_time_s=float(lap_times_s[lap]) if completed else None,
                mean_abs_deviation_m=float(deviation.mean()),
                max_abs_deviation_m=float(deviation.max()),
                time_outside_lane_s=float(
                    np.sum(np.asarray(steps["cost"])[mask] > 0) * control_dt_s
                ),
                steering_rate_rms_radps=float(np.sqrt(np.mean(steer_rate[mask] ** 2))),
            )
        )
    return metrics


def summarize(laps: list[LapMetrics]) -> dict:
    """Episode summary over its laps: completed laps, best and mean lap time, worst deviations."""
    completed = [lap for lap in laps if lap.completed]
    times = [lap.lap_time_s for lap in completed]
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
    }
