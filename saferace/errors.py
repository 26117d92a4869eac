"""Exceptions raised by SafeRace, each saying what was wrong and how to fix it."""


class SafeRaceError(Exception):
    """Base class of every error SafeRace raises on purpose."""


class TrackError(SafeRaceError, ValueError):
    """A track file or track arrays that cannot describe a drivable closed lane."""


class RacingLineError(SafeRaceError, RuntimeError):
    """The racing-line optimisation could not produce a line inside the lane."""
