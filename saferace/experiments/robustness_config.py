"""What a robustness evaluation drives: agent, task, track, looks, seeds, filter (light, so
that the command line builds its options from it fast)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from saferace.config import COUNT, IMAGE_SIZE, NON_NEGATIVE, POSITIVE, check_bounds, setting
from saferace.errors import ConfigError
from saferace.eval.filter_config import FilterConfig
from saferace.faults.spec import FaultError, canonical_faults
from saferace.names import DEFAULT_EXPERT_MODEL, FAULTS_HELP, MC_SAMPLES, TASKS, VEHICLE_MODELS

AGENT_HELP = "expert, pure-pursuit, drift, weave, speeding, learned:CHECKPOINT or MODULE:FACTORY"


@dataclass(frozen=True)
class RobustnessConfig:
    """One robustness evaluation: ``agent`` on ``task`` and each of ``tracks`` in each
    preset's (or shift severity's) looks.

    ``physics``: the car varies with the same preset too. ``monitor_state_source``
    (``learned:CKPT``): a state network scored beside an unfiltered run; a filtered run
    scores the one that feeds the filter.
    """

    agent: str = setting("expert", AGENT_HELP)
    task: str = setting("RacingLine", "the reference line to follow", choices=TASKS)
    tracks: tuple[str, ...] = setting(
        ("technical",), "built-in track names or track CSV paths", flag="--track", metavar="TRACK"
    )
    presets: tuple[str, ...] = setting(
        ("none", "mild", "strong"),
        "looks to drive in: presets, or shift severities severity-0 (the training look) .. "
        "severity-5",
        metavar="LOOK",
    )
    seeds: tuple[int, ...] = setting((0, 1, 2), "a look per seed", bounds=NON_NEGATIVE)
    laps: int = setting(1, "laps per run", bounds=COUNT)
    max_seconds: float | None = setting(
        60.0, "end a run after this much simulated time", bounds=POSITIVE
    )
    physics: bool = setting(False, "the car varies with the same preset too")
    faults: tuple[str, ...] = setting((), FAULTS_HELP, metavar="NAME[:KEY=VALUE,...]")
    safety: FilterConfig = field(default_factory=FilterConfig)
    monitor_state_source: str | None = setting(
        None,
        "score this state network beside an unfiltered run (a filtered run scores its own)",
        flag="--monitor-state",
        metavar="learned:CKPT",
    )
    model: str = setting(DEFAULT_EXPERT_MODEL, "the expert's vehicle model", choices=VEHICLE_MODELS)
    image_size: int = setting(64, "onboard image height and width", bounds=IMAGE_SIZE)
    stereo: bool = setting(False, "stereo camera pair (6 channels)")
    mc_samples: int = setting(
        MC_SAMPLES, "MC-dropout samples per step of a learned agent", bounds=COUNT
    )

    def __post_init__(self) -> None:
        check_bounds(self)
        for name in ("tracks", "presets", "seeds"):
            if not getattr(self, name):
                raise ConfigError(name, "must name at least one")
        try:
            faults = canonical_faults(self.faults)
        except FaultError as exc:
            raise ConfigError("faults", str(exc)) from exc
        object.__setattr__(self, "faults", faults)  # as written out: one key per run
        source = self.monitor_state_source
        if source is not None and not source.startswith("learned:"):
            raise ConfigError("monitor_state_source", f"must be learned:CHECKPOINT, got {source}")
        if source is not None and self.safety.state_source is not None:
            raise ConfigError(
                "monitor_state_source",
                "is not needed: the filter's state source is scored already",
            )

    def as_dict(self) -> dict:
        values = asdict(self)
        values["safety"] = self.safety.as_dict()
        return values
