"""What track-level planning needs to know about the car: its width and its limits."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class VehicleEnvelope:
    """Width and acceleration limits of the 1/10 car used for racing lines and speed profiles.

    Defaults describe the rc10 car (DESIGN.md section 3, ``assets/vehicles/rc10/README.md``):
    0.28 m track plus tyre width, about 7 m/s top speed, and grip of a rubber tyre on a
    smooth floor. Driving, the car accelerates at most at ``a_accel_max_mps2`` and at what
    its rear motors can push (:meth:`drive_accel_mps2`): their torque falls linearly to zero
    at the free speed, so above about 3 m/s the motor, not the grip, sets the acceleration.
    """

    width_m: float = 0.30
    v_max_mps: float = 7.0
    a_lat_max_mps2: float = 5.0
    a_accel_max_mps2: float = 4.0
    a_brake_max_mps2: float = 4.0
    #: The rear motors' stall force over the effective mass: 2 x 0.5 N m / 0.05 m / 3.77 kg.
    drive_accel_at_rest_mps2: float = 5.3
    #: Speed at which the motors' torque reaches zero: 150 rad/s x 0.05 m wheel radius.
    drive_free_speed_mps: float = 7.5
    #: Rolling losses per unit of speed: 4 wheels x 1e-4 N m s / (0.05 m)^2 / 3.77 kg.
    rolling_decel_per_s: float = 0.042

    def __post_init__(self) -> None:
        for name in (
            "width_m",
            "v_max_mps",
            "a_lat_max_mps2",
            "a_accel_max_mps2",
            "a_brake_max_mps2",
            "drive_accel_at_rest_mps2",
            "drive_free_speed_mps",
        ):
            if getattr(self, name) <= 0.0:
                raise ValueError(
                    f"VehicleEnvelope.{name} must be positive, got {getattr(self, name)}"
                )
        if self.rolling_decel_per_s < 0.0:
            raise ValueError(
                f"VehicleEnvelope.rolling_decel_per_s must not be negative, "
                f"got {self.rolling_decel_per_s}"
            )

    def drive_accel_mps2(self, speed_mps: float) -> float:
        """The most the car can speed up at ``speed_mps`` on a straight (m/s^2, >= 0)."""
        motor = self.drive_accel_at_rest_mps2 * max(
            0.0, 1.0 - speed_mps / self.drive_free_speed_mps
        )
        return max(0.0, min(self.a_accel_max_mps2, motor - self.rolling_decel_per_s * speed_mps))
