"""The steering's centre offset, estimated online from the odometry's yaw rate.

A servo a few degrees off centre turns the car while the filter thinks it steers straight:
0.07 rad on a 0.33 m wheelbase is a 4.7 m circle. While the filter certifies frame by
frame, its barriers feed back the drift; but a fallback that stops the car blind (the
camera in doubt) steers the lane's curvature open loop, and off centre it stopped the
drifting driver outside ``lab``'s lane for 35 s of 40. The car's own motion gives the
offset away: within the tyres' grip, the kinematic bicycle's yaw rate
``r = v_x tan(delta) / L`` says which angle the wheels hold, and its difference to the
angle the commands would have set (through the servo's rate limit and lag) is the offset.
Over 4,676 steps of four drivers behind the filter on the four built-in tracks, with and
without an offset, the two matched to 0.002 rad (one standard deviation, 0.0005 on
average) up to 7 m/s^2, in bends of any radius; beyond, the tyres slide (0.02 rad short
above 9 m/s^2). A wrong
speed scale (a biased odometry) drops out of the ratio ``r / v_x``; noise averages out.
Offsets within :data:`DEADBAND_RAD` are left alone: the lane margin the filter keeps
covers them, and a fault-free car's commands pass untouched.
"""

from __future__ import annotations

import math

import numpy as np

#: Steps below this speed (m/s) say nothing: the yaw rate vanishes with it.
MIN_SPEED_MPS = 1.0
#: Steps turning harder than this (m/s^2) are skipped: the tyres slide there, and the
#: kinematic bicycle over-promises the turn.
MAX_LATERAL_ACCEL_MPS2 = 7.0
#: Steps over which the wheels turned more than this (rad) are skipped: the car's yaw
#: follows the wheels a moment late (the first step of a 0.1 rad turn read 0.054).
MAX_WHEELS_TURN_RAD = 0.02
#: The estimate's memory (s): an offset found within about a quarter of a second of driving.
TIME_CONSTANT_S = 0.25
#: An estimate this small (rad) is not applied: inside the lane margin, and the bicycle's
#: mismatch on a fault-free car stays below it.
DEADBAND_RAD = 0.01


class SteeringTrim:
    """The offset ``offset_rad`` (positive: the wheels left of the command) of a car with
    ``wheelbase_m`` commanded every ``control_dt_s`` through a servo slewing at most
    ``max_steer_rate_radps`` and lagging by ``steer_time_constant_s``; :meth:`update` after
    each step with the command sent and the velocities measured at its end. Not
    ``applied``: estimated (``estimate_rad``) but never compensated (``offset_rad`` 0)."""

    def __init__(
        self,
        wheelbase_m: float,
        control_dt_s: float,
        steer_time_constant_s: float,
        max_steer_rate_radps: float,
        applied: bool = True,
    ) -> None:
        self.wheelbase_m = wheelbase_m
        self.max_slew_rad = max_steer_rate_radps * control_dt_s
        self.follow = 1.0 - math.exp(-control_dt_s / steer_time_constant_s)
        self.rate = control_dt_s / TIME_CONSTANT_S
        self.applied = applied
        self.reset()

    def reset(self) -> None:
        """Forget the estimate; the servo centred (as a task's reset leaves it)."""
        self.estimate_rad = 0.0
        self.samples = 0
        self._target_rad = self._wheels_rad = 0.0  # where the commands alone set them

    def update(self, command_rad: float, velocity: np.ndarray) -> None:
        """Take a step commanded ``command_rad`` that ended at ``velocity``
        (``[v_x, v_y, r]``) into the estimate, where it says anything (see the module)."""
        slew = command_rad - self._target_rad
        self._target_rad += min(max(slew, -self.max_slew_rad), self.max_slew_rad)
        turn_rad = self.follow * (self._target_rad - self._wheels_rad)
        self._wheels_rad += turn_rad
        v_x, yaw_rate = float(velocity[0]), float(velocity[2])
        if abs(turn_rad) > MAX_WHEELS_TURN_RAD or v_x < MIN_SPEED_MPS:
            return
        if abs(v_x * yaw_rate) > MAX_LATERAL_ACCEL_MPS2:
            return
        steered_rad = math.atan(self.wheelbase_m * yaw_rate / v_x)
        self.samples += 1
        weight = max(1.0 / self.samples, self.rate)
        self.estimate_rad += weight * (steered_rad - self._wheels_rad - self.estimate_rad)

    @property
    def offset_rad(self) -> float:
        """The offset to compensate: the estimate, or 0 within :data:`DEADBAND_RAD` (or
        where not ``applied``)."""
        applies = self.applied and abs(self.estimate_rad) > DEADBAND_RAD
        return self.estimate_rad if applies else 0.0
