"""The safety-filter protocol: what a user's filter is handed, what it gives back, and the
wrapper that holds it to that.

A safety filter sits between a driver and the car. Before the first step its factory,
``make(setup) -> filter``, reads the :class:`FilterSetup`: the map, the car's identified
model, the actuators' limits, the control period. Each step its ``certify(action, view)``
gets the driver's action ``[steer_rad, accel_mps2]`` and a :class:`FilterView`: the lane
state as the task's perception gives it (an estimate, the interval it claims holds the
truth and whether it is in doubt), the odometry, the wheels' measured angle, where the car
is along the map and where the opponents are. It never sees the simulator's state of its
own car: the view is built from the perception, the car's own sensors and the map, and
neither the env nor ``info`` reaches it. It answers with the action to send.

:class:`ProtocolSafetyFilter` wraps a task with such a filter. What the filter answers is
checked (two finite numbers) and clipped to the actuators' limits, the clipped steps
counted (``clipped`` in ``info["safety"]``). A filter that raises (made, reset or
certifying), or answers no action, ends the run there: the car brakes, the episode is
truncated and ``info["filter_error"]`` says what happened, so that a benchmark reports that
run and goes on with the rest. The filter's map is a copy: it cannot move the env's edges.
Filters load as ``MODULE:FACTORY`` from the current folder (``saferace eval --filter
my_filter:make``), as agents and perception methods do.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, cast, runtime_checkable

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from saferace.errors import SafeRaceError
from saferace.safety.cbf.chance import confidence_quantile
from saferace.safety.decision import SafetyDecision, decision_mode, nominal_parts, record_args
from saferace.safety.uncertainty.estimate import checked_action, estimate_state
from saferace.safety.uncertainty.state_sources import OracleStateSource, StateSource, prefetch
from saferace.safety.vehicle_params import VehicleParams, load_params

if TYPE_CHECKING:  # for typing only: importing saferace.envs sets up MuJoCo's OpenGL
    from saferace.envs.racing_env import RacingEnv
    from saferace.track.track import Track

#: Closer to the driver's action than this is no intervention (rad, m/s^2), as for our own.
INTERVENTION_TOLERANCE = (1e-3, 1e-2)
#: The confidence of the ``mean +- z std`` interval of a source that has no interval of its
#: own (the noisy oracle's samples), as our own filters take it.
INTERVAL_CONFIDENCE = 0.95
#: The opponents' columns in :attr:`FilterView.opponents`.
OPPONENT_COLUMNS = ("s_m", "e_y_m", "e_psi_rad", "speed_mps")


@dataclass(frozen=True)
class FilterSetup:
    """What a filter may know of its task before the first step: the ``track`` (the map:
    centre line, widths, curvature), the car's identified ``params``, the actions' limits
    ``action_low``/``action_high`` (``[steer_rad, accel_mps2]``), the ``control_dt_s``
    between steps, the car's half width and the episode's ``seed``."""

    track: Track
    params: VehicleParams
    action_low: np.ndarray
    action_high: np.ndarray
    control_dt_s: float
    car_half_width_m: float
    seed: int | None = None


@dataclass(frozen=True)
class FilterView:
    """One step's readings, all a filter sees: the perceived lane state ``mean``
    ``[e_y_m, e_psi_rad]`` with the box ``lower .. upper`` its perception claims holds the
    truth and whether it is ``in_doubt``; the odometry's ``velocity`` ``[v_x, v_y, r]``
    (m/s, m/s, rad/s) and the wheels' measured ``steer_angle_rad``; ``s_m``, where the car
    is along the map's centre line (a localisation on the map: the lane offset and heading
    are what perception must give); ``opponents``, one row per opponent on the track,
    :data:`OPPONENT_COLUMNS` (arc length, offset and heading on the map, speed: exact, as
    our filters get them; the suite models no sensor for other cars); the episode's
    ``time_s``."""

    mean: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    in_doubt: bool
    velocity: np.ndarray
    steer_angle_rad: float
    s_m: float
    opponents: np.ndarray
    time_s: float


@runtime_checkable
class SafetyFilterMethod(Protocol):
    """A safety filter of the protocol."""

    def reset(self, seed: int | None = None) -> None:
        """A new episode (``seed``: its seed)."""
        ...

    def certify(self, action: np.ndarray, view: FilterView) -> np.ndarray:
        """The action to send for the driver's ``action`` ``[steer_rad, accel_mps2]`` (within
        the limits) in the step ``view`` describes."""
        ...


class FilterAnswerError(SafeRaceError):
    """A filter of the protocol raised, or answered something that is no action."""


class ProtocolSafetyFilter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """A task behind a :class:`SafetyFilterMethod` that ``factory(setup)`` makes, fed by
    ``state_source`` (default: the oracle) and never by the simulator's state; ``name`` is
    how reports call it. A factory that makes no filter is refused at once; one that raises
    ends every run at its first step, reported. ``info["safety"]`` holds a
    :class:`~saferace.safety.decision.SafetyDecision` every step; ``clips`` counts the
    steps whose answer was clipped to the limits; ``error`` is what ended the run where the
    filter raised."""

    record_timings = False

    def __init__(
        self,
        env: gym.Env,
        factory: Callable[[FilterSetup], SafetyFilterMethod],
        state_source: StateSource | None = None,
        name: str = "filter",
        seed: int | None = None,
    ) -> None:
        record_args(self, locals())
        super().__init__(env)
        action_space = env.action_space
        assert isinstance(action_space, spaces.Box), "SafeRace tasks act in a Box"
        self.lower = np.asarray(action_space.low, dtype=float)
        self.upper = np.asarray(action_space.high, dtype=float)
        base = cast("RacingEnv", env.unwrapped)  # a SafeRace task
        self.track = base.track
        self.name = name
        self.state_source = state_source if state_source is not None else OracleStateSource()
        self.z = confidence_quantile(INTERVAL_CONFIDENCE)
        setup = FilterSetup(
            copy.deepcopy(base.track), load_params(), self.lower.copy(), self.upper.copy(),
            float(base.control_dt_s), float(base.car_half_width_m), seed,
        )  # fmt: skip
        self.method: SafetyFilterMethod | None = None
        self.made_error: str | None = None  # what the factory raised: every run ends at once
        try:
            method = factory(setup)
        except Exception as exc:  # a fault of the filter, reported per run
            self.made_error = f"{name} raised when made: {type(exc).__name__}: {exc}"
        else:
            if not isinstance(method, SafetyFilterMethod):
                raise SafeRaceError(
                    f"{name} made {method!r}, no safety filter: it needs reset(seed) and "
                    "certify(action, view) -> action (saferace.safety.filter_protocol)"
                )
            self.method = method
        self.clips = self.interventions = self.steps = 0
        self.error: str | None = None
        self._observation: dict[str, np.ndarray] | None = None
        self._info: dict[str, Any] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        self.state_source.reset(seed)
        self.clips = self.interventions = self.steps = 0
        self.error = self.made_error
        if self.method is not None:
            try:
                self.method.reset(seed)
            except Exception as exc:  # a fault of the filter: this run ends at its first step
                self.error = f"{self.name} raised in reset: {type(exc).__name__}: {exc}"
        self._observation, self._info = observation, info
        prefetch(self.state_source, observation)
        return observation, info

    def step(self, action):
        if self._observation is None or self._info is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        started = time.perf_counter()
        mean, std = nominal_parts(action)
        nominal, _ = checked_action(mean, std, np.zeros(2), np.zeros(2))
        nominal = np.clip(nominal, self.lower, self.upper)
        estimate = estimate_state(
            self.state_source, self._observation, self._info, self.z,
            self.track.centerline.curvature_scalar(float(self._info["s_m"])),
        )  # fmt: skip
        view = self._view(estimate.mean, estimate.lower, estimate.upper, estimate.alarm)
        solve_started = time.perf_counter()
        answer, clipped = np.array([0.0, self.lower[1]]), False  # where it failed: brake
        if self.error is None and self.method is not None:
            try:
                answer = self._answer(self.method, nominal, view)
                clipped = bool(np.any(answer < self.lower) or np.any(answer > self.upper))
            except Exception as exc:  # any fault of the filter ends its run, reported
                self.error = (
                    f"{self.name} raised at {view.time_s:.2f} s: {type(exc).__name__}: {exc}"
                )
        solve_time_s = time.perf_counter() - solve_started
        filtered = np.clip(answer, self.lower, self.upper)
        intervened = bool(np.any(np.abs(filtered - nominal) > INTERVENTION_TOLERANCE))
        self.steps += 1
        self.clips += clipped
        self.interventions += intervened
        observation, reward, terminated, truncated, info = self.env.step(
            filtered.astype(np.float32)
        )
        record = estimate.fields(self._info, float(estimate.lower[2]))
        decision = SafetyDecision(
            nominal_action=nominal.tolist(), filtered_action=filtered.tolist(),
            **record,
            barriers={}, constraints={}, tightening={}, slacks={}, intervened=intervened,
            monitor_score=estimate.monitor_score, alarm=estimate.alarm, fallback="",
            status="raised" if self.error else "answered", iterations=0,
            solve_time_s=solve_time_s if self.record_timings else 0.0,
            filter_time_s=time.perf_counter() - started if self.record_timings else 0.0,
            n_samples=len(estimate.samples), mode=decision_mode("", False), clipped=clipped,
        )  # fmt: skip
        info = {**info, "safety": decision.as_dict(timed=self.record_timings)}
        if self.error is not None:
            info["filter_error"] = self.error
            truncated = True
        self._observation, self._info = observation, info
        prefetch(self.state_source, observation)
        return observation, reward, terminated, truncated, info

    @staticmethod
    def _answer(method: SafetyFilterMethod, nominal: np.ndarray, view: FilterView) -> np.ndarray:
        """The filter's answer to ``nominal`` in ``view``, checked to be an action."""
        answer = method.certify(nominal.copy(), view)
        try:
            checked = np.asarray(answer, dtype=float).ravel()
        except (TypeError, ValueError):
            checked = np.full(0, np.nan)
        if checked.shape != (2,) or not np.all(np.isfinite(checked)):
            got = checked.tolist() if checked.size else type(answer).__name__
            raise FilterAnswerError(f"certify() must return 2 finite numbers, got {got}")
        return checked

    def _view(
        self, mean: np.ndarray, lower: np.ndarray, upper: np.ndarray, in_doubt: bool
    ) -> FilterView:
        """What the filter sees this step: the estimate, the car's sensors and the map."""
        assert self._observation is not None and self._info is not None
        info = self._info
        opponents = np.array(
            [[car[name] for name in OPPONENT_COLUMNS] for car in info.get("opponents", ())],
            dtype=float,
        ).reshape(-1, len(OPPONENT_COLUMNS))
        return FilterView(
            mean=np.array(mean[:2], dtype=float),
            lower=np.array(lower[:2], dtype=float),
            upper=np.array(upper[:2], dtype=float),
            in_doubt=bool(in_doubt),
            velocity=np.array(self._observation["velocity"], dtype=float),
            steer_angle_rad=float(info["steer_angle_rad"]),
            s_m=float(info["s_m"]),
            opponents=opponents,
            time_s=float(info["time_s"]),
        )
