"""What the safety filter reads off the map at the car's ``s``: lane widths and speed limit."""

from __future__ import annotations

import math

import numpy as np

from saferace.safety.cbf.barriers import BarrierContext
from saferace.safety.cbf.speed_limit import LaneSpeedLimit
from saferace.track import Track
from saferace.track.raceline import ReferenceLine
from saferace.track.vehicle_envelope import VehicleEnvelope

#: Step (m) of the finite differences of the speed limit and lane widths along the track.
MAP_DS_M = 0.05
#: The friction ellipse the speed limit brakes within (m/s^2): braking at half the car's
#: 4 on a straight, none where the limit turns at 7 (the limit's corners take 6.05, the
#: tyres' grip is about 9.8), so braking ends as the car turns in.
SPEED_LIMIT_DECEL_MPS2 = 2.0
SPEED_LIMIT_LATERAL_MPS2 = 7.0


class FilterMap:
    """The track's half widths (the narrowest within ``width_preview_s`` of driving, and
    their slopes along ``s``) and, with a ``speed_limit_factor``, the speed-limit barrier
    ``h_speed = v_limit(s) - v_x`` on ``reference``'s speed profile."""

    def __init__(
        self,
        track: Track,
        reference: ReferenceLine,
        width_preview_s: float,
        speed_limit_factor: float | None,
        speed_gain: float,
    ) -> None:
        if width_preview_s < 0.0:
            raise ValueError(f"width_preview_s must be non-negative, got {width_preview_s}")
        if speed_limit_factor is not None and speed_limit_factor <= 0.0:
            raise ValueError(f"speed_limit_factor must be positive, got {speed_limit_factor}")
        self.track = track
        self.width_preview_s = width_preview_s
        self.speed_gain = speed_gain
        self.speed_limit = (
            LaneSpeedLimit(
                track,
                reference,
                speed_limit_factor,
                SPEED_LIMIT_DECEL_MPS2,
                SPEED_LIMIT_LATERAL_MPS2,
                path_lateral_mps2=speed_limit_factor**2 * VehicleEnvelope().a_lat_max_mps2,
            )
            if speed_limit_factor
            else None
        )

    def widths(self, s_m: float, v_x: float) -> tuple[float, float, float, float]:
        """``(w_right, w_left, d w_left / ds, d w_right / ds)`` previewed at speed ``v_x``."""
        preview_m = self.width_preview_s * max(v_x, 0.0)
        w_right, w_left = self._lane_widths(s_m, preview_m)
        right_ahead, left_ahead = self._lane_widths(s_m + MAP_DS_M, preview_m)
        right_behind, left_behind = self._lane_widths(s_m - MAP_DS_M, preview_m)
        scale = 0.5 / MAP_DS_M
        return (
            w_right,
            w_left,
            (left_ahead - left_behind) * scale,
            (right_ahead - right_behind) * scale,
        )

    def barrier_context(
        self,
        s_m: float,
        v_x: float,
        half_width_m: float,
        theta_max_rad: float,
        lam: float | tuple[float, ...],
        lateral_decel_mps2: float,
    ) -> BarrierContext:
        """The barriers' map at ``s_m`` (widths previewed at speed ``v_x``) and gains."""
        w_right, w_left, w_left_slope, w_right_slope = self.widths(s_m, v_x)
        return BarrierContext(
            w_left_m=w_left,
            w_right_m=w_right,
            half_width_m=half_width_m,
            theta_max_rad=theta_max_rad,
            lam=lam,
            lateral_decel_mps2=lateral_decel_mps2,
            w_left_slope=w_left_slope,
            w_right_slope=w_right_slope,
        )

    def _lane_widths(self, s_m: float, preview_m: float) -> tuple[float, float]:
        """Right and left half widths at ``s_m``: the narrowest over the next ``preview_m``
        (sampled every ``MAP_DS_M``) when previewing."""
        if preview_m <= 0.0:
            right, left = self.track.widths(s_m)
            return float(right), float(left)
        ahead = s_m + np.linspace(0.0, preview_m, 2 + math.ceil(preview_m / MAP_DS_M))
        rights, lefts = self.track.widths(ahead)
        return float(rights.min()), float(lefts.min())

    def speed_constraint(
        self, s_m: float, v_x: float, e_y_m: np.ndarray
    ) -> tuple[np.ndarray, float, float] | None:
        """Row, bound and barrier value of ``accel <= lam_1 h + dv_limit/ds * v_x``, at the
        lane offset (of ``e_y_m``) with the lowest limit; None without a speed limit. The
        offset's own rate is left out: the limit's fall with the offset is a blend, not a
        dynamics."""
        if self.speed_limit is None:
            return None
        limit, e_y = self.speed_limit.lowest(s_m, e_y_m)
        ahead = self.speed_limit(s_m + MAP_DS_M, e_y)
        slope = (ahead - limit) / MAP_DS_M
        h = limit - v_x
        return np.array([0.0, 1.0]), self.speed_gain * h + slope * max(v_x, 0.0), h
