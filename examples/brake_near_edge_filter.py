"""A minimal safety filter: ``--filter brake_near_edge_filter:make``.

It leaves the driver alone until the perceived interval comes within a margin of a lane
edge (more, the faster the car closes on it while it stops), or the perception is in doubt,
or the car is too fast for the tyres' grip in a bend it would reach while stopping. Then it
brakes to a stop, steering to the centre line, until the car heads along the lane: it may
stay stopped (safe, not live).
"""

from __future__ import annotations

import numpy as np

from saferace.safety.filter_protocol import FilterSetup, FilterView

#: Room (m) kept between the car's side and the edge, however slow the car.
MARGIN_M = 0.1
#: The lateral acceleration (m/s^2) the tyres hold: faster into the bend ahead brakes.
GRIP_MPS2 = 6.0
#: Steering back (rad) per metre off the centre line and per radian of heading to it; the
#: heading (rad) beyond which the driver does not get the car back.
OFFSET_GAIN_RADPM, HEADING_GAIN, MAX_HEADING_RAD = 0.6, 1.0, 0.6


class BrakeNearEdge:
    """Brake to a stop, steering to the centre, when the interval nears an edge."""

    def __init__(self, setup: FilterSetup) -> None:
        self.setup = setup
        self.brake_mps2 = -float(setup.action_low[1])

    def reset(self, seed: int | None = None) -> None:
        """Nothing carried between steps."""

    def certify(self, action: np.ndarray, view: FilterView) -> np.ndarray:
        w_right_m, w_left_m = self.setup.track.widths(view.s_m)
        room_left_m = float(w_left_m) - self.setup.car_half_width_m - view.upper[0]
        room_right_m = float(w_right_m) - self.setup.car_half_width_m + view.lower[0]
        speed_mps = max(float(view.velocity[0]), 0.0)
        stop_s = speed_mps / self.brake_mps2
        heading = max(abs(view.lower[1]), abs(view.upper[1]))
        drift_m = speed_mps * np.sin(heading) * (self.setup.control_dt_s + stop_s / 2)  # edgewards
        clear_m = min(room_left_m, room_right_m) - MARGIN_M - drift_m
        if clear_m > 0 and heading < MAX_HEADING_RAD and not view.in_doubt:
            ahead_m = view.s_m + np.linspace(0.0, speed_mps * stop_s, 5)
            kappa = max(abs(self.setup.track.centerline.curvature_scalar(s)) for s in ahead_m)
            too_fast = speed_mps**2 * kappa > GRIP_MPS2
            return np.array([action[0], self.stopping_mps2(speed_mps)]) if too_fast else action
        steer = -OFFSET_GAIN_RADPM * view.mean[0] - HEADING_GAIN * view.mean[1]
        low, high = self.setup.action_low, self.setup.action_high
        return np.array([np.clip(steer, low[0], high[0]), self.stopping_mps2(speed_mps)])

    def stopping_mps2(self, speed_mps: float) -> float:
        """Brake as hard as the car can, but not past a stop into reverse."""
        return -min(self.brake_mps2, speed_mps / self.setup.control_dt_s)


def make(setup: FilterSetup) -> BrakeNearEdge:
    return BrakeNearEdge(setup)
