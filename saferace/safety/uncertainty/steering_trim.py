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

Actuators that may apply commands up to ``max_delay_steps`` steps late (a declared bound,
:mod:`~saferace.safety.uncertainty.pending_commands`) would fool this: the servo modelled
without the delay turns the wheels early, and on the expert swinging under a 150 ms delay
the estimate made up a 0.03 rad offset, steering the car out of Monza's lane. So a servo is
modelled for every delay up to the bound, each with its own offset, and the delay is the
one whose angles the yaw rate follows best (the least spread of the differences, over
:data:`DELAY_TIME_CONSTANT_S`); a delay is taken over another only where it fits clearly
better, so a car that steers steadily, which tells delays apart not at all, keeps the one
it has.
"""

from __future__ import annotations

import math
from collections import deque

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
#: Two steps in a row this far (rad) from the estimate, beyond the step's turn of the wheels
#: (:meth:`ServoModel.surprising`), restart it: an offset that sets in is
#: taken from the steps since (their mean), not found over the memory's quarter second,
#: in which a 0.07 rad offset at 7 m/s took the expert out of a 0.7 m lane. Seven times the
#: spread of the yaw rate about the modelled wheels on a fault-free car.
RESTART_RAD = 0.015
#: The largest offset the estimate takes (rad): a servo further off centre is a broken
#: car, not one to trim, and a step whose yaw rate is further off the wheels says no offset
#: at all. A spinning car (its rear sliding out, the yaw past what the wheels set) read
#: 1.06 rad on Monza, and the filter's steering box behind that offset was empty. Twice the
#: largest offset of the steering fault (0.07 at severity 3).
MAX_OFFSET_RAD = 0.15
#: The memory (s) over which delays are compared.
DELAY_TIME_CONSTANT_S = 0.5
#: Another delay is taken where the spread of its differences is below this share of the
#: present one's, and by at least :data:`MIN_SPREAD_GAIN_RAD2`.
SPREAD_RATIO = 0.5
MIN_SPREAD_GAIN_RAD2 = 1e-5


class ServoModel:
    """Where the commands alone set the wheels, for commands applied ``delay_steps`` late,
    with the offset the yaw rate gives on top and how well it follows them."""

    def __init__(self, delay_steps: int) -> None:
        self.delay_steps = delay_steps
        self.estimate_rad = 0.0
        self.samples = self.surprises = 0
        self.target_rad = self.wheels_rad = 0.0
        self.turn_rad = 0.0
        self.mean_rad = self.square_rad2 = 0.0  # of the differences, for the spread

    def slew(self, command_rad: float, max_slew_rad: float, follow: float) -> None:
        """One step of the servo towards ``command_rad`` (the one that acts now): its target
        slews by at most ``max_slew_rad``, the wheels follow it by the share ``follow``."""
        step = command_rad - self.target_rad
        self.target_rad += min(max(step, -max_slew_rad), max_slew_rad)
        self.turn_rad = follow * (self.target_rad - self.wheels_rad)
        self.wheels_rad += self.turn_rad

    def compare(self, steered_rad: float, weight: float) -> None:
        """Take the angle the yaw rate says the wheels held into the spread of the
        differences, with ``weight``."""
        difference = steered_rad - self.wheels_rad
        self.mean_rad += weight * (difference - self.mean_rad)
        self.square_rad2 += weight * (difference**2 - self.square_rad2)

    @property
    def spread_rad2(self) -> float:
        """How far the yaw rate strays from these wheels, about its mean offset (rad^2)."""
        return max(self.square_rad2 - self.mean_rad**2, 0.0)

    def learn(self, steered_rad: float, rate: float, sliding: bool) -> None:
        """Take a step into the offset where the wheels held still in it and the tyres did
        not slide (``sliding``): a mean of the steps, then a memory of ``rate`` per step;
        restarted where the offset changed. A step that turned the wheels or slid still
        tells a change where neither explains it (:meth:`surprising`): a restart there takes
        its difference for a start, which the next clean step replaces. A step more than
        :data:`MAX_OFFSET_RAD` off the wheels tells nothing."""
        difference = steered_rad - self.wheels_rad
        if abs(difference) > MAX_OFFSET_RAD:  # a spin, or the wheels blocked: no offset
            return
        clean = not sliding and abs(self.turn_rad) <= MAX_WHEELS_TURN_RAD
        if self.surprising(difference, steered_rad, sliding):
            self.surprises += 1
            if self.surprises == 2:  # the offset changed: the steps from this one on
                self.samples = 0  # (the first, its yaw a moment behind the wheels, left out)
                self.estimate_rad = difference
        elif clean:
            self.surprises = 0
        if clean:
            self.samples += 1
            weight = max(1.0 / self.samples, rate)
            self.estimate_rad += weight * (difference - self.estimate_rad)

    def surprising(self, difference_rad: float, steered_rad: float, sliding: bool) -> bool:
        """Whether a step's ``difference_rad`` (the yaw rate's angle ``steered_rad`` less the
        modelled wheels) is more than :data:`RESTART_RAD` off the estimate beyond what the
        step explains: the yaw follows a turn of the wheels late, by up to the turn, and
        sliding front tyres turn the car less than the wheels say (a car turning more, its
        rear sliding out, is spinning: :meth:`learn` leaves out what no offset explains)."""
        surprise = difference_rad - self.estimate_rad
        if sliding and surprise * steered_rad <= 0.0:
            return False
        return abs(surprise) > RESTART_RAD + abs(self.turn_rad)


class SteeringTrim:
    """The offset ``offset_rad`` (positive: the wheels left of the command) of a car with
    ``wheelbase_m`` commanded every ``control_dt_s`` through a servo slewing at most
    ``max_steer_rate_radps`` and lagging by ``steer_time_constant_s``, and the delay
    ``delay_steps`` (up to ``max_delay_steps``) with which its commands act; :meth:`update`
    after each step with the command sent and the velocities measured at its end. Not
    ``applied``: estimated (``estimate_rad``) but never compensated (``offset_rad`` 0)."""

    def __init__(
        self,
        wheelbase_m: float,
        control_dt_s: float,
        steer_time_constant_s: float,
        max_steer_rate_radps: float,
        applied: bool = True,
        max_delay_steps: int = 0,
    ) -> None:
        self.wheelbase_m = wheelbase_m
        self.max_slew_rad = max_steer_rate_radps * control_dt_s
        self.follow = 1.0 - math.exp(-control_dt_s / steer_time_constant_s)
        self.rate = control_dt_s / TIME_CONSTANT_S
        self.delay_rate = control_dt_s / DELAY_TIME_CONSTANT_S
        self.applied = applied
        self.max_delay_steps = max_delay_steps
        self.reset()

    def reset(self) -> None:
        """Forget the estimates; the servo centred (as a task's reset leaves it), no delay."""
        self.servos = [ServoModel(delay) for delay in range(self.max_delay_steps + 1)]
        self.servo = self.servos[0]
        self.sent: deque[float] = deque([0.0] * self.max_delay_steps)
        self.compared = 0

    @property
    def estimate_rad(self) -> float:
        return self.servo.estimate_rad

    @property
    def samples(self) -> int:
        """The steps the present delay's estimate has taken in."""
        return self.servo.samples

    @property
    def delay_steps(self) -> int:
        """The steps late the commands act, as the yaw rate says (0 without a bound)."""
        return self.servo.delay_steps

    def update(self, command_rad: float, velocity: np.ndarray) -> None:
        """Take a step commanded ``command_rad`` that ended at ``velocity``
        (``[v_x, v_y, r]``) into the estimates, where it says anything (see the module)."""
        self.sent.append(command_rad)
        for servo in self.servos:
            servo.slew(self.sent[-1 - servo.delay_steps], self.max_slew_rad, self.follow)
        self.sent.popleft()
        v_x, yaw_rate = float(velocity[0]), float(velocity[2])
        if v_x < MIN_SPEED_MPS:
            return
        sliding = abs(v_x * yaw_rate) > MAX_LATERAL_ACCEL_MPS2
        steered_rad = math.atan(self.wheelbase_m * yaw_rate / v_x)
        for servo in self.servos:
            servo.learn(steered_rad, self.rate, sliding)
        if len(self.servos) > 1 and not sliding:
            self._compare(steered_rad)

    def _compare(self, steered_rad: float) -> None:
        self.compared += 1
        weight = max(1.0 / self.compared, self.delay_rate)
        for servo in self.servos:
            servo.compare(steered_rad, weight)
        best = min(self.servos, key=lambda servo: servo.spread_rad2)
        present = self.servo.spread_rad2
        if best.spread_rad2 < SPREAD_RATIO * present and present - best.spread_rad2 > (
            MIN_SPREAD_GAIN_RAD2
        ):
            self.servo = best

    @property
    def offset_rad(self) -> float:
        """The offset to compensate: the estimate, or 0 within :data:`DEADBAND_RAD` (or
        where not ``applied``)."""
        applies = self.applied and abs(self.estimate_rad) > DEADBAND_RAD
        return self.estimate_rad if applies else 0.0
