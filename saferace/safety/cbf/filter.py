"""``SafetyFilter``: the probabilistic HOCBF QP between any agent and a racing task."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from saferace.names import SQUARED_SLACK
from saferace.safety.cbf.arguments import check_filter_arguments
from saferace.safety.cbf.backup import BackupPlan, PlanState
from saferace.safety.cbf.barriers import (
    BARRIER_NAMES,
    BarrierContext,
    class_k_gains,
)
from saferace.safety.cbf.chance import (
    ConstraintStatistics,
    confidence_quantile,
    constraint_std,
)
from saferace.safety.cbf.exact_penalty import solve_filter_qp_l1
from saferace.safety.cbf.filter_map import SPEED_LIMIT_LATERAL_MPS2, FilterMap
from saferace.safety.cbf.problem import lane_problem
from saferace.safety.cbf.qp import FilterProblem, FilterSolution, solve_filter_qp
from saferace.safety.decision import SafetyDecision, decision_mode, nominal_parts, record_args
from saferace.safety.models import lane_model_states, param_values, symbolic_model
from saferace.safety.traffic import car_barriers
from saferace.safety.uncertainty.estimate import checked_action, estimate_state
from saferace.safety.uncertainty.fallback import (
    FALLBACK_BRAKE_MPS2,
    FALLBACK_LATERAL_MPS2,
    fallback_steer_rad,
    fitting_speed_mps,
    grip_steer_rad,
    towards_speed,
)
from saferace.safety.uncertainty.intervals import interval_points
from saferace.safety.uncertainty.last_trusted import LastTrusted
from saferace.safety.uncertainty.late_frames import LateFrames
from saferace.safety.uncertainty.pending_commands import PendingCommands
from saferace.safety.uncertainty.stale_frames import StaleFrames
from saferace.safety.uncertainty.state_sources import OracleStateSource, StateSource, prefetch
from saferace.safety.uncertainty.steering_trim import SteeringTrim
from saferace.safety.vehicle_params import VehicleParams, load_params

if TYPE_CHECKING:  # for typing only: importing saferace.envs sets up MuJoCo's OpenGL
    from saferace.envs.racing_env import RacingEnv

#: Settings of ``SafetyFilter`` by name (:data:`saferace.names.GAIN_NAMES`): the paper's gain;
#: the same within the tyres' grip (the default: at racing speed the paper's kinematic filter
#: asks for corrections the car cannot drive); the gains measured to leave the expert most
#: alone while keeping every reckless ``saferace safety-table`` run inside; and those within
#: the grip, the robust mode's (a drifting agent slid out of a 2.2 m lane without it).
GRIP = {"max_lateral_accel_mps2": SPEED_LIMIT_LATERAL_MPS2}
GAIN_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {"lam": 2.5},
    "grip": {"lam": 2.5, **GRIP, "width_preview_s": 0.3},
    "tuned": {"lam": (20.0, 4.0), "lateral_decel_mps2": 5.0},
}
GAIN_PRESETS["tuned-grip"] = {**GAIN_PRESETS["tuned"], **GRIP}
#: Below ``creep_speed_mps`` the filter accelerates at least this much (or as the agent does,
#: if that is less): at a standstill the steering drops out of the lane barriers (its
#: effect grows with ``v^2``), so a car stopped heading for an edge cannot be steered away.
CREEP_ACCEL_MPS2 = 1.0
INTERVENTION_TOLERANCE = (1e-3, 1e-2)  # (rad, m/s^2): closer to the nominal is none
RELINEARISE_TOL = 1e-3  # rad: a steering this close to the linearisation point is final
#: A robust constraint needing more slack than this has no control that satisfies it (the
#: slack penalty leaves about 1e-4 on a constraint it holds at its edge; m/s^2 for a lane).
INFEASIBLE_SLACK = 1e-2


class SafetyFilter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Keep any agent in its lane with a (probabilistic) higher-order CBF QP (paper Sec. 3).

    Each step the filter takes the agent's action ``u_ref`` (and its spread, see
    :class:`NominalAction`), samples the lane state from ``state_source``, builds the lane
    and heading HOCBF constraints of ``model`` for every sample (linearised in the steering
    around ``u_ref``, then around the solution, ``linearisation_passes`` in all: ``tan``
    linearised at a hard-steering agent's action over-promises turn), turns them into
    chance constraints ``Pr(psi_m >= -eps) >= eta`` and applies the solution of

        min (u - u_ref)^T diag(u_std^2)^-1 (u - u_ref) + k_err * sum(eps^2)

    within the actuator limits (:mod:`saferace.safety.cbf.qp`), never braking the car backwards.
    With one sample, or ``probabilistic=False``, it is the deterministic HOCBF filter on the
    samples' mean. ``info["safety"]`` holds a ``SafetyDecision`` every step; a failed solve
    brakes at ``FALLBACK_BRAKE_MPS2``, steering the lane's curvature and toward the centre
    line, and is counted in ``failures``.

    ``uncertainty="robust"`` replaces the chance constraints by barrier conditions that must
    hold at every point of the state's interval (its corners and centre, see
    :func:`~saferace.safety.uncertainty.intervals.interval_points`; the measurement-robust CBF
    of Dean et al. 2020 and Cosner et al. 2021: the margin grows with the interval's width). The
    interval is the source's own (a conformal calibration) or ``mean +- z std`` of its samples;
    the curvature comes from the map (a network's is its worst output). The filter carries a set
    by odometry from the start pose (:mod:`~saferace.safety.uncertainty.dead_reckoning`) and
    holds the car over its meet with the interval, or over the set alone while the source is in
    doubt (its monitor raises, its interval misses the set, or the frame is stale:
    :mod:`~saferace.safety.uncertainty.stale_frames`); a frame that may be late is carried to
    now (:mod:`~saferace.safety.uncertainty.late_frames`). Where no control satisfies them, the
    filter falls back (:mod:`~saferace.safety.uncertainty.fallback`): it brakes towards a speed
    at which the interval fits inside the lane (a stop where even its offsets do not fit), never
    above the map's speed limit, steering the lane's curvature and towards the centre line from
    the interval's centre, within the tyres' grip. Such steps count in ``fallbacks``.

    Departures from the paper, each because the paper's form failed a measured case (the
    docs' safety-filter page gives the measurements):

    - the chance constraints' spread is taken at the agent's acceleration
      (:func:`~saferace.safety.cbf.chance.spread_at_accel`), so the filter does not brake at
      full force to narrow its own heading spread;
    - below ``creep_speed_mps`` it accelerates at least ``CREEP_ACCEL_MPS2`` (or as the
      agent does, if less): at a standstill the steering drops out of the lane barriers,
      and a stopped car heading for an edge could otherwise be held there for good;
    - ``speed_limit_factor`` adds the barrier ``h_speed = v_limit(s) - v_x`` on the task's
      speed profile (:mod:`saferace.safety.cbf.speed_limit`): the lane barriers cannot make the
      car brake, so a car too fast for the tyres' grip would slide out whatever it steers;
    - ``width_preview_s`` takes the narrowest half width reached within that time, since a
      second-order barrier cannot see a narrowing coming; ``map_curvature`` takes the
      curvature from the map (a state network judges it worst, and a wrong curvature turns
      the barriers' steering the wrong way);
    - ``backup_plan`` sends an action only if braking back onto the reference line after it
      keeps the car inside (:mod:`~saferace.safety.cbf.backup`), else the backup's own: the
      barriers see the lane where the car is, and at a chicane's 7 m/s pushed it off the line
      to where the tyres could not follow the bend (fallback ``"backup"``).

    Arguments: ``state_source`` (default: the oracle); ``model``: ``"kinematic"``, ``"dynamic"``
    or ``"dynamic-paper"``; ``lam``: the class-K gain (1/s) of every HOCBF order, or one per
    order; ``lateral_decel_mps2``: saturate the first class-K function at the stopping condition
    ``dh/dt >= -sqrt(2 a h)``; ``max_lateral_accel_mps2``: keep ``v_x^2 tan(delta) / L`` inside
    the tyres' grip (the kinematic model assumes no sliding); ``theta_max`` (rad) and ``eta`` as
    in the paper; ``k_err`` the slack weight; ``action_std``: the spread assumed when the agent
    gives none, ``min_action_std`` its floor; ``lane_margin_m``: added to the car's half width
    in the lane barriers (the models are not exact); ``params``: vehicle parameters (default:
    identified ones). ``uncertainty``: one of :data:`~saferace.names.UNCERTAINTY_MODES`;
    ``slack_penalty``: the QP's squared slack (the paper's) or the exact L1 one
    (:mod:`~saferace.safety.cbf.exact_penalty`). In traffic a barrier per opponent joins the QP,
    where the car is kept clear before the lane (:mod:`~saferace.safety.traffic.car_barriers`;
    where it cannot be, it brakes in the lane: fallback ``"car"``); ``opponent_noise_m``: noise
    on their positions (else the truth, as ``s`` is). ``estimate_steering_offset``: judge and
    undo the steering's centre offset (:mod:`~saferace.safety.uncertainty.steering_trim`);
    the decision's actions are the wheels', ``steering_offset_rad`` less than the command
    sent, certified where late commands meet the car
    (:mod:`~saferace.safety.uncertainty.pending_commands`). ``info["safety"]`` is the same for
    the same seed and actions (the env checker's ask): its clock times are 0 unless
    ``record_timings``."""

    record_timings = False

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
        uncertainty: str = "chance",
        slack_penalty: str = SQUARED_SLACK,
        opponent_noise_m: float = 0.0,
        estimate_steering_offset: bool = True,
        backup_plan: bool = True,
    ) -> None:
        record_args(self, locals())
        check_filter_arguments(locals())
        super().__init__(env)
        self.solve = solve_filter_qp if slack_penalty == SQUARED_SLACK else solve_filter_qp_l1
        gains = class_k_gains(lam)
        self.lateral_decel_mps2 = math.inf if lateral_decel_mps2 is None else lateral_decel_mps2
        self.max_lateral_accel_mps2 = max_lateral_accel_mps2
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
        self.half_width_m = float(base.car_half_width_m) + lane_margin_m
        self.robust = uncertainty == "robust"
        self.map_curvature = map_curvature or self.robust
        self.linearisation_passes = linearisation_passes
        self.creep_speed_mps = creep_speed_mps
        self.track = base.track
        self.map = FilterMap(
            self.track, base.reference, width_preview_s, speed_limit_factor, self.speed_gain
        )
        self.opponent_noise_m = opponent_noise_m
        self.backup = BackupPlan(
            self.track, base.reference, self.wheelbase_m, params.steer_time_constant_s,
            float(self.upper[0]), self.half_width_m, self.control_dt_s,
        ) if backup_plan else None  # fmt: skip
        self.opponents = tuple(base.traffic.names) if base.traffic is not None else ()
        self._noise_rng = np.random.default_rng()
        speed_names = ("speed",) if self.map.speed_limit else ()
        self.constraint_names = BARRIER_NAMES + speed_names + car_barriers.names(self.opponents)
        self.interventions = self.failures = self.fallbacks = self.steps = 0
        self.last_problem: FilterProblem | None = None  # for debugging and benchmarks
        self._observation: dict[str, np.ndarray] | None = None
        self._info: dict[str, Any] | None = None
        self.last_trusted = LastTrusted.of_task(env)  # the robust mode's
        self.stale_frames = StaleFrames.of_source(self.state_source)
        self.late_frames = LateFrames.of_task(env, self.state_source)
        self.pending = PendingCommands.of_task(env, self.control_dt_s, self.wheelbase_m)
        self.steering_trim = SteeringTrim(
            self.wheelbase_m, self.control_dt_s, params.steer_time_constant_s,
            base.params.max_steer_rate_radps, estimate_steering_offset,
            self.pending.max_delay_steps,
        )  # fmt: skip

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        self.state_source.reset(seed)
        if seed is not None:  # its own stream, apart from the state source's
            self._noise_rng = np.random.default_rng([seed, 1])
        self.interventions = self.failures = self.fallbacks = self.steps = 0
        self._observation, self._info = observation, info
        for part in (self.steering_trim, self.pending, self.stale_frames, self.late_frames):
            part.reset()
        self.last_trusted.reset(info if self.robust else None)  # robust: the start pose's
        prefetch(self.state_source, observation)  # the agent's network runs beside it
        return observation, info

    def step(self, action):
        if self._info is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        mean, std = nominal_parts(action)
        trim = np.array([self.steering_trim.offset_rad, 0.0])
        decision = self.certify(self._observation, self._info, mean + trim, std)  # the wheels'
        command = np.clip(np.asarray(decision.filtered_action) - trim, self.lower, self.upper)
        observation, reward, terminated, truncated, info = self.env.step(command.astype(np.float32))
        self.steering_trim.update(float(command[0]), observation["velocity"])
        self.pending.record(*map(float, command + trim))  # as the wheels take it
        decision = dataclasses.replace(decision, steering_offset_rad=float(trim[0]))
        info = {**info, "safety": decision.as_dict(timed=self.record_timings)}
        self._observation, self._info = observation, info
        prefetch(self.state_source, observation)
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
        nominal, spread = checked_action(action, action_std, self.action_std, self.min_action_std)
        u0 = np.clip(nominal, self.lower, self.upper)
        s_m = float(info["s_m"])
        curvature = self.track.centerline.curvature_scalar(s_m) if self.map_curvature else None
        stale = self.stale_frames.in_step(observation, info)  # no measurement
        estimate = estimate_state(self.state_source, observation, info, self.z, curvature, stale)
        estimate = self.late_frames.caught_up(estimate, info, self.last_trusted)
        interval = (estimate.lower, estimate.upper)
        judged = self.last_trusted.update(estimate.alarm, interval, info) if self.robust else None
        trusted, held = judged or (not estimate.alarm, None)  # the set certified over
        reckoned = None if trusted else held  # in doubt: the set carried forward
        if held is not None:
            lower, upper = held.interval(float(estimate.lower[2]))  # the map's curvature
            estimate = dataclasses.replace(estimate, lower=lower, upper=upper, bounded=True)
        velocity = observation["velocity"]
        if self.robust and estimate.bounded:  # where and how fast a late command meets it
            delay_steps = self.steering_trim.delay_steps
            estimate, velocity, s_m = self.pending.meet(estimate, velocity, s_m, delay_steps)
        samples, state_lower, state_upper = estimate.samples, estimate.lower, estimate.upper
        score, alarm = estimate.monitor_score, not trusted
        doubt = alarm and reckoned is None  # nothing holds the state: stop
        bounded = estimate.bounded
        chance = not self.robust and self.probabilistic and len(samples) > 1
        if self.robust and bounded:
            lane = interval_points(state_lower, state_upper)
        else:
            lane = samples if chance else estimate.mean[None]
            if self.map_curvature:
                lane = np.column_stack([lane[:, :2], np.full(len(lane), state_lower[2])])
        v_x = float(velocity[0])
        context = self.map.barrier_context(
            s_m, v_x, self.half_width_m, self.theta_max, self.lam, self.lateral_decel_mps2
        )
        speed = self.map.speed_constraint(s_m, v_x, lane[:, 0])
        states = lane_model_states(self.symbolic, lane, velocity)
        cars = car_barriers.opponent_predictions(
            info.get("opponents", ()), self.track, s_m, self.opponent_noise_m, self._noise_rng
        )
        problem, statistics, h, solution, solve_time = self._solve(
            states, lane[:, 2], u0, context, speed, cars, nominal, spread, chance,
            *self._action_box(v_x, float(u0[1])),
        )  # fmt: skip
        fallback = "alarm" if doubt and self.robust else "" if solution.solved else "solver"
        car_rows = car_barriers.ROWS_PER_CAR * len(cars)
        barrier_rows = len(problem.b) - (speed is not None) - car_rows
        if not fallback and self.robust and solution.slack[:barrier_rows].max() > INFEASIBLE_SLACK:
            fallback = "infeasible"
        self.last_problem = problem
        filtered = solution.u
        if fallback:  # the lane's curvature, and back to the centre where the belief holds
            feedforward = math.atan(self.wheelbase_m * self.track.centerline.curvature_scalar(s_m))
            steer = fallback_steer_rad(feedforward, None if doubt else lane.mean(axis=0))
            if fallback == "solver":  # brakes whatever the creep rule asks
                box, accel = self._action_box(v_x, -math.inf), -FALLBACK_BRAKE_MPS2
            else:
                doubted = (np.full(3, -math.inf), np.full(3, math.inf))  # stops the car
                interval = doubted if doubt else (state_lower, state_upper)
                box = self._fallback_box(v_x, float(u0[1]), interval, context, speed)
                accel = float(u0[1])
            filtered = np.clip(np.array([steer, accel]), *box)
            if cars:  # nor into a car ahead
                filtered[1] = car_barriers.follow_capped(problem, car_rows, filtered[1], box)
        elif cars and car_barriers.car_conflict(
            problem, solution, car_rows, barrier_rows, INFEASIBLE_SLACK
        ):
            fallback = "car"  # no room for the car: brake in the lane, not around the car
            lower, upper = self._action_box(v_x, -math.inf)
            upper[1] = lower[1]
            filtered = np.clip(self._solve(
                states, lane[:, 2], u0, context, speed, [], nominal, spread, chance, lower, upper
            )[3].u, lower, upper)  # fmt: skip
        if not fallback and trusted and self.backup is not None:  # in doubt: the set stops it
            wheels = float(info.get("steer_angle_rad", u0[0]))
            e_y, e_psi = map(float, lane.mean(axis=0)[:2])
            at = PlanState(s_m, e_y, e_psi, v_x, wheels)
            backup = self.backup.instead(at, filtered, float(state_upper[0] - state_lower[0]) / 2)
            if backup is not None:
                fallback, filtered = "backup", np.clip(backup, *self._action_box(v_x, -math.inf))
        intervened = bool(np.any(np.abs(filtered - u0) > INTERVENTION_TOLERANCE))
        count = len(self.constraint_names)
        spread_at_u = np.zeros(count)
        if statistics is not None:  # chance-constrained
            spread_at_u[: len(BARRIER_NAMES)] = constraint_std(statistics, filtered)
        self.steps += 1
        self.interventions += intervened
        self.failures += fallback == "solver"
        self.fallbacks += bool(fallback)
        reduce = np.min if self.robust else np.mean
        return SafetyDecision(
            nominal_action=nominal.tolist(),
            filtered_action=filtered.tolist(),
            **estimate.fields(info, float(lane[:, 2].mean())),
            barriers=self._by_name(reduce(h, axis=0)),
            constraints=self._by_name(
                self._per_constraint(problem.b - problem.a @ filtered, np.min)
            ),
            tightening=self._by_name(self.z * spread_at_u),
            slacks=self._by_name(self._per_constraint(solution.slack, np.max)),
            intervened=intervened,
            monitor_score=score,
            alarm=alarm,
            fallback=fallback,
            status=solution.status,
            iterations=solution.iterations,
            solve_time_s=solve_time,
            filter_time_s=time.perf_counter() - started,
            n_samples=len(samples),
            mode=decision_mode(fallback, propagated=reckoned is not None),
        )

    def _solve(
        self,
        states: np.ndarray,
        kappa: np.ndarray,
        u0: np.ndarray,
        context: BarrierContext,
        speed: tuple[np.ndarray, float, float] | None,
        cars: list[tuple[float, float, float]],
        nominal: np.ndarray,
        spread: np.ndarray,
        chance: bool,
        lower: np.ndarray,
        upper: np.ndarray,
    ) -> tuple[FilterProblem, ConstraintStatistics | None, np.ndarray, FilterSolution, float]:
        """The last solved pass of linearising at ``u0`` and then at each solution (the first
        pass if none solved), and the seconds spent solving."""
        solve_time, linearised_at = 0.0, u0
        accepted: (
            tuple[FilterProblem, ConstraintStatistics | None, np.ndarray, FilterSolution] | None
        ) = None
        for _ in range(self.linearisation_passes):
            problem, statistics, h = lane_problem(
                self.model_name, self.param_values, states, kappa, linearised_at, context,
                speed, nominal, spread, (lower, upper), self.k_err, self.z if chance else None,
            )  # fmt: skip
            if cars:
                rows = car_barriers.car_rows(
                    self.model_name, self.param_values, states.mean(axis=0),
                    float(kappa.mean()), linearised_at, cars, car_barriers.CAR_GAINS,
                    self.z * self.opponent_noise_m,
                )  # fmt: skip
                problem, h = car_barriers.with_car_rows(problem, h, rows)
            solve_started = time.perf_counter()
            solution = self.solve(problem)
            solve_time += time.perf_counter() - solve_started
            if accepted is not None and not solution.solved:
                break  # keep the last solved pass
            accepted = problem, statistics, h, solution
            if not solution.solved or abs(solution.u[0] - linearised_at[0]) < RELINEARISE_TOL:
                break  # linearised in the steering only
            linearised_at = solution.u
        assert accepted is not None  # linearisation_passes >= 1, and the first pass is kept
        return (*accepted, solve_time)

    def _fallback_box(
        self,
        v_x: float,
        agent_accel: float,
        interval: tuple[np.ndarray, np.ndarray],
        context: BarrierContext,
        speed: tuple[np.ndarray, float, float] | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The action box of a fallback step (:func:`towards_speed`): towards the speed the
        ``interval`` fits the lane at, under the map's limit (``speed``, which needs no lane
        state; without it a speeding agent left a 1.6 m turn), inside the tyres' grip."""
        lane = (context.w_left_m, context.w_right_m, self.half_width_m, self.creep_speed_mps)
        target = fitting_speed_mps(*interval, *lane)
        box = self._action_box(v_x, agent_accel if target > 0.0 else -math.inf)
        lateral_mps2 = self.max_lateral_accel_mps2 or FALLBACK_LATERAL_MPS2
        steer_max = grip_steer_rad(v_x, lateral_mps2, self.wheelbase_m)
        limit = None if speed is None else speed[1]
        return towards_speed(box, v_x, target, self.control_dt_s, limit, steer_max)

    def _per_constraint(self, rows: np.ndarray, reduce: Any) -> np.ndarray:
        """One value per constraint name from a value per QP row (``reduce`` over the robust
        mode's state points)."""
        barrier_rows = len(rows) - (len(self.constraint_names) - len(BARRIER_NAMES))
        per_point = np.asarray(rows[:barrier_rows]).reshape(-1, len(BARRIER_NAMES))
        return np.concatenate([reduce(per_point, axis=0), rows[barrier_rows:]])

    def _action_box(self, v_x: float, agent_accel: float) -> tuple[np.ndarray, np.ndarray]:
        """The actuator box, less braking than stops the car within one control step (the
        models hold for forward driving only, and an infeasible lane constraint asks for
        braking every step: past standstill it would reverse the car), below
        ``creep_speed_mps`` an acceleration of at least ``min(agent_accel,
        CREEP_ACCEL_MPS2)``, and with ``max_lateral_accel_mps2`` a steering of
        ``|tan delta| <= a_max L / v_x^2``; the wheels' angles a steering offset leaves."""
        lower, upper = self.lower.copy(), self.upper.copy()
        offset = self.steering_trim.offset_rad  # the wheels' reach: the commands' less it
        lower[0], upper[0] = lower[0] + max(offset, 0.0), upper[0] + min(offset, 0.0)
        lower[1] = max(lower[1], -max(v_x, 0.0) / self.control_dt_s)
        if self.creep_speed_mps > 0.0 and v_x < self.creep_speed_mps:
            lower[1] = max(lower[1], min(agent_accel, CREEP_ACCEL_MPS2))
        if self.max_lateral_accel_mps2 is not None:
            steer_max = grip_steer_rad(v_x, self.max_lateral_accel_mps2, self.wheelbase_m)
            lower[0], upper[0] = max(lower[0], -steer_max), min(upper[0], steer_max)
        return lower, upper

    def _by_name(self, values: np.ndarray) -> dict[str, float]:
        return {name: float(v) for name, v in zip(self.constraint_names, values, strict=True)}
