"""Collisions between cars, read from MuJoCo's contact list, with the car at fault.

Every car has a massless ``bumper`` box around its wheels and body that collides only with
the other cars' bumpers. A collision starts when two bumpers touch that had not touched
for ``SEPARATION_S`` (cars that bounce against each other touch on and off), and is
reported once, with both cars, the time, their relative speed and
the car at fault under the usual racing rule:

- one car behind the other (their centres more than ``ALONGSIDE_M`` apart along the
  track): the car behind, which ran into the car ahead, is at fault (unless the car ahead
  backed into it faster);
- alongside: the car that moved sideways into the other (the larger lateral speed toward
  it) is at fault.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from saferace.envs.car_io import CarIO
from saferace.names import RC10_BUMPER_HALF_EXTENTS_M

#: Two cars whose centres are closer than this along the track are alongside (m): about
#: half the car's 0.45 m length, so that a car nosing into another's flank is alongside.
ALONGSIDE_M = 0.25
#: Two cars touching again within this time of their last touch are still in one collision (s).
SEPARATION_S = 0.5
#: Two bumpers cannot touch while their centres are further apart than this (m): the
#: distance from the centre to a bumper's corner, twice.
BUMPER_REACH_M = 2.0 * math.hypot(*RC10_BUMPER_HALF_EXTENTS_M)
#: The fastest two cars close on each other (m/s): each at most 8 m/s.
MAX_CLOSING_MPS = 16.0


@dataclass(frozen=True)
class CarMotion:
    """A car's position and velocity in the world's x-y plane at a collision."""

    position_m: np.ndarray
    velocity_mps: np.ndarray


@dataclass(frozen=True)
class Collision:
    """Two cars' bumpers touching, from the first contact on."""

    time_s: float
    cars: tuple[str, str]
    at_fault: str
    kind: str  # "rear-end" or "side"
    relative_speed_mps: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "time_s": self.time_s,
            "cars": list(self.cars),
            "at_fault": self.at_fault,
            "kind": self.kind,
            "relative_speed_mps": self.relative_speed_mps,
        }


def attribute_fault(
    first: CarMotion, second: CarMotion, track_tangent: np.ndarray
) -> tuple[int, str]:
    """``(index of the car at fault, kind)`` of a collision of ``first`` and ``second`` on a
    track whose direction of travel there is the unit vector ``track_tangent``."""
    tangent = np.asarray(track_tangent, float)
    normal = np.array([-tangent[1], tangent[0]])
    offset = second.position_m - first.position_m
    along = float(offset @ tangent)
    if abs(along) > ALONGSIDE_M:  # the one closing the gap: the car behind, unless the car
        behind, ahead = (0, 1) if along > 0.0 else (1, 0)  # ahead backs into it
        motions = (first, second)
        closing_behind = float(motions[behind].velocity_mps @ tangent)
        closing_ahead = -float(motions[ahead].velocity_mps @ tangent)
        return (behind if closing_behind >= closing_ahead else ahead), "rear-end"
    side = 1.0 if offset @ normal >= 0.0 else -1.0  # where the second car is, seen by the first
    first_toward = float(first.velocity_mps @ normal) * side
    second_toward = -float(second.velocity_mps @ normal) * side
    return (0 if first_toward >= second_toward else 1), "side"


class CollisionMonitor:
    """Finds the cars' collisions: :meth:`check` after every physics substep, :meth:`collect`
    once per control step for the collisions that started during it."""

    def __init__(self, data: mujoco.MjData, cars: list[CarIO], names: list[str]) -> None:
        self.data, self.cars, self.names = data, cars, names
        bumpers = [car.model.geom(car.prefix + "bumper").id for car in cars]
        self._car_of_bumper = {geom: index for index, geom in enumerate(bumpers)}
        self._last_touch_s: dict[tuple[int, int], float] = {}
        self._started: list[tuple[float, int, int, CarMotion, CarMotion]] = []

    def may_touch(self, duration_s: float) -> bool:
        """Whether any two cars could touch within ``duration_s`` (checking the contacts
        after every substep costs a tenth of a two-car step)."""
        reach = BUMPER_REACH_M + MAX_CLOSING_MPS * duration_s
        positions = self.data.xpos[[car.chassis for car in self.cars], :2].tolist()
        return any(
            math.dist(first, second) < reach
            for index, first in enumerate(positions)
            for second in positions[index + 1 :]
        )

    def pending(self) -> bool:
        """Whether collisions have started since the last :meth:`collect`."""
        return bool(self._started)

    def get_state(self) -> dict[str, Any]:
        return {"last_touch_s": dict(self._last_touch_s), "started": list(self._started)}

    def set_state(self, state: dict[str, Any]) -> None:
        self._last_touch_s = dict(state["last_touch_s"])
        self._started = list(state["started"])

    def reset(self) -> None:
        self._last_touch_s = {}
        self._started = []

    def check(self) -> None:
        """Note the pairs of cars touching now, and each pair whose collision starts now."""
        data = self.data
        if not data.ncon:
            return
        time_s = float(data.time)
        car_of = self._car_of_bumper
        for first_geom, second_geom in data.contact.geom[: data.ncon]:
            first, second = car_of.get(int(first_geom)), car_of.get(int(second_geom))
            if first is None or second is None:
                continue
            pair = (min(first, second), max(first, second))
            last = self._last_touch_s.get(pair)
            if last is None or time_s - last > SEPARATION_S:
                motions = (self._motion(pair[0]), self._motion(pair[1]))
                self._started.append((time_s, *pair, *motions))
            self._last_touch_s[pair] = time_s

    def collect(self, track_tangents: list[np.ndarray]) -> list[Collision]:
        """The collisions started since the last call; ``track_tangents[i]`` is the direction
        of travel along the track at car ``i``."""
        collisions = []
        for time_s, first, second, first_motion, second_motion in self._started:
            fault, kind = attribute_fault(first_motion, second_motion, track_tangents[first])
            relative = float(np.linalg.norm(first_motion.velocity_mps - second_motion.velocity_mps))
            collisions.append(
                Collision(
                    time_s=time_s,
                    cars=(self.names[first], self.names[second]),
                    at_fault=self.names[(first, second)[fault]],
                    kind=kind,
                    relative_speed_mps=relative,
                )
            )
        self._started = []
        return collisions

    def _motion(self, index: int) -> CarMotion:
        """Car ``index``'s position and velocity when the contact list was made: both from
        the step's start (``qvel`` is already past the contact's impulse)."""
        car = self.cars[index]
        velocity = np.empty(6)  # [angular; linear], in the world frame
        mujoco.mj_objectVelocity(
            car.model, self.data, mujoco.mjtObj.mjOBJ_BODY, car.chassis, velocity, 0
        )
        return CarMotion(
            position_m=self.data.xpos[car.chassis, :2].copy(), velocity_mps=velocity[3:5]
        )
