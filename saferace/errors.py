"""Exceptions raised by SafeRace, each saying what was wrong and how to fix it."""


class SafeRaceError(Exception):
    """Base class of every error SafeRace raises on purpose."""


class TrackError(SafeRaceError, ValueError):
    """A track file or track arrays that cannot describe a drivable closed lane."""


class RacingLineError(SafeRaceError, RuntimeError):
    """The racing-line optimisation could not produce a line inside the lane."""


class ConfigError(SafeRaceError, ValueError):
    """A config field with a value it cannot take.

    ``field`` names the config field; the command line shows its option in its place.
    """

    def __init__(self, field: str, problem: str) -> None:
        super().__init__(f"{field} {problem}")
        self.field = field
        self.problem = problem
