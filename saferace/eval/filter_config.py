"""Safety-filter settings: which filter wraps the agent and what state it sees.

Import-light (no gymnasium, no solver), so that the command line can build its options
from :class:`FilterConfig` fast; :mod:`saferace.eval.filters` applies it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from saferace.config import COUNT, NON_NEGATIVE, POSITIVE, Bounds, check_bounds, setting
from saferace.errors import ConfigError
from saferace.names import (
    ADAPTIVE_FEEDBACK as FEEDBACK_KINDS,
)
from saferace.names import (
    AUTO,
    DEFAULT_FILTER_MODELS,
    DEFAULT_GAINS,
    FILTER_KINDS,
    GAIN_NAMES,
    GENERIC_SOURCE,
    NOISY_SAMPLES,
    ROBUST_GAINS,
    SLACK_PENALTIES,
    SQUARED_SLACK,
    UNCERTAINTY_MODES,
    VEHICLE_MODELS,
)

#: State sources of the packages above ``eval``, as ``KIND:ARGUMENT``: loaded on first use,
#: ``FACTORY(ARGUMENT, IMAGE_SHAPE, n_samples=N, seed=S)`` (a checkpoint's state network:
#: ``learned:CHECKPOINT``; the generic perception model: ``generic`` or ``generic:RECIPE``).
STATE_SOURCE_FACTORIES = {
    "learned": "saferace.learning.agent:learned_state_source",
    "generic": "saferace.learning.perception:generic_state_source",
}
#: The state sources whose argument may be left out.
OPTIONAL_ARGUMENT_SOURCES = ("generic",)


#: The settings of :class:`FilterConfig` that a filter of the user's has: the state it is fed.
USERS_FILTER_SETTINGS = (
    "kind", "state_noise", "samples", "state_source", "own_track_calibration", "spread_scale",
    "adaptive", "fuse_odometry",
)  # fmt: skip


def users_filter(kind: str) -> bool:
    """Whether ``kind`` names a user's safety filter, ``MODULE:FACTORY``
    (:mod:`saferace.safety.filter_protocol`), not one of ours."""
    module, _, factory = kind.partition(":")
    return bool(module and factory)


def users_perception(state_source: str) -> bool:
    """Whether ``state_source`` names a user's perception method, ``MODULE:FACTORY``
    (:mod:`saferace.safety.uncertainty.perception`), not one of :data:`STATE_SOURCE_FACTORIES`."""
    return state_source.partition(":")[0] not in STATE_SOURCE_FACTORIES


@dataclass(frozen=True)
class FilterConfig:
    """Which filter wraps the agent and what state it sees.

    The state source is the oracle unless ``state_noise`` ``(e_y_m, e_psi_rad)`` standard
    deviations make it a noisy oracle with ``samples`` samples, or ``state_source`` names a
    learned one (``learned:CHECKPOINT``: the state network's ``samples`` MC-dropout samples,
    the perceived state; a bare ``learned`` is a placeholder that a DAgger run fills with
    its iteration's checkpoint). ``spread_scale`` widens the samples about their mean (a
    calibration of the MC-dropout spread,
    :class:`~saferace.safety.uncertainty.state_sources.SpreadScaledStateSource`);
    ``fuse_odometry`` fuses them with odometry
    (:class:`~saferace.safety.uncertainty.state_fusion.OdometryFusedStateSource`).

    ``uncertainty`` and ``gains`` left at ``auto`` are settled when the config is made (see
    :data:`saferace.names.AUTO`): with a learned state source the robust mode (which takes
    the curvature from the map) and :data:`~saferace.names.ROBUST_GAINS`; otherwise, and
    where an option of the chance constraints is set (``probabilistic=False``,
    ``spread_scale``, ``fuse_odometry``: each hides a calibrated source's interval and
    monitor), the paper's chance constraints and :data:`~saferace.names.DEFAULT_GAINS`. A
    copy made with ``replace`` keeps what was settled.
    """

    kind: str = setting(
        "none",
        "wrap the agent in a safety filter: none, ours (cbf, mpsf) or one of your own",
        flag="--filter",
        metavar="|".join((*FILTER_KINDS, "MODULE:FACTORY")),
    )
    model: str = setting(
        AUTO,
        "the filter's vehicle model; auto: "
        + ", ".join(f"{model} for {kind}" for kind, model in DEFAULT_FILTER_MODELS.items()),
        flag="--filter-model",
        choices=(AUTO, *VEHICLE_MODELS),
    )
    state_noise: tuple[float, float] | None = setting(
        None,
        "the filter sees noisy state samples with these standard deviations",
        metavar=("E_Y_M", "E_PSI_RAD"),
        bounds=NON_NEGATIVE,
    )
    samples: int = setting(NOISY_SAMPLES, "state samples per step", bounds=COUNT)
    probabilistic: bool = setting(
        True,
        "filter on the samples' mean instead of with chance constraints",
        flag="--deterministic",
    )
    eta: float = setting(
        0.95, "the chance constraints' confidence level", bounds=Bounds(minimum=0.5, below=1)
    )
    gains: str = setting(
        AUTO,
        "the filter's settings: the paper's gain, the same with the steering held within the "
        "tyres' grip (drivable at racing speed), the gains measured to cost the expert "
        "least on the built-in tracks (tuned), or those within the grip (tuned-grip); auto: "
        f"{ROBUST_GAINS} in the robust mode (an uncertain heading keeps its speed), "
        f"{DEFAULT_GAINS} otherwise",
        flag="--filter-gains",
        choices=(AUTO, *GAIN_NAMES),
    )
    state_source: str | None = setting(
        None,
        "what feeds the filter the lane state",
        metavar="oracle|noisy|generic[:RECIPE]|learned:CKPT|MODULE:FACTORY",
    )
    own_track_calibration: bool = setting(
        False,
        "with --state-source generic: its interval and monitor calibrated on the run's own "
        "track (the expert drives it with steering noise for about a minute, once; cached by "
        "the track's hash) instead of pooled over random tracks",
    )
    map_curvature: bool = setting(
        False,
        "the filter takes the centerline's curvature from the map at the car's s instead of "
        "from the state source (a state network judges it worst; always in the robust mode)",
    )
    spread_scale: tuple[float, float, float] | None = setting(
        None,
        "widen the state samples' spread about their mean by these factors (a calibration of "
        "the state network's, see `saferace dagger --calibrate-spread`)",
        metavar=("E_Y", "E_PSI", "KAPPA"),
        bounds=POSITIVE,
    )
    uncertainty: str = setting(
        AUTO,
        "how the filter treats the state's uncertainty: chance constraints on the samples' "
        "spread (the paper's), or barriers that hold over the whole interval (a learned "
        "source's conformal one) with a fallback that slows the car where they cannot, or "
        "where the source's monitor raises; auto: robust with the map's curvature for a "
        "learned state source, chance otherwise and with --deterministic, --spread-scale or "
        "--fuse-odometry",
        flag="--filter-uncertainty",
        choices=(AUTO, *UNCERTAINTY_MODES),
    )
    adaptive: str | None = setting(
        None,
        "adapt a calibrated learned source's interval online (adaptive conformal inference) "
        "from the truth a step late (oracle feedback, which no real car has) or from the "
        "odometry's prediction",
        flag="--adaptive-conformal",
        choices=FEEDBACK_KINDS,
    )
    fuse_odometry: bool = setting(
        False,
        "fuse the state samples with odometry (yaw rate, speed, the map's curvature) in a "
        "Kalman filter that leaves out outliers",
    )
    slack: str = setting(
        SQUARED_SLACK,
        "the filter QP's penalty on its slacks: squared (the paper's: each active constraint "
        "gives a little) or the exact l1 (the hard constraints wherever they can hold)",
        flag="--filter-slack",
        choices=SLACK_PENALTIES,
    )

    opponent_noise_m: float = setting(
        0.0,
        "in traffic: the standard deviation (m) of the noise on the opponents' positions the "
        "filter's car barriers see, which widen by it (0: their true positions)",
        flag="--opponent-noise",
        metavar="M",
        bounds=NON_NEGATIVE,
    )

    def __post_init__(self) -> None:
        check_bounds(self)
        learned = self.state_source is not None
        chance_options = not self.probabilistic or self.spread_scale or self.fuse_odometry
        if self.uncertainty == AUTO:
            robust = learned and not chance_options
            object.__setattr__(self, "uncertainty", "robust" if robust else "chance")
        if self.model == AUTO:
            default = DEFAULT_FILTER_MODELS.get(self.kind, DEFAULT_FILTER_MODELS["cbf"])
            object.__setattr__(self, "model", default)
        if self.gains == AUTO:
            robust = self.uncertainty == "robust"
            object.__setattr__(self, "gains", ROBUST_GAINS if robust else DEFAULT_GAINS)
        if self.kind not in FILTER_KINDS and not users_filter(self.kind):
            raise ConfigError(
                "kind",
                f"must be one of {', '.join(FILTER_KINDS)} or MODULE:FACTORY (a filter of your "
                f"own), got {self.kind!r}",
            )
        if users_filter(self.kind):
            self._check_own_filter()
        if self.gains not in GAIN_NAMES:
            raise ConfigError(
                "gains", f"must be one of {', '.join(GAIN_NAMES)}, got {self.gains!r}"
            )
        if self.uncertainty not in UNCERTAINTY_MODES:
            raise ConfigError(
                "uncertainty",
                f"must be one of {', '.join(UNCERTAINTY_MODES)}, got {self.uncertainty!r}",
            )
        source_kind = (self.state_source or "").partition(":")[0]
        if self.own_track_calibration and source_kind != GENERIC_SOURCE:
            raise ConfigError(
                "own_track_calibration",
                "calibrates the generic perception model: use it with --state-source generic "
                f"(the state source is {self.state_source or 'the oracle'})",
            )
        if self.kind == "mpsf" and self.opponent_noise_m:
            raise ConfigError(
                "opponent_noise_m",
                "is the CBF filter's car barriers': the predictive filter (mpsf) has none",
            )
        if self.slack not in SLACK_PENALTIES:
            raise ConfigError(
                "slack", f"must be one of {', '.join(SLACK_PENALTIES)}, got {self.slack!r}"
            )
        if self.kind == "mpsf" and self.slack != SQUARED_SLACK:
            raise ConfigError(
                "slack", "is the CBF filter's QP penalty: the predictive filter (mpsf) has none"
            )
        if self.model not in VEHICLE_MODELS:
            raise ConfigError(
                "model",
                f"must be one of {', '.join(VEHICLE_MODELS)}, got {self.model!r}",
            )
        if self.state_noise is not None and len(self.state_noise) != 2:
            raise ConfigError(
                "state_noise",
                f"must be two standard deviations (e_y_m, e_psi_rad), got {self.state_noise}",
            )
        if self.samples < (2 if self.state_noise is not None else 1):
            raise ConfigError(
                "samples", f"must be at least 1 (2 for noisy state), got {self.samples}"
            )
        if self.state_source is not None:
            kind, _, factory = self.state_source.partition(":")
            if users_perception(self.state_source) and not (kind and factory):
                raise ConfigError(
                    "state_source",
                    "must be oracle, noisy, generic[:RECIPE], learned:CHECKPOINT or "
                    f"MODULE:FACTORY (a perception method of your own), got "
                    f"{self.state_source!r}",
                )
            if self.state_noise is not None:
                raise ConfigError(
                    "state_noise", "is for the noisy oracle, not a learned state source"
                )
            if users_perception(self.state_source):
                self._check_own_perception()
        if self.adaptive is not None and (
            self.adaptive not in FEEDBACK_KINDS or self.state_source is None
        ):
            raise ConfigError(
                "adaptive",
                f"adapts a calibrated learned state source's interval with feedback "
                f"{' or '.join(FEEDBACK_KINDS)}, got {self.adaptive!r} with state source "
                f"{self.state_source!r}",
            )
        if self.fuse_odometry and self.state_source is None and self.state_noise is None:
            raise ConfigError(
                "fuse_odometry", "fuses an uncertain state source (noisy or learned), not the truth"
            )
        if self.spread_scale is not None and len(self.spread_scale) != 3:
            raise ConfigError(
                "spread_scale", f"must be 3 factors (e_y, e_psi, kappa), got {self.spread_scale}"
            )

    def _check_own_filter(self) -> None:
        """A filter of the user's is handed the state source's estimate and interval
        (:mod:`saferace.safety.filter_protocol`): our filters' own settings are not its."""
        ours = {
            "slack": self.slack != SQUARED_SLACK,
            "opponent_noise_m": self.opponent_noise_m != 0.0,
            "map_curvature": self.map_curvature,
        }
        for name, asked in ours.items():
            if asked:
                raise ConfigError(
                    name, f"is a setting of our filters, not of your own ({self.kind})"
                )

    @property
    def uncertain_state(self) -> bool:
        """Whether the filter sees an estimate (noisy or learned) rather than the truth."""
        return self.state_source is not None or self.state_noise is not None

    def _check_own_perception(self) -> None:
        """A perception method of the user's gives one estimate and its interval a step: it
        feeds the robust filter alone, as it is (no samples to take chance constraints on,
        to widen, fuse or adapt)."""
        chance_options = {
            "uncertainty": self.uncertainty != "robust",
            "probabilistic": not self.probabilistic,
            "spread_scale": self.spread_scale is not None,
            "fuse_odometry": self.fuse_odometry,
            "adaptive": self.adaptive is not None,
        }
        for name, asked in chance_options.items():
            if asked:
                raise ConfigError(
                    name,
                    f"is not for a perception method of your own ({self.state_source}): it "
                    "feeds the robust filter its estimate and interval as they are",
                )

    @property
    def label(self) -> str:
        """Short name for tables: ``none``, ``oracle``, ``noisy-prob``, ``noisy-det``,
        ``learned-prob`` or ``learned-det`` (``noisy-fused-prob`` and so on when fused;
        ``-robust`` in place of ``-prob`` in the robust mode; ``-l1`` after any of them with
        the L1 slack; ``mpsf-`` before them for the predictive filter, ``MODULE:FACTORY-``
        for a filter of the user's)."""
        if self.kind == "none":
            return "none"
        slack = "" if self.slack == SQUARED_SLACK else f"-{self.slack}"
        family = "mpsf-" if self.kind == "mpsf" else ""
        family = f"{self.kind}-" if users_filter(self.kind) else family
        if not self.uncertain_state:
            return f"{family}oracle{slack}"
        source = "noisy" if self.state_source is None else self.state_source.split(":", 1)[0]
        fused = "-fused" if self.fuse_odometry else ""
        fused += f"-aci-{self.adaptive}" if self.adaptive else ""
        mode = "robust" if self.uncertainty == "robust" else "prob" if self.probabilistic else "det"
        return f"{family}{source}{fused}-{mode}{slack}"

    def as_dict(self) -> dict:
        """The settings; for a filter of the user's only those that are its (the state it
        is fed), not our filters' (gains, model, uncertainty mode, slack...)."""
        settings = asdict(self)
        if users_filter(self.kind):
            return {name: settings[name] for name in USERS_FILTER_SETTINGS}
        return settings
