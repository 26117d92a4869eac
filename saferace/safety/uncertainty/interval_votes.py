"""The recent trusted intervals, carried to the car, and the box most of them agree on.

The carried set (:mod:`~saferace.safety.uncertainty.dead_reckoning`) is narrowed by each
trusted frame's interval widened twofold, so that a frame that misses the car does not lose
it; on a straight it is therefore about twice as wide as the network's interval. The filter
certifies over its meet with something tighter. That was the frame's own interval, which
holds nothing of what earlier frames said: on YasMarina's hairpin (a 0.8 m radius no
training track has) the network's intervals widen to +-0.6 m and +-5 rad, the carried set
entered it +-0.7 m wide from the straight, and the expert stopped for good at 198 m.

What the earlier frames said is kept here. The last :data:`VOTES` trusted intervals, one per
:data:`SPACING_M` driven (a car at rest sees the same image, which says nothing new), are
carried to the car as the set is (exactly, by odometry and the map), and the filter
certifies over the box of the points that at least :data:`MAJORITY` of them hold
(:func:`voted_box`). A frame that misses the car, or a few in a row, is outvoted; an
interval made wide by an unfamiliar look holds every point and decides nothing. A box the
majority lost is not kept: it is recounted every step from frames that leave the window
after :data:`VOTES` spacings, and the sound carried set still bounds it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from saferace.safety.uncertainty.dead_reckoning import DeadReckoning

if TYPE_CHECKING:
    from saferace.track.path import ClosedPath

#: How many recent trusted intervals vote.
VOTES = 9
#: How many of them must hold a point for it to be in the voted box.
MAJORITY = 5
#: How far the car drives between two intervals kept (m): about one control step at the
#: circuits' speeds, and a new look at the lane at lower ones.
SPACING_M = 0.25


def voted_box(
    lower: np.ndarray, upper: np.ndarray, votes: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """Column by column, the hull of the points inside at least ``votes`` of the intervals
    ``lower[i] .. upper[i]`` (each of shape ``(n, d)``); None where no point is."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)

    def held_by(points: np.ndarray) -> np.ndarray:  # (n, d): how many intervals hold each
        inside = (lower[None] <= points[:, None]) & (points[:, None] <= upper[None])
        return inside.sum(axis=1)

    from_below, from_above = held_by(lower) >= votes, held_by(upper) >= votes
    if not from_below.any(axis=0).all():
        return None
    return (
        np.where(from_below, lower, np.inf).min(axis=0),
        np.where(from_above, upper, -np.inf).max(axis=0),
    )


class RecentIntervals:
    """The last :data:`VOTES` trusted intervals of ``[e_y, e_psi]``, carried to the car."""

    def __init__(self) -> None:
        self.boxes: DeadReckoning | None = None  # lower, upper: (n, 2)
        self.added_at_m = 0.0  # the boxes' driven_m when the last one was added

    def reset(self) -> None:
        """None kept."""
        self.boxes = None

    def carry(
        self, pose: np.ndarray, s_m: float, centerline: ClosedPath, scale_error: float = 0.0
    ) -> None:
        """Carry every kept interval to the car at ``pose`` and ``s_m``, by an odometry
        up to the fraction ``scale_error`` off."""
        if self.boxes is not None:
            self.boxes = self.boxes.carried(pose, s_m, centerline, scale_error)

    def add(self, interval: tuple[np.ndarray, np.ndarray], pose: np.ndarray, s_m: float) -> None:
        """Keep a trusted frame's ``interval`` (the car at ``pose`` and ``s_m``, where the
        kept ones were carried to), if the car drove :data:`SPACING_M` since the last."""
        lower, upper = (np.asarray(bound, float)[None, :2] for bound in interval)
        boxes = self.boxes
        if boxes is None:
            self.boxes = DeadReckoning(lower, upper, np.asarray(pose, float).copy(), float(s_m))
            self.added_at_m = 0.0
        elif boxes.driven_m - self.added_at_m >= SPACING_M:
            self.boxes = DeadReckoning(
                np.concatenate([boxes.lower, lower])[-VOTES:],
                np.concatenate([boxes.upper, upper])[-VOTES:],
                boxes.pose,
                boxes.s_m,
                boxes.driven_m,
            )
            self.added_at_m = boxes.driven_m

    def voted(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The box :data:`MAJORITY` of the kept intervals hold (:func:`voted_box`); None
        while fewer are kept, or where they hold no common point."""
        boxes = self.boxes
        if boxes is None or len(boxes.lower) < MAJORITY:
            return None
        return voted_box(boxes.lower, boxes.upper, MAJORITY)
