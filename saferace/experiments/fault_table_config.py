"""What a fault table drives: tracks, drivers, faults and severities, the run's length, and
what feeds the default filter (light, so that the command line builds its options from it
fast; :mod:`saferace.experiments.fault_table` runs it)."""

from __future__ import annotations

from dataclasses import dataclass

from saferace.config import COUNT, NON_NEGATIVE, POSITIVE, Bounds, check_bounds, setting
from saferace.errors import ConfigError
from saferace.faults.spec import FAULT_KINDS, SEVERITIES
from saferace.names import FAULT_TABLE_DRIVERS, GENERIC_SOURCE, MC_SAMPLES

DRIVERS_HELP = (
    "the drivers: drift, weave, speeding (on the racing line), expert, learned:CHECKPOINT or "
    "MODULE:FACTORY"
)


@dataclass(frozen=True)
class FaultTableConfig:
    """One fault table: each of ``drivers`` on each of ``tracks`` and ``random_tracks``
    (seeds of random tracks), fault-free and with each of ``faults`` at each of
    ``severities``, without a filter and behind the default one fed ``state_source``."""

    tracks: tuple[str, ...] = setting(
        ("technical",), "built-in track names or track CSV paths", metavar="TRACK"
    )
    random_tracks: tuple[int, ...] = setting(
        (),
        "also random tracks of these seeds (written to OUT/tracks)",
        bounds=NON_NEGATIVE,
        metavar="SEED",
    )
    drivers: tuple[str, ...] = setting(FAULT_TABLE_DRIVERS, DRIVERS_HELP, metavar="DRIVER")
    faults: tuple[str, ...] = setting(
        tuple(FAULT_KINDS),
        f"the faults ({', '.join(FAULT_KINDS)}), each at every severity asked for, from 3 s "
        "into a run",
        choices=tuple(FAULT_KINDS),
        metavar="FAULT",
    )
    severities: tuple[int, ...] = setting(
        SEVERITIES,
        "the faults' severities (saferace.faults.spec gives their sizes)",
        metavar="SEVERITY",
        bounds=Bounds(minimum=min(SEVERITIES), maximum=max(SEVERITIES)),
    )
    seconds: float = setting(20.0, "simulated time of each run", bounds=POSITIVE)
    seed: int = setting(0, "every run's seed", bounds=NON_NEGATIVE)
    state_source: str = setting(
        GENERIC_SOURCE,
        "what the default filter is fed: the generic perception model (built once by saferace "
        "perception) or a calibrated checkpoint's state network",
        metavar="generic[:RECIPE]|learned:CKPT",
    )
    mc_samples: int = setting(MC_SAMPLES, "MC-dropout samples of the network", bounds=COUNT)

    def __post_init__(self) -> None:
        check_bounds(self)
        if not self.tracks and not self.random_tracks:
            raise ConfigError("tracks", "name at least one, or random tracks")
        for name in ("drivers", "faults", "severities"):
            values = getattr(self, name)
            if not values:
                raise ConfigError(name, "must name at least one")
            if len(set(values)) < len(values):
                raise ConfigError(name, f"names one twice: {', '.join(map(str, values))}")
        unknown = sorted(set(self.faults) - set(FAULT_KINDS))
        if unknown:
            known = ", ".join(FAULT_KINDS)
            raise ConfigError("faults", f"unknown {', '.join(unknown)}: use {known}")
        kind = self.state_source.partition(":")[0]
        if kind not in (GENERIC_SOURCE, "learned"):
            raise ConfigError(
                "state_source", f"must be generic[:RECIPE] or learned:CHECKPOINT, got {kind}"
            )
