"""Sensor and actuator faults, seeded and named as strings (see :mod:`.spec`)."""

from saferace.faults.spec import (
    ACTUATOR_FAULTS,
    CAMERA_FAULTS,
    FAULT_KINDS,
    ODOMETRY_FAULTS,
    Fault,
    FaultError,
    parse_faults,
)
from saferace.faults.wrapper import SensorFaults, with_faults

__all__ = [
    "ACTUATOR_FAULTS",
    "CAMERA_FAULTS",
    "FAULT_KINDS",
    "ODOMETRY_FAULTS",
    "Fault",
    "FaultError",
    "SensorFaults",
    "parse_faults",
    "with_faults",
]
