"""Frenet projection ``(x, y, yaw) -> (s, e_y, e_psi)`` and its inverse.

:class:`FrenetProjector` keeps the last arc length and refines it with Newton's
method on ``(r(s) - p) . r'(s) = 0``, so a projection costs a few cubic
evaluations (microseconds) instead of a scan over the whole track. It falls back
to a global scan on the first call, after :meth:`FrenetProjector.reset`, and when
the local search jumps too far or fails to converge.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np

from saferace.track.path import ClosedPath

#: An arc length or an array of them.
Arc = TypeVar("Arc", float, np.ndarray)


def wrap_angle(angle_rad: float) -> float:
    """Angle wrapped into ``[-pi, pi)``."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


class FrenetProjector:
    """Stateful projector onto a :class:`ClosedPath`.

    ``max_jump_m`` bounds how far ``s`` may move between two calls before the local
    result is distrusted and a global scan is made (a car moves at most ~0.5 m per
    control step).
    """

    def __init__(
        self,
        path: ClosedPath,
        max_jump_m: float = 2.0,
        max_newton_steps: int = 12,
        tolerance_m: float = 1e-8,
    ) -> None:
        self.path = path
        self.max_jump_m = max_jump_m
        self.max_newton_steps = max_newton_steps
        self.tolerance_m = tolerance_m
        self._last_s: float | None = None
        self._last_foot = (0.0, 0.0, 1.0, 0.0)

    def reset(self, s_m: float | None = None) -> None:
        """Forget the last position (or start the local search at ``s_m``)."""
        if s_m is None:
            self._last_s = None
            return
        px, py, dx, dy, _, _ = self.path.eval_scalar(s_m)
        norm = math.hypot(dx, dy)
        self._last_s = s_m % self.path.length_m
        self._last_foot = (px, py, dx / norm, dy / norm)

    def get_state(self) -> tuple[float | None, tuple[float, float, float, float]]:
        """The search state (last ``s`` and foot point), for saving and restoring an episode."""
        return self._last_s, self._last_foot

    def set_state(self, state: tuple[float | None, tuple[float, float, float, float]]) -> None:
        """Restore what :meth:`get_state` returned."""
        self._last_s, self._last_foot = state

    def project(self, x_m: float, y_m: float) -> tuple[float, float]:
        """Arc length ``s`` and signed lateral offset ``e_y`` (positive left) of a point."""
        s, e_y, _ = self._project(x_m, y_m)
        return s, e_y

    def to_frenet(self, x_m: float, y_m: float, yaw_rad: float) -> tuple[float, float, float]:
        """``(s, e_y, e_psi)`` of a pose; ``e_psi`` is yaw minus path heading, in [-pi, pi)."""
        s, e_y, heading = self._project(x_m, y_m)
        return s, e_y, wrap_angle(yaw_rad - heading)

    def from_frenet(
        self, s_m: float, e_y_m: float, e_psi_rad: float = 0.0
    ) -> tuple[float, float, float]:
        """``(x, y, yaw)`` of the pose at ``(s, e_y, e_psi)``."""
        px, py, dx, dy, _, _ = self.path.eval_scalar(s_m)
        norm = math.hypot(dx, dy)
        tx, ty = dx / norm, dy / norm
        return px - e_y_m * ty, py + e_y_m * tx, wrap_angle(math.atan2(ty, tx) + e_psi_rad)

    def _project(self, x: float, y: float) -> tuple[float, float, float]:
        last_s = self._last_s
        if last_s is not None:
            # First-order guess: the last foot point moved along the last tangent.
            last_x, last_y, tx, ty = self._last_foot
            guess = last_s + (x - last_x) * tx + (y - last_y) * ty
            result = self._newton(x, y, guess)
            if (
                result is not None
                and abs(wrap_arc(result[0] - last_s, self.path.length_m)) <= self.max_jump_m
            ):
                return result
        result = self._newton(x, y, self.path.nearest_knot(x, y))
        if result is None:  # pragma: no cover - Newton from the nearest knot always converges
            raise RuntimeError(f"Frenet projection of ({x}, {y}) did not converge")
        return result

    def _newton(self, x: float, y: float, s: float) -> tuple[float, float, float] | None:
        """Newton iterations for the foot point; ``(s, e_y, heading)`` or None if it fails.

        The cubic piece is evaluated inline: this is the per-step hot path.
        """
        path = self.path
        length, ds, pieces, last_piece = (
            path.length_m,
            path.knot_spacing_m,
            path.pieces,
            path.piece_count - 1,
        )
        for _ in range(self.max_newton_steps):
            s %= length
            k = min(int(s / ds), last_piece)
            t = s - k * ds
            ax, bx, cx, px, ay, by, cy, py = pieces[k]
            px += ((ax * t + bx) * t + cx) * t
            py += ((ay * t + by) * t + cy) * t
            dx = (3.0 * ax * t + 2.0 * bx) * t + cx
            dy = (3.0 * ay * t + 2.0 * by) * t + cy
            rx, ry = px - x, py - y
            slope = (
                dx * dx + dy * dy + rx * (6.0 * ax * t + 2.0 * bx) + ry * (6.0 * ay * t + 2.0 * by)
            )
            if slope <= 1e-9:
                return None
            step = (rx * dx + ry * dy) / slope
            s -= max(-1.0, min(1.0, step))
            if abs(step) < self.tolerance_m:
                norm = math.sqrt(dx * dx + dy * dy)
                tx, ty = dx / norm, dy / norm
                s %= length
                self._last_s = s
                self._last_foot = (px, py, tx, ty)
                return s, rx * ty - ry * tx, math.atan2(ty, tx)
        return None


def wrap_arc(delta_s: Arc, length_m: float) -> Arc:
    """Arc-length difference(s) wrapped into ``[-length/2, length/2)``."""
    return (delta_s + 0.5 * length_m) % length_m - 0.5 * length_m
