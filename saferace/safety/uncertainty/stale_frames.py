"""Frames that cannot be fresh: one repeated while the car moved, or one with nothing in it.

A frozen camera, or one dropping frames, sends its last image again: a frame in the
network's distribution, the monitor quiet, and an interval of where the car was. A car
standing still sees the same image too, and so does one driving down a straight in a small
image: at 16 pixels wide the expert drove up to 3.5 m under one unchanged frame on Monza's
straights (0.7 m at 32, never at 48 or 64), though never turning more than 8 mrad under one.
So a frame is stale where it is the same, to the bit, as the last one that changed while the
odometry turned the car more than :data:`STALE_TURN_RAD` since, or moved it more than
:data:`STALE_DISTANCE_M` scaled by the square of how many times narrower than
:data:`REFERENCE_WIDTH_PX` the image is.

A blacked-out camera (or a lens cap) sends a frame with nothing in it: every pixel within
:data:`BLANK_RANGE` levels of the others. Either is no measurement, and the filter treats
the step as in doubt. (A timestamp that stops would tell the same; the tasks' frames carry
none.)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from saferace.safety.uncertainty.dead_reckoning import car_pose
from saferace.safety.uncertainty.state_sources import StateSource, reads_image
from saferace.track.odometry import odometry_step

#: How far the odometry may move the car under one unchanged image of
#: :data:`REFERENCE_WIDTH_PX` before it is stale (m): at 3 m/s a frozen camera is caught
#: within 0.2 s. Each halving of the width quadruples it (8 m at 16 pixels).
STALE_DISTANCE_M = 0.5
#: The image width at which :data:`STALE_DISTANCE_M` holds (the tasks' default).
REFERENCE_WIDTH_PX = 64
#: How far the odometry may turn the car under one unchanged image (rad): a car turning
#: sees its view sweep, even in 16 pixels.
STALE_TURN_RAD = 0.05
#: Levels (of 255) within which a frame's every pixel lies where it shows nothing.
BLANK_RANGE = 8


def blank(image: np.ndarray) -> bool:
    """Whether ``image`` shows nothing: every pixel within :data:`BLANK_RANGE` levels."""
    return int(image.max()) - int(image.min()) <= BLANK_RANGE


class StaleFrames:
    """Tells, frame by frame, whether a camera's frame is stale (see the module); where it
    does not ``apply`` (the state source reads no frame), never."""

    def __init__(self, apply: bool = True) -> None:
        self.apply = apply
        self.reset()

    @classmethod
    def of_source(cls, source: StateSource) -> StaleFrames:
        """The detector of a filter fed by ``source``: it applies where the source reads the
        frame (:func:`~saferace.safety.uncertainty.state_sources.reads_image`); the truth
        does not go stale in a blackout."""
        return cls(reads_image(source))

    def reset(self) -> None:
        """Forget the last frame (a new episode)."""
        self._changed: np.ndarray | None = None  # the last frame that differed from before
        self._pose_at_change = np.zeros(3)

    def in_step(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> bool:
        """Whether a task's step (``observation``, ``info``) brought a stale frame."""
        return self.apply and self.stale(observation["image"], car_pose(info))

    def stale(self, image: np.ndarray, odometry_pose: np.ndarray) -> bool:
        """Whether ``image``, seen with the car at ``odometry_pose`` (``(x, y, yaw)`` as its
        odometry integrates it), is stale: blank, or unchanged while the car moved."""
        image = np.asarray(image)
        if blank(image):
            return True
        if self._changed is None or not np.array_equal(image, self._changed):
            self._changed, self._pose_at_change = image.copy(), np.asarray(odometry_pose)
            return False
        dx, dy, dyaw = odometry_step(self._pose_at_change, odometry_pose)
        return bool(
            math.hypot(dx, dy) > stale_distance_m(image.shape[1]) or abs(dyaw) > STALE_TURN_RAD
        )


def stale_distance_m(width_px: int) -> float:
    """How far the car may move under one unchanged image ``width_px`` wide (m)."""
    return STALE_DISTANCE_M * (REFERENCE_WIDTH_PX / width_px) ** 2
