"""Track geometry: centerlines, Frenet frames, racing lines and speed profiles."""

from saferace.track.frenet import FrenetProjector, wrap_angle
from saferace.track.path import ClosedPath
from saferace.track.track import Track, builtin_track_names
from saferace.track.vehicle_envelope import VehicleEnvelope

__all__ = [
    "ClosedPath",
    "FrenetProjector",
    "Track",
    "VehicleEnvelope",
    "builtin_track_names",
    "wrap_angle",
]
