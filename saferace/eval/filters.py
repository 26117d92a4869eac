"""Safety-filter settings for the runner and the command line, and the wrapping they imply."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import gymnasium as gym

from saferace.eval.agents import load_entry_point
from saferace.safety.filter import DEFAULT_GAINS, GAIN_PRESETS, SafetyFilter
from saferace.safety.state_fusion import OdometryFusedStateSource
from saferace.safety.state_sources import (
    NoisyOracleStateSource,
    OracleStateSource,
    SpreadScaledStateSource,
)

FILTER_KINDS = ("none", "cbf")
#: State sources of the packages above ``eval``, as ``KIND:ARGUMENT``: loaded on first use,
#: ``FACTORY(ARGUMENT, IMAGE_SHAPE, n_samples=N, seed=S)`` (the state network:
#: ``learned:CHECKPOINT``).
STATE_SOURCE_KINDS = {"learned": "saferace.learning.agent:learned_state_source"}


@dataclass(frozen=True)
class FilterConfig:
    """Which filter wraps the agent and what state it sees.

    The state source is the oracle unless ``state_noise`` ``(e_y_m, e_psi_rad)`` standard
    deviations make it a noisy oracle with ``samples`` samples, or ``state_source`` names a
    learned one (``learned:CHECKPOINT``: the state network's ``samples`` MC-dropout samples,
    the perceived state); ``probabilistic=False`` filters deterministically on the samples'
    mean. ``gains`` names an entry of :data:`~saferace.safety.filter.GAIN_PRESETS`;
    ``map_curvature`` takes the curvature from the track map instead of the state source;
    ``spread_scale`` ``(e_y, e_psi, kappa)`` widens the state source's samples about their
    mean (a calibration of the MC-dropout spread, see
    :class:`~saferace.safety.state_sources.SpreadScaledStateSource`); ``fuse_odometry``
    fuses the source's samples with odometry in a Kalman filter that gates outliers
    (:class:`~saferace.safety.state_fusion.OdometryFusedStateSource`).
    """

    kind: str = "none"
    model: str = "kinematic"
    state_noise: tuple[float, float] | None = None
    samples: int = 20
    probabilistic: bool = True
    eta: float = 0.95
    gains: str = DEFAULT_GAINS
    state_source: str | None = None
    map_curvature: bool = False
    spread_scale: tuple[float, float, float] | None = None
    fuse_odometry: bool = False

    def __post_init__(self) -> None:
        if self.kind not in FILTER_KINDS:
            raise ValueError(f"unknown filter {self.kind!r}: use one of {', '.join(FILTER_KINDS)}")
        if self.gains not in GAIN_PRESETS:
            raise ValueError(f"unknown gains {self.gains!r}: use one of {', '.join(GAIN_PRESETS)}")
        if self.state_noise is not None and len(self.state_noise) != 2:
            raise ValueError(f"state_noise is (e_y_m, e_psi_rad), got {self.state_noise}")
        if self.state_source is not None:
            kind = self.state_source.split(":", 1)[0]
            if kind not in STATE_SOURCE_KINDS or ":" not in self.state_source:
                raise ValueError(
                    f"unknown state source {self.state_source!r}: use oracle, noisy or "
                    "learned:CHECKPOINT"
                )
            if self.state_noise is not None:
                raise ValueError("a learned state source takes no state_noise")
        if self.fuse_odometry and self.state_source is None and self.state_noise is None:
            raise ValueError("fuse_odometry fuses an uncertain state source, not the truth")
        if self.spread_scale is not None and (
            len(self.spread_scale) != 3 or min(self.spread_scale) <= 0.0
        ):
            raise ValueError(
                f"spread_scale is 3 positive factors (e_y, e_psi, kappa), got {self.spread_scale}"
            )

    @property
    def label(self) -> str:
        """Short name for tables: ``none``, ``oracle``, ``noisy-prob``, ``noisy-det``,
        ``learned-prob`` or ``learned-det`` (``noisy-fused-prob`` and so on when fused)."""
        if self.kind == "none":
            return "none"
        if self.state_source is None and self.state_noise is None:
            return "oracle"
        source = "noisy" if self.state_source is None else self.state_source.split(":", 1)[0]
        fused = "-fused" if self.fuse_odometry else ""
        return f"{source}{fused}-{'prob' if self.probabilistic else 'det'}"

    def as_dict(self) -> dict:
        return asdict(self)


def apply_filter(env: gym.Env, config: FilterConfig, seed: int | None = None) -> gym.Env:
    """``env`` wrapped as ``config`` says (unchanged for ``kind="none"``)."""
    if config.kind == "none":
        return env
    if config.state_source is not None:
        kind, argument = config.state_source.split(":", 1)
        factory = load_entry_point(STATE_SOURCE_KINDS[kind])
        image_shape = env.observation_space["image"].shape
        source = factory(argument, image_shape, n_samples=config.samples, seed=seed)
    elif config.state_noise is None:
        source = OracleStateSource()
    else:
        e_y_std, e_psi_std = config.state_noise
        source = NoisyOracleStateSource((e_y_std, e_psi_std, 0.0), config.samples, seed)
    if config.spread_scale is not None:
        source = SpreadScaledStateSource(source, config.spread_scale)
    if config.fuse_odometry:
        base = env.unwrapped
        source = OdometryFusedStateSource(source, base.track, base.control_dt_s)
    return SafetyFilter(
        env,
        state_source=source,
        model=config.model,
        eta=config.eta,
        probabilistic=config.probabilistic,
        map_curvature=config.map_curvature,
        **GAIN_PRESETS[config.gains],
    )
