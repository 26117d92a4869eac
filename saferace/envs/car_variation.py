"""Per-episode variations of the car's physics, applied to the compiled model in place.

The chassis' mass and inertia, the tyre-road friction (the tyres' and the ground's, since
MuJoCo takes the larger of the two) and the motors' stall torque are scaled by factors drawn
from :class:`~saferace.envs.randomization.PhysicsRandomization`. The drivetrain's
feed-forward keeps the nominal mass: a controller does not know the car it drives.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import mujoco
import numpy as np

from saferace.envs.drivetrain import DrivetrainParams
from saferace.envs.randomization import PhysicsRandomization

TYRES = ("front_left_tyre", "front_right_tyre", "rear_left_tyre", "rear_right_tyre")


class CarVariation:
    """Draws car variations from ``ranges`` and applies them to ``model``."""

    def __init__(
        self, model: mujoco.MjModel, params: DrivetrainParams, ranges: PhysicsRandomization
    ) -> None:
        self.model, self.params, self.ranges = model, params, ranges
        self._chassis = model.body("chassis").id
        self._mass = float(model.body_mass[self._chassis])
        self._inertia = model.body_inertia[self._chassis].copy()
        self._contact_geoms = [model.geom(name).id for name in (*TYRES, "ground")]
        self._friction = model.geom_friction[self._contact_geoms, 0].copy()

    def apply(self, rng: np.random.Generator) -> tuple[DrivetrainParams, dict[str, Any]]:
        """Draw scales with ``rng``, write them into the model; the drivetrain to use and
        the scales drawn."""
        drawn = {
            name: float(rng.uniform(*getattr(self.ranges, name)))
            for name in ("mass_scale", "friction_scale", "motor_scale")
        }
        model = self.model
        model.body_mass[self._chassis] = self._mass * drawn["mass_scale"]
        model.body_inertia[self._chassis] = self._inertia * drawn["mass_scale"]
        model.geom_friction[self._contact_geoms, 0] = self._friction * drawn["friction_scale"]
        params = dataclasses.replace(
            self.params,
            motor_stall_torque_nm=self.params.motor_stall_torque_nm * drawn["motor_scale"],
        )
        return params, drawn
