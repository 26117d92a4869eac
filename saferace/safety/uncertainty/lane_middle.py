"""A camera sees the lane's edges, not the map's centre line: offsets from the lane's middle.

A track's centre line need not lie midway between its edges: a random track's lane is up
to 18 cm wider on one side than the other, and the difference changes along the lap. An
image shows the edges only, so a state network trained on the offset from the centre line
must guess the invisible part: on ten unseen random tracks its lateral error followed the
lane's asymmetry (correlation -0.76; ``docs/uncertainty.md``). Trained on the offset from
the lane's middle instead, the network learns what it sees; the map, which the filter
trusts already, says where the centre line lies from the middle at the car's arc length:
``e_y = e_y_middle + (w_left - w_right) / 2``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from saferace.safety.uncertainty.state_sources import StateSource


def lane_middle_offset_m(w_left_m: Any, w_right_m: Any) -> Any:
    """How far left of the centre line the lane's middle lies, for the lane's half widths
    ``w_left_m`` and ``w_right_m`` (scalars or arrays)."""
    return 0.5 * (np.asarray(w_left_m, float) - np.asarray(w_right_m, float))


class LaneMiddleStateSource:
    """``source``'s samples, whose ``e_y`` is the offset from the lane's middle, moved to
    the offset from the centre line by the map's widths at the car (``info["w_left_m"]``
    and ``info["w_right_m"]``, the map's at the localised arc length, as the filter's lane
    barriers read them). The samples' spread is the source's; its features are passed on
    for a feature monitor."""

    def __init__(self, source: StateSource) -> None:
        self.source = source

    @property
    def last_features(self) -> np.ndarray | None:
        return getattr(self.source, "last_features", None)

    def reset(self, seed: int | None = None) -> None:
        self.source.reset(seed)

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        samples = np.array(self.source.samples(observation, info), dtype=float, ndmin=2)
        samples[:, 0] += lane_middle_offset_m(info["w_left_m"], info["w_right_m"])
        return samples

    def describe(self) -> dict:
        inner: dict[str, Any] = getattr(self.source, "describe", dict)()
        return {**inner, "lateral_reference": "lane middle, moved by the map's widths"}
