"""The speed limit of the filter's speed barrier: the reference's profile, braked for in time.

The task's reference speed profile (planned for 5 m/s^2 of lateral acceleration), scaled
by ``factor``, bounds the speed in each corner. Ahead of a slower stretch the limit falls
no faster than a friction ellipse allows: ``decel_mps2`` on a straight, less where the
limit already turns with ``v^2 kappa`` of the ellipse's ``lateral_mps2``. So a car held
below it has braked before it turns in, and does not brake hard while it turns (braking
in a corner near the grip limit spins this car: its rear brakes take 40% of the braking).

The reference's profile holds on the reference line only. A racing line cuts its corners,
so a car far from it, riding the centre of a tight turn, turns tighter than the line at
the same speed (on Spielberg's 2.1 m turn, smoothed by 5 cm, the racing line's limit is
6.6 m/s, the centre's 4). :class:`LaneSpeedLimit` therefore also bounds a car away from
the reference by the same profile computed along the parallel of the centre line through
the car's offset.
"""

from __future__ import annotations

import math

import numpy as np

from saferace.track.periodic import PeriodicInterpolator
from saferace.track.raceline import ReferenceLine
from saferace.track.track import Track

#: Curvature below which a path is straight for the limit (1/m): it then sets no corner speed.
STRAIGHT_CURVATURE_RADPM = 1e-6
#: The least ``1 - kappa e_y`` a parallel path keeps: offsets beyond a turn's centre, outside
#: the lane there, get a very tight path instead of a folded one.
MIN_PARALLEL_STRETCH = 0.05


def braking_speed_limit(
    reference: ReferenceLine, factor: float, decel_mps2: float, lateral_mps2: float
) -> PeriodicInterpolator:
    """``v_limit(s)`` on the centerline's arc length: ``v^2 <= (factor v_ref)^2`` everywhere
    ahead, less ``2 decel sqrt(1 - (v^2 kappa / lateral)^2)`` per metre to it (a backward
    pass, twice round the closed track; ``kappa`` is the reference line's curvature).
    """
    _check_positive(factor=factor, decel_mps2=decel_mps2, lateral_mps2=lateral_mps2)
    s = np.asarray(reference.center_s_m, dtype=float)
    limit_sq = (factor * np.asarray(reference.center_vx_mps, dtype=float)) ** 2
    curvature = np.abs(np.asarray(reference.center_kappa_radpm, dtype=float))
    gaps = np.diff(np.append(s, s[0] + reference.track_length_m))
    limit = braked(limit_sq[None], curvature[None], gaps[None], decel_mps2, lateral_mps2)[0]
    return PeriodicInterpolator(s, limit, reference.track_length_m)


def braked(
    limit_sq: np.ndarray,
    curvature_radpm: np.ndarray,
    gaps_m: np.ndarray,
    decel_mps2: float,
    lateral_mps2: float,
) -> np.ndarray:
    """Speed limits (m/s; rows: paths, columns: samples ``gaps_m`` apart round a closed path)
    no faster than the squared limits ``limit_sq`` allow anywhere ahead, braked for within
    the friction ellipse."""
    limit_sq = np.array(limit_sq, dtype=float)
    count = limit_sq.shape[1]
    for k in range(2 * count, 0, -1):
        i, j = (k - 1) % count, k % count
        grip_used = np.minimum(1.0, limit_sq[:, j] * curvature_radpm[:, j] / lateral_mps2)
        reachable = limit_sq[:, j] + 2.0 * decel_mps2 * np.sqrt(1.0 - grip_used**2) * gaps_m[:, i]
        limit_sq[:, i] = np.minimum(limit_sq[:, i], reachable)
    return np.sqrt(limit_sq)


class LaneSpeedLimit:
    """``v_limit(s, e_y)``: the reference's braked limit where the car is near the reference
    line; from ``near_m`` to ``far_m`` away from it, blending into the lower of that and the
    limit of the centre line's parallel through ``e_y``.

    The parallel at offset ``d`` has curvature ``kappa / (1 - kappa d)`` and arc length
    ``(1 - kappa d) ds``; its limit is ``sqrt(path_lateral_mps2 / |kappa_d|)``, braked for
    as :func:`braking_speed_limit` brakes (computed on a grid of offsets ``offset_step_m``
    apart across the widest lane, linear in between). The parallels alone would slow a car
    on the racing line at every apex, where the line turns more gently than the parallel
    of the inner edge it touches; hence the blend by distance from the reference. An
    ``e_y`` beyond the grid takes its outermost parallel.

    The blend itself is not braked for: a car holding the centre while the line moves away
    from it meets the lower limit within metres (at Spielberg's 2.1 m turn, smoothed by
    8 cm, the limit at ``e_y = 0`` falls by 3.1 m/s in 1.2 m), and the barrier then asks
    for more braking than the car has. Braking each offset's blended limit along the track
    would mend that, but would slow a car on its line wherever the line leaves that offset
    downstream: to 0.92-0.94 of the reference's limit on the built-in tracks and 0.43-0.63
    on the F1TENTH circuits. :meth:`invariant_limit` is a lower bound that is braked for.
    """

    def __init__(
        self,
        track: Track,
        reference: ReferenceLine,
        factor: float,
        decel_mps2: float,
        lateral_mps2: float,
        path_lateral_mps2: float,
        near_m: float = 0.3,
        far_m: float = 0.6,
        offset_step_m: float = 0.1,
    ) -> None:
        _check_positive(path_lateral_mps2=path_lateral_mps2, offset_step_m=offset_step_m)
        if not 0.0 <= near_m < far_m:
            raise ValueError(f"need 0 <= near_m < far_m, got {near_m}, {far_m}")
        self.reference_limit = braking_speed_limit(reference, factor, decel_mps2, lateral_mps2)
        self.reference_offset = reference.offset_at
        self.near_m, self.far_m = near_m, far_m
        s = np.asarray(reference.center_s_m, dtype=float)
        right, left = track.widths(s)
        count = 1 + math.ceil((np.max(right) + np.max(left)) / offset_step_m)
        self.offsets_m = np.linspace(-np.max(right), np.max(left), max(count, 2))
        kappa = track.centerline.curvature(s)
        stretch = np.maximum(1.0 - np.outer(self.offsets_m, kappa), MIN_PARALLEL_STRETCH)
        path_curvature = np.maximum(np.abs(kappa) / stretch, STRAIGHT_CURVATURE_RADPM)
        gaps = np.diff(np.append(s, s[0] + track.length_m)) * stretch
        limits = braked(
            path_lateral_mps2 / path_curvature, path_curvature, gaps, decel_mps2, lateral_mps2
        )
        self.parallel_limits = [PeriodicInterpolator(s, row, track.length_m) for row in limits]

    def __call__(self, s_m: float, e_y_m: float) -> float:
        return self.lowest(s_m, np.array([e_y_m]))[0]

    def lowest(self, s_m: float, e_y_m: np.ndarray) -> tuple[float, float]:
        """The lowest limit at ``s_m`` over the offsets ``e_y_m``, and the offset it is at."""
        limit = float(self.reference_limit(s_m))
        weights = self._blend_weights(s_m, e_y_m)
        lowest, at = limit, float(e_y_m[0])
        for weight, e_y in zip(weights[weights > 0.0], e_y_m[weights > 0.0], strict=True):
            blended = self._blended(limit, float(weight), s_m, float(e_y))
            if blended < lowest:
                lowest, at = blended, float(e_y)
        return lowest, at

    def along(self, s_m: np.ndarray, e_y_m: np.ndarray) -> np.ndarray:
        """The limit at each pair of ``s_m`` and ``e_y_m`` (a plan's stages), with one lookup
        of the reference's limits for all of them."""
        s_m, e_y_m = np.asarray(s_m, dtype=float), np.asarray(e_y_m, dtype=float)
        limits = self.reference_limit(s_m)
        weights = self._blend_weights(s_m, e_y_m)
        for i in np.flatnonzero(weights):  # the few stages far from the reference line
            limits[i] = self._blended(limits[i], weights[i], float(s_m[i]), float(e_y_m[i]))
        return limits

    def invariant_limit(self, s_m: float, e_y_m: float) -> float:
        """A limit at ``(s_m, e_y_m)`` that the limit ahead never falls faster than braking
        allows, for a car that follows the reference line from within ``near_m`` of it or
        else keeps its offset: the reference's limit near the line, and beyond it the lower
        of that and the parallel's, the most the blend can lower it to. Both profiles are
        braked for along their paths, and so is their minimum; the blend in between is not
        (a predictive plan's last stage is held to this, its other stages to the blend)."""
        limit = float(self.reference_limit(s_m))
        if self._blend_weights(s_m, np.array([e_y_m]))[0] <= 0.0:
            return limit
        return min(limit, self.parallel_limit(s_m, e_y_m))

    def _blend_weights(self, s_m: float | np.ndarray, e_y_m: np.ndarray) -> np.ndarray:
        """How far each offset has blended into its parallel's limit: 0 within ``near_m`` of
        the reference line, 1 beyond ``far_m``."""
        away = np.abs(e_y_m - self.reference_offset(s_m))
        return np.clip((away - self.near_m) / (self.far_m - self.near_m), 0.0, 1.0)

    def _blended(self, limit: float, weight: float, s_m: float, e_y_m: float) -> float:
        """The reference's ``limit`` lowered by ``weight`` towards the parallel's."""
        return limit - weight * max(0.0, limit - self.parallel_limit(s_m, e_y_m))

    def parallel_limit(self, s_m: float, e_y_m: float) -> float:
        """The braked limit along the centre line's parallel through ``e_y_m``."""
        position = float(np.interp(e_y_m, self.offsets_m, np.arange(len(self.offsets_m))))
        below = min(int(position), len(self.offsets_m) - 2)
        fraction = position - below
        low = float(self.parallel_limits[below](s_m))
        high = float(self.parallel_limits[below + 1](s_m))
        return low + fraction * (high - low)


def _check_positive(**values: float) -> None:
    bad = [f"{name}={value}" for name, value in values.items() if value <= 0.0]
    if bad:
        raise ValueError(f"{', '.join(values)} must be positive, got {', '.join(bad)}")
