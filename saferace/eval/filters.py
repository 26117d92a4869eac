"""The wrapping a :class:`~saferace.eval.filter_config.FilterConfig` asks for."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
from gymnasium import spaces

from saferace.errors import ConfigError
from saferace.eval.agents import load_entry_point
from saferace.eval.filter_config import (
    OPTIONAL_ARGUMENT_SOURCES,
    STATE_SOURCE_FACTORIES,
    FilterConfig,
    users_filter,
    users_perception,
)
from saferace.safety.cbf.filter import GAIN_PRESETS, SafetyFilter
from saferace.safety.filter_protocol import ProtocolSafetyFilter
from saferace.safety.predictive.filter import PredictiveSafetyFilter
from saferace.safety.uncertainty.adaptive import AdaptiveConformalStateSource
from saferace.safety.uncertainty.intervals import ConformalStateSource, IntervalStateSource
from saferace.safety.uncertainty.perception import PerceptionSetup, PerceptionStateSource
from saferace.safety.uncertainty.state_fusion import OdometryFusedStateSource
from saferace.safety.uncertainty.state_sources import (
    NoisyOracleStateSource,
    OracleStateSource,
    SpreadScaledStateSource,
    StateSource,
)

if TYPE_CHECKING:  # for typing only: importing saferace.envs sets up MuJoCo's OpenGL
    from saferace.envs.racing_env import RacingEnv

__all__ = ["STATE_SOURCE_FACTORIES", "FilterConfig", "apply_filter", "has_safety_filter"]


def apply_filter(
    env: gym.Env, config: FilterConfig, seed: int | None = None, timed: bool = False
) -> gym.Env:
    """``env`` wrapped as ``config`` says (unchanged for ``kind="none"``; a filter of the
    user's, ``MODULE:FACTORY``, behind :class:`ProtocolSafetyFilter`); ``timed``: its
    decisions record their wall-clock times (``SafetyFilter.record_timings``)."""
    if config.kind == "none":
        return env
    base = cast("RacingEnv", env.unwrapped)  # a SafeRace task
    source: StateSource
    if config.state_source is not None and users_perception(config.state_source):
        source = users_state_source(config.state_source, env, seed)
    elif config.state_source is not None:
        kind, _, argument = config.state_source.partition(":")
        if not argument and kind not in OPTIONAL_ARGUMENT_SOURCES:
            raise ConfigError(
                "state_source", f"{kind!r} names no checkpoint: use {kind}:CHECKPOINT"
            )
        factory = load_entry_point(STATE_SOURCE_FACTORIES[kind])
        image_shape = image_shape_of(env)
        own_track = {"track": base.track} if config.own_track_calibration else {}
        source = factory(argument, image_shape, n_samples=config.samples, seed=seed, **own_track)
        ours = not users_filter(config.kind)  # a filter of the protocol takes mean +- z std
        if ours and config.uncertainty == "robust" and not isinstance(source, IntervalStateSource):
            raise ConfigError(
                "uncertainty",
                f"robust holds the car over the state network's calibrated interval, and "
                f"{argument} has no calibration: run saferace calibrate {argument} DATA --out "
                "CKPT2 (frames it never trained on), or ask for the paper's chance constraints "
                "on its spread with --filter-uncertainty chance",
            )
    elif config.state_noise is None:
        source = OracleStateSource()
    else:
        e_y_std, e_psi_std = config.state_noise
        source = NoisyOracleStateSource((e_y_std, e_psi_std, 0.0), config.samples, seed)
    if config.spread_scale is not None:
        source = SpreadScaledStateSource(source, config.spread_scale)
    if config.adaptive is not None:
        if not isinstance(source, ConformalStateSource):
            raise ConfigError(
                "adaptive",
                f"needs a conformally calibrated state source: {config.state_source} has no "
                "calibration (saferace calibrate CKPT DATA --out CKPT2)",
            )
        source = AdaptiveConformalStateSource(
            source, config.adaptive, base.track, base.control_dt_s
        )
    if config.fuse_odometry:
        source = OdometryFusedStateSource(source, base.track, base.control_dt_s)
    if users_filter(config.kind):
        factory = load_entry_point(config.kind)
        protocol = ProtocolSafetyFilter(env, factory, source, config.kind, seed)
        protocol.record_timings = timed
        return protocol
    wrapped = our_filter(env, config, source)
    wrapped.record_timings = timed
    return wrapped


def our_filter(env: gym.Env, config: FilterConfig, source: StateSource) -> SafetyFilter:
    """``env`` behind our filter family ``config.kind`` (cbf or mpsf), fed by ``source``."""
    shared: dict[str, Any] = {
        "state_source": source,
        "model": config.model,
        "eta": config.eta,
        "probabilistic": config.probabilistic,
        "map_curvature": config.map_curvature,
        "uncertainty": config.uncertainty,
    }
    if config.kind == "mpsf":
        return PredictiveSafetyFilter(env, **shared)
    return SafetyFilter(
        env,
        **shared,
        slack_penalty=config.slack,
        opponent_noise_m=config.opponent_noise_m,
        **GAIN_PRESETS[config.gains],
    )


def has_safety_filter(env: gym.Env) -> bool:
    """Whether ``env`` is behind a safety filter, ours or one of the protocol's."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, (SafetyFilter, ProtocolSafetyFilter)):
            return True
        env = env.env
    return False


def image_shape_of(env: gym.Env) -> tuple[int, ...]:
    """The shape of ``env``'s camera frames."""
    observation_space = env.observation_space
    assert isinstance(observation_space, spaces.Dict), "SafeRace observations are a Dict"
    return tuple(observation_space["image"].shape or ())


def users_state_source(spec: str, env: gym.Env, seed: int | None) -> PerceptionStateSource:
    """The perception method ``MODULE:FACTORY`` makes (from the current folder too), handed
    the :class:`~saferace.safety.uncertainty.perception.PerceptionSetup` of ``env``'s task."""
    base = cast("RacingEnv", env.unwrapped)  # a SafeRace task
    setup = PerceptionSetup(image_shape_of(env), float(base.control_dt_s), base.track, seed)
    return PerceptionStateSource(load_entry_point(spec)(setup), base.track)
