"""Frames that may arrive up to ``max_latency_steps`` control steps late: where the car is
now, from where a late frame saw it.

A camera behind a slow pipe (a USB camera, a busy encoder) sends a frame taken some steps
ago, and a network reading it gives an interval of where the car *was*. Unnoticed, the
filter certifies the past: the drifting driver on Brands Hatch widened to 2.6 m, its camera
200 ms late, left the lane for 0.35 s, its interval 0.2 m behind the car on a bend. Nothing
in a late frame tells its age, but a car's datasheet gives its camera's latency bound, as
it gives its actuators' (:data:`~saferace.names.CAMERA_LATENCY_ATTRIBUTE`, declared by the
fault wrapper). Within it, the interval of a frame ``k`` steps old is carried to now by
the odometry of the last ``k`` steps and the map
(:meth:`~saferace.safety.uncertainty.dead_reckoning.DeadReckoning.carried`, with the
odometry's declared error), and the car lies in the hull over every ``k`` from 0 to the
bound: a latency that is fixed, random or none is covered alike. Without a declared
latency nothing changes. The interval is what the robust mode certifies over; the chance
constraints take the source's samples as they are.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections import deque
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from saferace.faults.wrapper import declared
from saferace.names import CAMERA_LATENCY_ATTRIBUTE, ODOMETRY_ERROR_ATTRIBUTE
from saferace.safety.uncertainty.dead_reckoning import DeadReckoning, car_pose
from saferace.safety.uncertainty.estimate import StateEstimate
from saferace.safety.uncertainty.last_trusted import LastTrusted, offset_with_heading
from saferace.safety.uncertainty.state_sources import StateSource, reads_image

if TYPE_CHECKING:
    from saferace.track.path import ClosedPath


class LateFrames:
    """The poses (by odometry) and arc lengths of the last ``max_latency_steps`` steps on
    ``centerline``, and where they carry a frame's interval."""

    def __init__(
        self, max_latency_steps: int, centerline: ClosedPath, odometry_scale_error: float = 0.0
    ) -> None:
        if max_latency_steps < 0:
            raise ValueError(f"max_latency_steps must be >= 0, got {max_latency_steps}")
        self.max_latency_steps = max_latency_steps
        self.centerline = centerline
        self.odometry_scale_error = odometry_scale_error
        #: Each step's odometry pose, arc length and the set carried there (None: none).
        self.seen: deque[tuple[np.ndarray, float, DeadReckoning | None]] = deque(
            maxlen=max_latency_steps + 1
        )

    @classmethod
    def of_task(cls, env: gym.Env, source: StateSource) -> LateFrames:
        """The camera of ``env`` as ``source`` reads it: as late as the task's wrappers
        declare (none: the simulator's, whose frames are the step's; or a source that reads
        no frame, as the truth is never late), carried with the odometry's declared error."""
        steps = int(declared(env, CAMERA_LATENCY_ATTRIBUTE)) if reads_image(source) else 0
        error = declared(env, ODOMETRY_ERROR_ATTRIBUTE)
        return cls(steps, env.unwrapped.track.centerline, error)  # type: ignore[attr-defined]

    def reset(self) -> None:
        self.seen.clear()

    def caught_up(
        self, estimate: StateEstimate, info: dict[str, Any], last_trusted: LastTrusted | None
    ) -> StateEstimate:
        """Where the car in ``info`` is, for a frame whose ``estimate`` may be up to the bound
        late: its interval the hull of the frame's carried from each of the last steps'
        poses to now (the curvature's as it is). With ``last_trusted`` (the robust filter's
        set), the frame's heading meets the set's at each of those steps first, where they
        meet: a network's heading is +-0.2 rad or more and the gyro's a few mrad, and
        carried, every radian of heading spreads the offset by the distance driven (on
        Spielberg's lane narrowed to 0.7 m, 100 ms late, it slowed the expert to 83% of its
        fault-free progress; met, 97%)."""
        if not self.max_latency_steps:
            return estimate
        carried = None if last_trusted is None else last_trusted.carried(info)
        self.seen.append((car_pose(info), float(info["s_m"]), carried))
        interval = (estimate.lower, estimate.upper)
        if not np.all(np.isfinite(interval[0][:2]) & np.isfinite(interval[1][:2])):
            return estimate  # no bound to carry
        boxes = None  # the frame's box as taken at each earlier step, carried together
        for (pose, s_m, then), (next_pose, next_s_m, _) in itertools.pairwise(self.seen):
            met = then is not None and then.meets(*interval)
            box_lower, box_upper = offset_with_heading(interval, then if met else None)
            if boxes is None:
                boxes = DeadReckoning(box_lower[None], box_upper[None], pose, s_m)
            else:
                boxes = dataclasses.replace(
                    boxes,
                    lower=np.vstack([boxes.lower, box_lower]),
                    upper=np.vstack([boxes.upper, box_upper]),
                )
            boxes = boxes.carried(next_pose, next_s_m, self.centerline, self.odometry_scale_error)
        lower, upper = (np.array(bound, dtype=float) for bound in interval)
        if boxes is not None:
            lower[:2] = np.minimum(lower[:2], boxes.lower.min(axis=0))
            upper[:2] = np.maximum(upper[:2], boxes.upper.max(axis=0))
        return dataclasses.replace(estimate, lower=lower, upper=upper)
