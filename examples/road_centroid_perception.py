"""A minimal perception method: ``--state-source road_centroid_perception:make``.

The lane state from where the road's grey pixels lie in two bands of the frame, a far and a
near one, each as its centroid's offset from the image's middle. The coefficients are a
least-squares fit on 900 frames of the expert driving ``lab``, ``oval`` and ``technical``
with steering noise: ``e_y`` within 0.14 m and ``e_psi`` within 0.19 rad on 95% of them. The
interval claimed is about twice that; a frame with no road in a band is in doubt.
"""

from __future__ import annotations

import numpy as np

from saferace.safety.uncertainty.perception import Perception, PerceptionSetup

#: The bands' rows, as fractions of the frame's height: far (near the horizon), near.
BANDS = ((0.38, 0.47), (0.47, 0.70))
#: ``e_y`` in lane widths, and ``e_psi`` in rad, per unit of the bands' offsets.
OFFSET_LANE_WIDTHS = np.array([-0.040, 1.577])
HEADING_RAD = np.array([0.634, -0.208])
#: The interval's half width about the estimate, ``[e_y (m), e_psi (rad)]``.
HALF_WIDTH = np.array([0.3, 0.4])


def road_offsets(image: np.ndarray) -> np.ndarray | None:
    """Each band's road centroid, from the image's middle in image widths (None: no road)."""
    height, width = image.shape[:2]
    pixels = image.astype(int)
    grey = (np.ptp(pixels, axis=2) < 12) & (pixels[..., 0] > 60) & (pixels[..., 0] < 130)
    offsets = []
    for top, bottom in BANDS:
        columns = np.nonzero(grey[int(top * height) : int(bottom * height)])[1]
        if len(columns) == 0:
            return None
        offsets.append((columns.mean() - (width - 1) / 2) / width)
    return np.array(offsets)


class RoadCentroid:
    """The perception method (see the module), on a map of the track's mean lane width."""

    def __init__(self, setup: PerceptionSetup) -> None:
        left_m, right_m = setup.track.widths(setup.track.point_s_m)
        self.lane_width_m = float(np.mean(left_m + right_m))

    def reset(self, seed: int | None = None) -> None:
        """Nothing is kept between frames."""

    def perceive(self, image: np.ndarray, velocity: np.ndarray) -> Perception:
        offsets = road_offsets(image)
        if offsets is None:
            return Perception(np.zeros(2), np.full(2, -np.inf), np.full(2, np.inf), True)
        e_y_m = float(OFFSET_LANE_WIDTHS @ offsets) * self.lane_width_m
        mean = np.array([e_y_m, float(HEADING_RAD @ offsets)])
        return Perception(mean, mean - HALF_WIDTH, mean + HALF_WIDTH)


def make(setup: PerceptionSetup) -> RoadCentroid:
    return RoadCentroid(setup)
