"""Reference lines for the tasks: the center line and the minimum-curvature racing line.

The racing line (paper eq. 3, Heilmeier et al. 2019) shifts every centerline sample
``r_i`` by ``alpha_i`` along its left normal ``n_i`` and minimises the integral of the
squared curvature of the shifted path subject to ``alpha_i`` keeping the car inside
the lane minus half its width and a margin. With finite differences in the centerline
parameter, the second derivative of the path is linear in ``alpha`` while its first
derivative is frozen at the last iterate; so each iteration is a sparse QP, solved with
OSQP, and the problem is re-linearised until the offsets stop moving.

Both lines get their speed profile from the same forward-backward code, so their
lap-time estimates are comparable.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import osqp
import scipy.sparse as sp

from saferace.errors import RacingLineError
from saferace.track.frenet import FrenetProjector
from saferace.track.path import ClosedPath
from saferace.track.periodic import PeriodicInterpolator
from saferace.track.speed_profile import speed_profile
from saferace.track.track import Track
from saferace.track.vehicle_envelope import VehicleEnvelope

logger = logging.getLogger(__name__)

#: The curvature objective squares second differences, so its condition number grows
#: like N^4 (about 3e9 for 1000 offsets). These settings let OSQP's polishing step find
#: the exact active set (offsets within 1e-6 m of an interior-point reference).
_OSQP_SETTINGS = {
    "eps_abs": 1e-7,
    "eps_rel": 1e-7,
    "sigma": 1e-9,
    "adaptive_rho_tolerance": 2.0,
    "max_iter": 50000,
    "polishing": True,
}

CSV_COLUMNS = ("s_m", "x_m", "y_m", "psi_rad", "kappa_radpm", "vx_mps", "ax_mps2")


@dataclass(frozen=True)
class RacingLineSettings:
    """Discretisation and stopping rule of the minimum-curvature optimisation: stop when no
    offset moves by ``tolerance_m`` or the integral of kappa^2 changes by less than
    ``curvature_tolerance`` of itself; at ``max_iterations`` the warning says how far it was
    from either. ``draft_tolerance``: OSQP's tolerance for the QPs before the rule first
    holds (each only moves the point the next is linearised at, and a loose solve takes a
    fifth of the time of a tight one); then they are solved tight until it holds again.
    ``None`` solves every QP tight."""

    margin_m: float = 0.10
    step_m: float = 0.1
    max_iterations: int = 50
    tolerance_m: float = 1e-4
    curvature_tolerance: float = 1e-4
    draft_tolerance: float | None = 1e-5


@dataclass(frozen=True)
class ReferenceLine:
    """A closed reference line with its speed profile.

    Arrays ``s_m ... ax_mps2`` are equally spaced samples along the line's own arc
    length. ``center_s_m``/``offset_m``/``center_vx_mps``/``center_kappa_radpm`` describe
    the line as a lateral offset from the centerline at centerline arc length, which is
    how the tasks ask "where should the car be at this ``s``?".
    """

    name: str
    path: ClosedPath
    s_m: np.ndarray
    kappa_radpm: np.ndarray
    vx_mps: np.ndarray
    ax_mps2: np.ndarray
    lap_time_s: float
    center_s_m: np.ndarray
    offset_m: np.ndarray
    center_vx_mps: np.ndarray
    center_kappa_radpm: np.ndarray
    track_length_m: float
    _centerline: ClosedPath
    _offset: PeriodicInterpolator
    _speed: PeriodicInterpolator
    _heading_offset: PeriodicInterpolator

    @property
    def length_m(self) -> float:
        """Length of the line itself."""
        return self.path.length_m

    @property
    def curvature_squared_integral(self) -> float:
        """Integral of the squared curvature along the line, in 1/m."""
        return self.path.curvature_squared_integral()

    def offset_at(self, center_s_m: np.ndarray | float) -> np.ndarray | float:
        """Lateral offset from the centerline (positive left) at centerline arc length."""
        return self._offset(center_s_m)

    def heading_offset_at(self, center_s_m: np.ndarray | float) -> np.ndarray | float:
        """The line's heading minus the centerline's, at centerline arc length (rad)."""
        return self._heading_offset(center_s_m)

    def speed_at(self, center_s_m: np.ndarray | float) -> np.ndarray | float:
        """Reference speed at centerline arc length."""
        return self._speed(center_s_m)

    def pose_at(self, center_s_m: float) -> tuple[float, float, float]:
        """``(x, y, yaw)`` of the line at centerline arc length, heading along the line."""
        center = self._centerline
        xy = center.position(center_s_m) + self.offset_at(center_s_m) * center.normal(center_s_m)
        line_s, _ = FrenetProjector(self.path).project(float(xy[0]), float(xy[1]))
        return float(xy[0]), float(xy[1]), float(self.path.heading(line_s))

    def to_csv(self, path: str | Path) -> None:
        """Write ``s_m,x_m,y_m,psi_rad,kappa_radpm,vx_mps,ax_mps2``, one row per sample."""
        xy = self.path.position(self.s_m)
        columns = (
            self.s_m,
            xy[:, 0],
            xy[:, 1],
            self.path.heading(self.s_m),
            self.kappa_radpm,
            self.vx_mps,
            self.ax_mps2,
        )
        with open(path, "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(CSV_COLUMNS)
            for row in zip(*columns, strict=True):
                writer.writerow([f"{value:.6f}" for value in row])


def center_line(
    track: Track, envelope: VehicleEnvelope | None = None, step_m: float = 0.1
) -> ReferenceLine:
    """The centerline as a reference line, with its speed profile."""
    envelope = envelope or VehicleEnvelope()
    center_s = track.centerline.sample(step_m)
    return _reference(
        "center",
        track.centerline,
        center_s,
        np.zeros_like(center_s),
        center_s,
        track,
        envelope,
        step_m,
    )


def racing_line(
    track: Track,
    envelope: VehicleEnvelope | None = None,
    settings: RacingLineSettings | None = None,
) -> ReferenceLine:
    """The minimum-curvature racing line of ``track`` with its speed profile."""
    envelope = envelope or VehicleEnvelope()
    settings = settings or RacingLineSettings()
    center_s = track.centerline.sample(settings.step_m)
    offsets = min_curvature_offsets(track, center_s, envelope.width_m, settings)
    points = track.centerline.position(center_s) + offsets[:, None] * track.centerline.normal(
        center_s
    )
    path = ClosedPath(points)
    return _reference(
        "racing", path, center_s, offsets, path.point_s_m, track, envelope, settings.step_m
    )


def offset_bounds(
    track: Track, center_s_m: np.ndarray, car_width_m: float, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest lateral offset that keep the car ``margin_m`` inside the lane."""
    w_right, w_left = track.widths(center_s_m)
    clearance = 0.5 * car_width_m + margin_m
    lower, upper = -(w_right - clearance), w_left - clearance
    tight = np.flatnonzero(lower > upper)
    if tight.size:
        s = center_s_m[tight[0]]
        raise RacingLineError(
            f"at s = {s:.2f} m the lane ({w_right[tight[0]] + w_left[tight[0]]:.3f} m) is narrower "
            f"than the car plus margins ({2 * clearance:.3f} m); lower --car-width-m or --margin-m"
        )
    return lower, upper


def curvature_qp(
    track: Track, center_s_m: np.ndarray, offsets_m: np.ndarray
) -> tuple[sp.csc_matrix, np.ndarray, float]:
    """``P, q`` of ``min 1/2 a^T P a + q^T a``: integral of kappa^2 linearised at ``offsets_m``;
    also that integral at ``offsets_m`` (finite differences)."""
    count = len(center_s_m)
    h = track.length_m / count
    r = track.centerline.position(center_s_m)
    n = track.centerline.normal(center_s_m)
    p = r + offsets_m[:, None] * n
    d1 = (np.roll(p, -1, axis=0) - np.roll(p, 1, axis=0)) / (2.0 * h)
    speed = np.linalg.norm(d1, axis=1)
    second = (
        sp.diags(
            [np.ones(count - 1), -2.0 * np.ones(count), np.ones(count - 1), [1.0], [1.0]],
            [1, 0, -1, -(count - 1), count - 1],
            format="csc",
        )
        / h**2
    )
    weight_x = d1[:, 0] / speed**3
    weight_y = d1[:, 1] / speed**3
    kappa_matrix = sp.diags(weight_x) @ second @ sp.diags(n[:, 1]) - sp.diags(
        weight_y
    ) @ second @ sp.diags(n[:, 0])
    kappa_constant = weight_x * (second @ r[:, 1]) - weight_y * (second @ r[:, 0])
    ds = sp.diags(speed * h)  # integrate kappa^2 over the shifted path's own arc length
    P = 2.0 * (kappa_matrix.T @ ds @ kappa_matrix)
    q = 2.0 * (kappa_matrix.T @ (ds @ kappa_constant))
    kappa = kappa_matrix @ offsets_m + kappa_constant
    return sp.csc_matrix(P), q, float(np.sum(kappa**2 * speed * h))


def min_curvature_offsets(
    track: Track, center_s_m: np.ndarray, car_width_m: float, settings: RacingLineSettings
) -> np.ndarray:
    """Lateral offsets of the minimum-curvature line at ``center_s_m`` (sequential QPs)."""
    lower, upper = offset_bounds(track, center_s_m, car_width_m, settings.margin_m)
    count = len(center_s_m)
    offsets = np.zeros(count)
    solver: osqp.OSQP | None = None
    change = relative = previous_integral = np.inf
    draft_tolerance = settings.draft_tolerance
    draft = draft_tolerance is not None
    draft_settings = _tolerance(draft_tolerance) if draft_tolerance is not None else {}
    for iteration in range(1, settings.max_iterations + 2):
        P, q, integral = curvature_qp(track, center_s_m, offsets)
        if iteration > 1:
            relative = abs(integral - previous_integral) / integral
            logger.debug(
                "racing line iteration %d: max offset change %.2e m, integral of kappa^2 "
                "%.6f 1/m (relative change %.1e)%s",
                iteration - 1,
                change,
                integral,
                relative,
                " (draft tolerance)" if draft else "",
            )
            if change < settings.tolerance_m or relative < settings.curvature_tolerance:
                if not draft:
                    return offsets
                draft = False
                assert solver is not None  # set up in the first iteration
                solver.update_settings(**_tolerance(_OSQP_SETTINGS["eps_abs"]))
            if iteration > settings.max_iterations:
                break
        if solver is None:
            solver = osqp.OSQP()
            solver.setup(
                P=sp.triu(P, format="csc"),
                q=q,
                A=sp.identity(count, format="csc"),
                l=lower,
                u=upper,
                verbose=False,
                **{**_OSQP_SETTINGS, **(draft_settings if draft else {})},
            )
        else:
            solver.update(Px=sp.triu(P, format="csc").data, q=q)
        result = solver.solve(raise_error=False)
        if result.x is None or not np.all(np.isfinite(result.x)):
            raise RacingLineError(
                f"the racing-line QP failed ({result.info.status}) on {track.name}"
            )
        change = float(np.max(np.abs(result.x - offsets)))
        offsets = np.clip(result.x, lower, upper)
        previous_integral = integral
    logger.warning(
        "racing line on %s not converged after %d iterations: offsets still move by %.2e m "
        "(tolerance %.0e m) and the integral of kappa^2 by %.1e of itself (tolerance %.0e)",
        track.name,
        settings.max_iterations,
        change,
        settings.tolerance_m,
        relative,
        settings.curvature_tolerance,
    )
    return offsets


def _tolerance(eps: float) -> dict[str, float]:
    """OSQP's absolute and relative tolerance, both ``eps``."""
    return {"eps_abs": eps, "eps_rel": eps}


def _reference(
    name: str,
    path: ClosedPath,
    center_s: np.ndarray,
    offsets: np.ndarray,
    line_s_of_center: np.ndarray,
    track: Track,
    envelope: VehicleEnvelope,
    step_m: float,
) -> ReferenceLine:
    s = path.sample(step_m)
    kappa = path.curvature(s)
    profile = speed_profile(kappa, path.length_m / len(s), envelope)
    center_vx = np.interp(line_s_of_center, s, profile.vx_mps, period=path.length_m)
    heading_offset = np.angle(
        np.exp(1j * (path.heading(line_s_of_center) - track.centerline.heading(center_s)))
    )
    return ReferenceLine(
        name=name,
        path=path,
        s_m=s,
        kappa_radpm=kappa,
        vx_mps=profile.vx_mps,
        ax_mps2=profile.ax_mps2,
        lap_time_s=profile.lap_time_s,
        center_s_m=center_s,
        offset_m=offsets,
        center_vx_mps=center_vx,
        center_kappa_radpm=np.interp(line_s_of_center, s, kappa, period=path.length_m),
        track_length_m=track.length_m,
        _centerline=track.centerline,
        _offset=PeriodicInterpolator(center_s, offsets, track.length_m),
        _speed=PeriodicInterpolator(center_s, center_vx, track.length_m),
        _heading_offset=PeriodicInterpolator(center_s, heading_offset, track.length_m),
    )
