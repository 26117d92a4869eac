"""Sensor and actuator faults, seeded and named as strings (see :mod:`.spec`)."""

from saferace.faults.spec import (
    FAULT_KINDS,
    Fault,
    FaultError,
    parse_faults,
)
from saferace.faults.wrapper import SensorFaults, with_faults

__all__ = [
    "FAULT_KINDS",
    "Fault",
    "FaultError",
    "SensorFaults",
    "parse_faults",
    "with_faults",
]
