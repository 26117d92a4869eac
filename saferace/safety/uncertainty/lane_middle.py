"""A camera sees the lane's edges, not the map's centre line: offsets from the lane's middle.

A track's centre line need not lie midway between its edges: a random track's lane is up
to 18 cm wider on one side than the other, and the difference changes along the lap. An
image shows the edges only, so a state network trained on the offset from the centre line
must guess the invisible part: on ten unseen random tracks its lateral error followed the
lane's asymmetry (correlation -0.76; ``docs/uncertainty.md``). Trained on the offset from
the lane's middle instead, the network learns what it sees; the map, which the filter
trusts already, says where the centre line lies from the middle at the car's arc length:
``e_y = e_y_middle + (w_left - w_right) / 2``.

The lane's width is the map's too, and a camera cannot tell it from where the edges appear:
seen from the same height, a lane twice as wide with the car at the same fraction of its
half width shows edges whose slopes in the image are twice as steep, and a network that
learned offsets in metres on lanes of 0.9-1.3 m misread a 2.2 m lane with confidence (a
mean error of 0.49 m). The ratio of the two edges' slopes, though, is ``(1 - f) / (1 + f)``
for the offset ``f = e_y_middle / w_half`` in half widths, whatever the width: a network
trained on ``f`` over many widths learns what the image holds, and the map's half width at
the car turns it back into metres.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from saferace.safety.uncertainty.state_sources import StateSource


def lane_middle_offset_m(w_left_m: Any, w_right_m: Any) -> Any:
    """How far left of the centre line the lane's middle lies, for the lane's half widths
    ``w_left_m`` and ``w_right_m`` (scalars or arrays)."""
    return 0.5 * (np.asarray(w_left_m, float) - np.asarray(w_right_m, float))


def lane_middle_state(
    e_y_m: Any, w_left_m: Any, w_right_m: Any, per_half_width: bool = False
) -> Any:
    """The offset from the lane's middle of a car ``e_y_m`` left of the centre line, in
    metres or (``per_half_width``) as a fraction of the lane's half width
    ``(w_left + w_right) / 2``; :func:`centre_line_offset_m` undoes it."""
    middle = np.asarray(e_y_m, float) - lane_middle_offset_m(w_left_m, w_right_m)
    if per_half_width:
        return middle / lane_half_width_m(w_left_m, w_right_m)
    return middle


def centre_line_offset_m(
    middle: Any, w_left_m: Any, w_right_m: Any, per_half_width: bool = False
) -> Any:
    """The offset from the centre line of a car ``middle`` left of the lane's middle (in
    metres, or half widths with ``per_half_width``): :func:`lane_middle_state` undone."""
    scale = lane_half_width_m(w_left_m, w_right_m) if per_half_width else 1.0
    return np.asarray(middle, float) * scale + lane_middle_offset_m(w_left_m, w_right_m)


def lane_half_width_m(w_left_m: Any, w_right_m: Any) -> Any:
    return 0.5 * (np.asarray(w_left_m, float) + np.asarray(w_right_m, float))


class LaneMiddleStateSource:
    """``source``'s samples, whose ``e_y`` is the offset from the lane's middle (in half
    widths with ``per_half_width``), moved to the offset from the centre line in metres by
    the map's widths at the car (``info["w_left_m"]`` and ``info["w_right_m"]``, the map's
    at the localised arc length, as the filter's lane barriers read them). The samples'
    spread is the source's, scaled with them; its features are passed on for a feature
    monitor."""

    def __init__(self, source: StateSource, per_half_width: bool = False) -> None:
        self.source = source
        self.per_half_width = per_half_width

    @property
    def last_features(self) -> np.ndarray | None:
        return getattr(self.source, "last_features", None)

    def reset(self, seed: int | None = None) -> None:
        self.source.reset(seed)

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        samples = np.array(self.source.samples(observation, info), dtype=float, ndmin=2)
        samples[:, 0] = centre_line_offset_m(
            samples[:, 0], info["w_left_m"], info["w_right_m"], self.per_half_width
        )
        return samples

    def describe(self) -> dict:
        inner: dict[str, Any] = getattr(self.source, "describe", dict)()
        unit = "half widths" if self.per_half_width else "metres"
        return {**inner, "lateral_reference": f"lane middle in {unit}, moved by the map's widths"}
