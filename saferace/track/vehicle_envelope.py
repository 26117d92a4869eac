"""What track-level planning needs to know about the car: its width and its limits."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class VehicleEnvelope:
    """Width and acceleration limits of the 1/10 car used for racing lines and speed profiles.

    Defaults describe the rc10 car (DESIGN.md section 3): 0.28 m track plus tyre width,
    about 7 m/s top speed, and grip of a rubber tyre on a smooth floor.
    """

    width_m: float = 0.30
    v_max_mps: float = 7.0
    a_lat_max_mps2: float = 5.0
    a_accel_max_mps2: float = 4.0
    a_brake_max_mps2: float = 4.0

    def __post_init__(self) -> None:
        for name in (
            "width_m",
            "v_max_mps",
            "a_lat_max_mps2",
            "a_accel_max_mps2",
            "a_brake_max_mps2",
        ):
            if getattr(self, name) <= 0.0:
                raise ValueError(
                    f"VehicleEnvelope.{name} must be positive, got {getattr(self, name)}"
                )
