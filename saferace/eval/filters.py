"""Safety-filter settings for the runner and the command line, and the wrapping they imply."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import gymnasium as gym

from saferace.safety.filter import GAIN_PRESETS, SafetyFilter
from saferace.safety.state_sources import NoisyOracleStateSource, OracleStateSource

FILTER_KINDS = ("none", "cbf")


@dataclass(frozen=True)
class FilterConfig:
    """Which filter wraps the agent and what state it sees.

    ``state_noise`` ``(e_y_m, e_psi_rad)`` standard deviations make the state source a
    noisy oracle with ``samples`` samples; ``probabilistic=False`` then filters
    deterministically on the samples' mean. ``gains`` names an entry of
    :data:`~saferace.safety.filter.GAIN_PRESETS`.
    """

    kind: str = "none"
    model: str = "kinematic"
    state_noise: tuple[float, float] | None = None
    samples: int = 20
    probabilistic: bool = True
    eta: float = 0.95
    gains: str = "paper"

    def __post_init__(self) -> None:
        if self.kind not in FILTER_KINDS:
            raise ValueError(f"unknown filter {self.kind!r}: use one of {', '.join(FILTER_KINDS)}")
        if self.gains not in GAIN_PRESETS:
            raise ValueError(f"unknown gains {self.gains!r}: use one of {', '.join(GAIN_PRESETS)}")
        if self.state_noise is not None and len(self.state_noise) != 2:
            raise ValueError(f"state_noise is (e_y_m, e_psi_rad), got {self.state_noise}")

    @property
    def label(self) -> str:
        """Short name for tables: ``none``, ``oracle``, ``noisy-prob`` or ``noisy-det``."""
        if self.kind == "none":
            return "none"
        if self.state_noise is None:
            return "oracle"
        return "noisy-prob" if self.probabilistic else "noisy-det"

    def as_dict(self) -> dict:
        return asdict(self)


def apply_filter(env: gym.Env, config: FilterConfig, seed: int | None = None) -> gym.Env:
    """``env`` wrapped as ``config`` says (unchanged for ``kind="none"``)."""
    if config.kind == "none":
        return env
    if config.state_noise is None:
        source = OracleStateSource()
    else:
        e_y_std, e_psi_std = config.state_noise
        source = NoisyOracleStateSource((e_y_std, e_psi_std, 0.0), config.samples, seed)
    return SafetyFilter(
        env,
        state_source=source,
        model=config.model,
        eta=config.eta,
        probabilistic=config.probabilistic,
        **GAIN_PRESETS[config.gains],
    )
