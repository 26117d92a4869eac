"""The perception protocol: what a user's method to perceive the lane state is handed, and
what it gives back.

A perception method sees what a car's own sensors give, never the simulator's state: each
step the camera's frame and the odometry's velocities ``[v_x, v_y, r]``. It answers with
the lane state it sees, ``[e_y, e_psi]`` (m, rad: the car's offset from the centre line and
its heading to it), an interval that it claims holds the truth, and whether it is in doubt
(a frame unlike what it knows: the filter then holds the car over the set it carried by
odometry). Before the first frame it may read the :class:`PerceptionSetup`: the frame's
shape, the control period and the map. It is made by a factory, ``make(setup) -> method``,
loaded as ``MODULE:FACTORY`` from the current folder
(``saferace eval --filter cbf --state-source my_perception:make``), as agents are.

:class:`PerceptionStateSource` turns such a method into the filter's state source; the map
gives the curvature where the car is, as it does to every robust filter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from saferace.errors import SafeRaceError

if TYPE_CHECKING:
    from saferace.track.track import Track


@dataclass(frozen=True)
class PerceptionSetup:
    """What a perception method may know of its task before the first frame: the camera's
    ``image_shape`` (height, width, channels), the ``control_dt_s`` between frames, the
    ``track`` (the map: its centre line, widths and curvature) and the episode's ``seed``."""

    image_shape: tuple[int, ...]
    control_dt_s: float
    track: Track
    seed: int | None = None


@dataclass(frozen=True)
class Perception:
    """One frame's lane state ``mean`` ``[e_y_m, e_psi_rad]``, the box ``lower .. upper``
    claimed to hold the truth, and whether the method is ``in_doubt``."""

    mean: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    in_doubt: bool = False

    def __post_init__(self) -> None:
        for name in ("mean", "lower", "upper"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (2,) or np.isnan(value).any():
                raise SafeRaceError(
                    f"a perception's {name} must be 2 numbers [e_y_m, e_psi_rad], none of "
                    f"them NaN, got {getattr(self, name)!r}"
                )
            object.__setattr__(self, name, value)
        if not np.isfinite(self.mean).all():
            raise SafeRaceError(f"a perception's mean must be finite, got {self.mean.tolist()}")
        if np.any(self.lower > self.mean) or np.any(self.mean > self.upper):
            raise SafeRaceError(
                f"a perception's mean {self.mean.tolist()} must lie within its lower "
                f"{self.lower.tolist()} and upper {self.upper.tolist()}"
            )


@runtime_checkable
class PerceptionMethod(Protocol):
    """A way to perceive the lane state from the car's own sensors."""

    def reset(self, seed: int | None = None) -> None:
        """A new episode (``seed``: its seed)."""
        ...

    def perceive(self, image: np.ndarray, velocity: np.ndarray) -> Perception:
        """The lane state in the camera's ``image`` (``(H, W, 3)`` uint8), with the
        odometry's ``velocity`` ``[v_x, v_y, r]`` (m/s, m/s, rad/s) of the step before."""
        ...


class PerceptionStateSource:
    """A :class:`PerceptionMethod` as the filter's state source: one sample, the method's
    interval and its doubt; the curvature the map's at the car."""

    reads_image = True

    def __init__(self, method: PerceptionMethod, track: Track) -> None:
        if not isinstance(method, PerceptionMethod):
            raise SafeRaceError(
                f"{method!r} is no perception method: it needs reset(seed) and "
                "perceive(image, velocity) -> Perception (saferace.safety.uncertainty.perception)"
            )
        self.method = method
        self.track = track
        self._last: Perception | None = None

    def reset(self, seed: int | None = None) -> None:
        self.method.reset(seed)
        self._last = None

    def samples(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> np.ndarray:
        """The method's mean as one sample; it is handed the frame and the odometry only
        (the map's curvature is looked up at the car's arc length, as the filter does)."""
        image = np.array(observation["image"], copy=True)  # its own copy: nothing to alter
        perception = self.method.perceive(image, np.array(observation["velocity"], copy=True))
        if not isinstance(perception, Perception):
            raise SafeRaceError(f"perceive() must return a Perception, got {perception!r}")
        self._last = perception
        kappa = self.track.centerline.curvature_scalar(float(info["s_m"]))
        return np.array([[*perception.mean, kappa]])

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The method's box, the curvature the sample's."""
        last = self._require_perception()
        kappa = float(samples[0, 2])
        return np.append(last.lower, kappa), np.append(last.upper, kappa)

    def monitor(self, samples: np.ndarray) -> tuple[float | None, bool]:
        """No score; the alarm is the method's doubt."""
        return None, self._require_perception().in_doubt

    def _require_perception(self) -> Perception:
        if self._last is None:
            raise SafeRaceError("no frame perceived yet: samples() comes first each step")
        return self._last
