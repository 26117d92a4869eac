"""``SafetyFilter``: the probabilistic HOCBF QP between any agent and a racing task."""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from saferace.safety.barriers import (
    BARRIER_NAMES,
    BarrierContext,
    class_k_gains,
    linearised_constraints,
)
from saferace.safety.chance import (
    ConstraintStatistics,
    confidence_quantile,
    constraint_statistics,
    constraint_std,
    spread_at_accel,
)
from saferace.safety.models import MIN_SPEED_MPS, param_values, symbolic_model
from saferace.safety.qp import FilterProblem, FilterSolution, solve_filter_qp
from saferace.safety.speed_limit import LaneSpeedLimit
from saferace.safety.state_sources import OracleStateSource, StateSource
from saferace.safety.vehicle_params import VehicleParams, load_params
from saferace.track.vehicle_envelope import VehicleEnvelope

if TYPE_CHECKING:  # for typing only: importing saferace.envs sets up MuJoCo's OpenGL
    from saferace.envs.racing_env import RacingEnv

#: Fallback when a solve fails: brake at this rate and steer toward the centerline.
FALLBACK_BRAKE_MPS2 = 2.0
FALLBACK_STEER_PER_M = 1.0  # rad of steering per m of lateral offset
FALLBACK_STEER_PER_RAD = 1.0  # rad of steering per rad of heading error
#: Step (m) of the finite differences of the speed limit and lane widths along the track.
MAP_DS_M = 0.05
#: The friction ellipse the speed limit brakes within (m/s^2): braking at half the car's
#: 4 on a straight, none where the limit turns at 7 (the limit's corners take 6.05, the
#: tyres' grip is about 9.8), so braking ends as the car turns in.
SPEED_LIMIT_DECEL_MPS2 = 2.0
SPEED_LIMIT_LATERAL_MPS2 = 7.0
#: Settings of ``SafetyFilter`` by name (:data:`saferace.names.GAIN_NAMES`): the paper's
#: gain; the same with the steering held within the tyres' grip (``max_lateral_accel_mps2``,
#: :data:`saferace.names.DEFAULT_GAINS`), since at racing speed the paper's kinematic filter
#: asks for corrections the car cannot drive; and the gains measured to leave the expert
#: most alone while keeping every reckless run of ``saferace safety-table`` inside its lane.
GAIN_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {"lam": 2.5},
    "grip": {
        "lam": 2.5,
        "max_lateral_accel_mps2": SPEED_LIMIT_LATERAL_MPS2,
        "width_preview_s": 0.3,
    },
    "tuned": {"lam": (20.0, 4.0), "lateral_decel_mps2": 5.0},
}
#: Below ``creep_speed_mps`` the filter accelerates at least this much (or as the agent does,
#: if that is less): at a standstill the steering drops out of the lane barriers (its
#: effect grows with ``v^2``), so a car stopped heading for an edge cannot be steered away.
CREEP_ACCEL_MPS2 = 1.0
#: A filtered action this close to the nominal one is not an intervention.
INTERVENTION_TOLERANCE = (1e-3, 1e-2)  # (rad, m/s^2)
RELINEARISE_TOL = 1e-3  # rad: a steering this close to the linearisation point is final


@dataclass(frozen=True)
class NominalAction:
    """An agent's action with the spread of its own uncertainty (e.g. its MC-dropout std).

    Agents may return this instead of a plain action; the filter then weighs each control's
    deviation by ``1 / std^2``, so it bends the controls the agent is least sure of.
    """

    mean: np.ndarray
    std: np.ndarray | None = None


def nominal_parts(action: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """``(mean, std or None)`` of a plain action or a :class:`NominalAction`."""
    if isinstance(action, NominalAction):
        std = None if action.std is None else np.asarray(action.std, dtype=float).ravel()
        return np.asarray(action.mean, dtype=float).ravel(), std
    return np.asarray(action, dtype=float).ravel(), None


@dataclass(frozen=True)
class SafetyDecision:
    """What the filter did in one step (``info["safety"]``); per-barrier values by name.

    ``barriers`` are the estimated ``h`` (mean over state samples; m for the lanes, rad for
    the heading); ``constraints`` the HOCBF condition ``psi_m`` at the filtered action (mean
    over samples, ``>= 0`` holds); ``tightening`` the chance-constraint margin
    ``Phi^-1(eta) * std`` (the spread at the agent's acceleration, see below); ``slacks`` what each
    constraint needed. ``state_mean`` and ``state_std`` are the ``[e_y, e_psi, kappa]`` the
    filter believed (the curvature from the map where it takes it from there),
    ``state_true`` the simulator's at the same moment.
    """

    nominal_action: list[float]
    filtered_action: list[float]
    state_true: list[float]
    state_mean: list[float]
    state_std: list[float]
    barriers: dict[str, float]
    constraints: dict[str, float]
    tightening: dict[str, float]
    slacks: dict[str, float]
    intervened: bool
    fallback: bool
    status: str
    iterations: int
    solve_time_s: float
    filter_time_s: float
    n_samples: int

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class SafetyFilter(gym.Wrapper):
    """Keep any agent in its lane with a (probabilistic) higher-order CBF QP (paper Sec. 3).

    Each step the filter takes the agent's action ``u_ref`` (and its spread, see
    :class:`NominalAction`), samples the lane state from ``state_source``, builds the lane
    and heading HOCBF constraints of ``model`` for every sample (linearised in the steering
    around ``u_ref``, then around the solution, ``linearisation_passes`` in all: ``tan``
    linearised at a hard-steering agent's action over-promises turn), turns them into
    chance constraints ``Pr(psi_m >= -eps) >= eta`` and applies the solution of

        min (u - u_ref)^T diag(u_std^2)^-1 (u - u_ref) + k_err * sum(eps^2)

    within the actuator limits (:mod:`saferace.safety.qp`), never braking the car backwards.
    With one sample, or ``probabilistic=False``, it is the deterministic HOCBF filter on the
    samples' mean. ``info["safety"]`` holds a :class:`SafetyDecision` every step; a failed
    solve brakes at ``FALLBACK_BRAKE_MPS2`` while steering toward the centre line, and is
    counted in ``failures``.

    Departures from the paper, each because the paper's form failed a measured case (the
    docs' safety-filter page gives the measurements):

    - the chance constraints' spread is taken at the agent's acceleration
      (:func:`~saferace.safety.chance.spread_at_accel`), so the filter does not brake at
      full force to narrow its own heading spread;
    - below ``creep_speed_mps`` it accelerates at least ``CREEP_ACCEL_MPS2`` (or as the
      agent does, if less): at a standstill the steering drops out of the lane barriers,
      and a stopped car heading for an edge could otherwise be held there for good;
    - ``speed_limit_factor`` adds the barrier ``h_speed = v_limit(s) - v_x`` on the task's
      speed profile (:mod:`saferace.safety.speed_limit`): the lane barriers cannot make the
      car brake, so a car too fast for the tyres' grip would slide out whatever it steers;
    - ``width_preview_s`` takes the narrowest half width reached within that time, since a
      second-order barrier cannot see a narrowing coming; ``map_curvature`` takes the
      curvature from the map (a state network judges it worst, and a wrong curvature turns
      the barriers' steering the wrong way).

    Arguments: ``state_source`` (default: the oracle); ``model``: ``"kinematic"``,
    ``"dynamic"`` or ``"dynamic-paper"``; ``lam``: the class-K gain (1/s) of every HOCBF
    order, or one per order; ``lateral_decel_mps2``: saturate the first class-K function at
    the stopping condition ``dh/dt >= -sqrt(2 a h)``; ``max_lateral_accel_mps2``: keep
    ``v_x^2 tan(delta) / L`` inside the tyres' grip (the kinematic model assumes no
    sliding); ``theta_max`` (rad) and ``eta`` as in the paper; ``k_err`` the slack weight;
    ``action_std``: the spread assumed when the agent gives none, ``min_action_std`` its
    floor; ``lane_margin_m``: added to the car's half width in the lane barriers (the
    models are not exact); ``params``: vehicle parameters (default: identified ones).
    ``GAIN_PRESETS`` names the settings the command line offers.
    """

    def __init__(
        self,
        env: gym.Env,
        state_source: StateSource | None = None,
        model: str = "kinematic",
        lam: float | tuple[float, ...] = 2.5,
        lateral_decel_mps2: float | None = None,
        max_lateral_accel_mps2: float | None = None,
        theta_max: float = math.pi / 4,
        eta: float = 0.95,
        k_err: float = 1e4,
        action_std: tuple[float, float] = (0.1, 1.0),
        min_action_std: tuple[float, float] = (0.02, 0.2),
        probabilistic: bool = True,
        lane_margin_m: float = 0.05,
        speed_limit_factor: float | None = 1.1,
        map_curvature: bool = False,
        linearisation_passes: int = 2,
        width_preview_s: float = 0.0,
        creep_speed_mps: float = 0.5,
        params: VehicleParams | None = None,
    ) -> None:
        super().__init__(env)
        gains = class_k_gains(lam)
        for name, value in (
            ("lateral_decel_mps2", lateral_decel_mps2),
            ("max_lateral_accel_mps2", max_lateral_accel_mps2),
        ):
            if value is not None and value <= 0.0:
                raise ValueError(f"{name} must be positive or None, got {value}")
        self.lateral_decel_mps2 = math.inf if lateral_decel_mps2 is None else lateral_decel_mps2
        self.max_lateral_accel_mps2 = max_lateral_accel_mps2
        if not 0.0 < theta_max < math.pi / 2:
            raise ValueError(f"need 0 < theta_max < pi/2, got {theta_max}")
        if min(action_std) <= 0.0 or min(min_action_std) <= 0.0:
            raise ValueError("action_std and min_action_std must be positive")
        self.state_source = state_source if state_source is not None else OracleStateSource()
        self.model_name = model
        self.symbolic = symbolic_model(model)  # raises on an unknown model name
        self.lam, self.theta_max, self.eta, self.k_err = lam, theta_max, eta, k_err
        self.speed_gain = gains[0]  # a first-order barrier: the first order's gain
        self.z = confidence_quantile(eta)
        self.action_std = np.asarray(action_std, dtype=float)
        self.min_action_std = np.asarray(min_action_std, dtype=float)
        self.probabilistic = probabilistic
        params = params or load_params()
        self.wheelbase_m = params.wheelbase_m
        self.param_values = param_values(params)
        action_space = env.action_space
        assert isinstance(action_space, spaces.Box), "SafeRace tasks act in a Box"
        self.lower = np.asarray(action_space.low, dtype=float)
        self.upper = np.asarray(action_space.high, dtype=float)
        base = cast("RacingEnv", env.unwrapped)  # a SafeRace task
        self.control_dt_s = float(base.control_dt_s)
        if lane_margin_m < 0.0:
            raise ValueError(f"lane_margin_m must be non-negative, got {lane_margin_m}")
        self.half_width_m = float(base.car_half_width_m) + lane_margin_m
        if speed_limit_factor is not None and speed_limit_factor <= 0.0:
            raise ValueError(f"speed_limit_factor must be positive, got {speed_limit_factor}")
        self.speed_limit_factor = speed_limit_factor
        self.map_curvature = map_curvature
        if linearisation_passes < 1:
            raise ValueError(f"linearisation_passes must be at least 1, got {linearisation_passes}")
        self.linearisation_passes = linearisation_passes
        if width_preview_s < 0.0:
            raise ValueError(f"width_preview_s must be non-negative, got {width_preview_s}")
        self.width_preview_s = width_preview_s
        if creep_speed_mps < 0.0:
            raise ValueError(f"creep_speed_mps must be non-negative, got {creep_speed_mps}")
        self.creep_speed_mps = creep_speed_mps
        self.track = base.track
        self.speed_limit = (
            LaneSpeedLimit(
                self.track,
                base.reference,
                speed_limit_factor,
                SPEED_LIMIT_DECEL_MPS2,
                SPEED_LIMIT_LATERAL_MPS2,
                path_lateral_mps2=speed_limit_factor**2 * VehicleEnvelope().a_lat_max_mps2,
            )
            if speed_limit_factor
            else None
        )
        self.constraint_names = BARRIER_NAMES + (("speed",) if speed_limit_factor else ())
        self.interventions = 0
        self.failures = 0
        self.steps = 0
        self.last_problem: FilterProblem | None = None  # for debugging and benchmarks
        self._observation: dict[str, np.ndarray] | None = None
        self._info: dict[str, Any] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        self.state_source.reset(seed)
        self.interventions = self.failures = self.steps = 0
        self._observation, self._info = observation, info
        return observation, info

    def step(self, action):
        if self._info is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        mean, std = nominal_parts(action)
        decision = self.certify(self._observation, self._info, mean, std)
        observation, reward, terminated, truncated, info = self.env.step(
            np.asarray(decision.filtered_action, dtype=np.float32)
        )
        info = {**info, "safety": decision.as_dict()}
        self._observation, self._info = observation, info
        return observation, reward, terminated, truncated, info

    def certify(
        self,
        observation: dict[str, np.ndarray],
        info: dict[str, Any],
        action: np.ndarray,
        action_std: np.ndarray | None = None,
    ) -> SafetyDecision:
        """The filtered action for ``action`` in the state seen by ``observation``/``info``."""
        started = time.perf_counter()
        nominal = np.asarray(action, dtype=float).ravel()
        if nominal.shape != (2,) or not np.all(np.isfinite(nominal)):
            raise ValueError(f"action must be 2 finite numbers [steer, accel], got {action!r}")
        spread = self.action_std if action_std is None else np.asarray(action_std, dtype=float)
        spread = np.maximum(spread, self.min_action_std)
        u0 = np.clip(nominal, self.lower, self.upper)

        samples = np.atleast_2d(self.state_source.samples(observation, info))
        lane = samples
        chance = self.probabilistic and len(lane) > 1
        if not chance:
            lane = lane.mean(axis=0, keepdims=True)
        states = self._model_states(lane, observation["velocity"])
        s_m = float(info["s_m"])
        v_x = float(observation["velocity"][0])
        preview_m = self.width_preview_s * max(v_x, 0.0)
        w_right, w_left = self._lane_widths(s_m, preview_m)
        w_left_slope, w_right_slope = self._width_slopes(s_m, preview_m)
        context = BarrierContext(
            w_left_m=w_left,
            w_right_m=w_right,
            half_width_m=self.half_width_m,
            theta_max_rad=self.theta_max,
            lam=self.lam,
            lateral_decel_mps2=self.lateral_decel_mps2,
            w_left_slope=w_left_slope,
            w_right_slope=w_right_slope,
        )
        kappa, kappa_std = lane[:, 2], float(samples[:, 2].std())
        if self.map_curvature:
            kappa = np.full(len(lane), self.track.centerline.curvature_scalar(s_m))
        lower, upper = self._action_box(v_x, float(u0[1]))
        speed = (
            self._speed_constraint(info, observation["velocity"], lane[:, 0])
            if self.speed_limit_factor
            else None
        )
        solve_time, linearised_at = 0.0, u0
        accepted: (
            tuple[FilterProblem, ConstraintStatistics | None, np.ndarray, FilterSolution] | None
        ) = None
        for _ in range(self.linearisation_passes):
            problem, statistics, h = self._problem(
                states, kappa, linearised_at, context, speed, nominal, spread, lower, upper, chance
            )
            solve_started = time.perf_counter()
            solution = solve_filter_qp(problem)
            solve_time += time.perf_counter() - solve_started
            if accepted is not None and not solution.solved:
                break  # keep the last solved pass
            accepted = problem, statistics, h, solution
            if not solution.solved or abs(solution.u[0] - linearised_at[0]) < RELINEARISE_TOL:
                break  # linearised in the steering only
            linearised_at = solution.u
        assert accepted is not None  # linearisation_passes >= 1, and the first pass is kept
        problem, statistics, h, solution = accepted
        self.last_problem = problem
        a_mean, b_mean = problem.a, problem.b

        fallback = not solution.solved
        if fallback:  # brakes whatever the creep rule asks
            filtered = self._fallback(lane.mean(axis=0), *self._action_box(v_x, -math.inf))
        else:
            filtered = solution.u
        intervened = bool(np.any(np.abs(filtered - u0) > INTERVENTION_TOLERANCE))
        count = len(self.constraint_names)
        spread_at_u = np.zeros(count)
        if statistics is not None:  # chance-constrained
            spread_at_u[: len(BARRIER_NAMES)] = constraint_std(statistics, filtered)
        self.steps += 1
        self.interventions += intervened
        self.failures += fallback
        return SafetyDecision(
            nominal_action=nominal.tolist(),
            filtered_action=filtered.tolist(),
            state_true=[float(info[name]) for name in ("e_y_m", "e_psi_rad", "kappa_radpm")],
            state_mean=[*samples[:, :2].mean(axis=0), float(np.mean(kappa))],
            state_std=[*samples[:, :2].std(axis=0), 0.0 if self.map_curvature else kappa_std],
            barriers=self._by_name(h.mean(axis=0)),
            constraints=self._by_name(b_mean - a_mean @ filtered),
            tightening=self._by_name(self.z * spread_at_u),
            slacks=self._by_name(solution.slack),
            intervened=intervened,
            fallback=fallback,
            status=solution.status,
            iterations=solution.iterations,
            solve_time_s=solve_time,
            filter_time_s=time.perf_counter() - started,
            n_samples=len(lane),
        )

    def _problem(
        self,
        states: np.ndarray,
        kappa: np.ndarray,
        linearised_at: np.ndarray,
        context: BarrierContext,
        speed: tuple[np.ndarray, float, float] | None,
        nominal: np.ndarray,
        spread: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        chance: bool,
    ) -> tuple[FilterProblem, ConstraintStatistics | None, np.ndarray]:
        """The QP with the constraints linearised in the steering at ``linearised_at``, the
        samples' statistics (``None`` if deterministic) and the barrier values."""
        a, b, h = linearised_constraints(
            self.model_name, self.param_values, states, kappa, linearised_at, context
        )
        if chance:
            a, b = spread_at_accel(a, b, float(np.clip(nominal[1], lower[1], upper[1])))
        statistics = constraint_statistics(a, b) if chance else None
        if statistics is not None:
            a_mean, b_mean, covariance = statistics.a_mean, statistics.b_mean, statistics.covariance
        else:
            a_mean, b_mean, covariance = a[0], b[0], None
        if speed is not None:
            speed_row, speed_bound, speed_h = speed
            a_mean = np.vstack([a_mean, speed_row])
            b_mean = np.append(b_mean, speed_bound)
            h = np.column_stack([h, np.full(len(h), speed_h)])
            if covariance is not None:  # measured speed, the samples' lowest limit: no spread
                covariance = np.concatenate([covariance, np.zeros((1, 3, 3))])
        problem = FilterProblem(
            u_mean=nominal,
            u_std=spread,
            a=a_mean,
            b=b_mean,
            lower=lower,
            upper=upper,
            k_err=self.k_err,
            covariance=covariance,
            z=self.z if chance else 0.0,
        )
        return problem, statistics, h

    def _model_states(self, lane: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """The model's state for each lane-state sample and the measured velocities."""
        v_x = max(float(velocity[0]), MIN_SPEED_MPS)
        columns: dict[str, np.ndarray | float] = {
            "e_y": lane[:, 0],
            "e_psi": lane[:, 1],
            "v": v_x,
            "v_x": v_x,
            "v_y": float(velocity[1]),
            "r": float(velocity[2]),
        }
        return np.column_stack(
            [np.broadcast_to(columns[str(x)], len(lane)) for x in self.symbolic.state]
        )

    def _action_box(self, v_x: float, agent_accel: float) -> tuple[np.ndarray, np.ndarray]:
        """The actuator box, less braking than stops the car within one control step, and
        below ``creep_speed_mps`` an acceleration of at least ``min(agent_accel,
        CREEP_ACCEL_MPS2)``.

        The models hold for forward driving only, and a filter that brakes past standstill
        would reverse the car (an infeasible lane constraint asks for braking every step).
        With ``max_lateral_accel_mps2`` the steering is narrowed to
        ``|tan delta| <= a_max L / v_x^2``.
        """
        lower, upper = self.lower.copy(), self.upper.copy()
        lower[1] = max(lower[1], -max(v_x, 0.0) / self.control_dt_s)
        if self.creep_speed_mps > 0.0 and v_x < self.creep_speed_mps:
            lower[1] = max(lower[1], min(agent_accel, CREEP_ACCEL_MPS2))
        if self.max_lateral_accel_mps2 is not None:
            speed_sq = max(v_x, MIN_SPEED_MPS) ** 2
            steer_max = math.atan(self.max_lateral_accel_mps2 * self.wheelbase_m / speed_sq)
            lower[0], upper[0] = max(lower[0], -steer_max), min(upper[0], steer_max)
        return lower, upper

    def _lane_widths(self, s_m: float, preview_m: float) -> tuple[float, float]:
        """Right and left half widths of the map at ``s_m``: the narrowest over the next
        ``preview_m`` (sampled every ``MAP_DS_M``) when previewing."""
        if preview_m <= 0.0:
            right, left = self.track.widths(s_m)
            return float(right), float(left)
        ahead = s_m + np.linspace(0.0, preview_m, 2 + math.ceil(preview_m / MAP_DS_M))
        rights, lefts = self.track.widths(ahead)
        return float(rights.min()), float(lefts.min())

    def _width_slopes(self, s_m: float, preview_m: float) -> tuple[float, float]:
        """``(d w_left / ds, d w_right / ds)`` of :meth:`_lane_widths` at ``s_m``."""
        right_ahead, left_ahead = self._lane_widths(s_m + MAP_DS_M, preview_m)
        right_behind, left_behind = self._lane_widths(s_m - MAP_DS_M, preview_m)
        scale = 0.5 / MAP_DS_M
        return (left_ahead - left_behind) * scale, (right_ahead - right_behind) * scale

    def _speed_constraint(
        self, info: dict[str, Any], velocity: np.ndarray, e_y_m: np.ndarray
    ) -> tuple[np.ndarray, float, float]:
        """Row, bound and barrier value of ``accel <= lam_1 h + dv_limit/ds * v_x``, at the
        lane offset (of the samples ``e_y_m``) with the lowest limit. The offset's own rate
        is left out: the limit's fall with the offset is a blend, not a dynamics."""
        assert self.speed_limit is not None  # asked for only with a speed_limit_factor
        s, v_x = float(info["s_m"]), float(velocity[0])
        limit, e_y = self.speed_limit.lowest(s, e_y_m)
        ahead = self.speed_limit(s + MAP_DS_M, e_y)
        slope = (ahead - limit) / MAP_DS_M
        h = limit - v_x
        return np.array([0.0, 1.0]), self.speed_gain * h + slope * max(v_x, 0.0), h

    def _by_name(self, values: np.ndarray) -> dict[str, float]:
        return {name: float(v) for name, v in zip(self.constraint_names, values, strict=True)}

    @staticmethod
    def _fallback(lane_mean: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        steer = -FALLBACK_STEER_PER_M * lane_mean[0] - FALLBACK_STEER_PER_RAD * lane_mean[1]
        return np.clip(np.array([steer, -FALLBACK_BRAKE_MPS2]), lower, upper)
