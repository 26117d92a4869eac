"""``PredictiveSafetyFilter``: the second filter family, a predictive safety filter (MPSF).

Where the CBF filter judges an action by barrier conditions at the car's current point, the
predictive filter plans ahead along the map (:mod:`saferace.safety.predictive.plan`): an
action is let through if some continuation of it keeps the car inside the lane over the
horizon and ends where the map's speed limit holds, and is bent as little as that needs
otherwise. A kink ahead is in the plan before the car reaches it.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any, cast

import gymnasium as gym
import numpy as np

from saferace.names import UNCERTAINTY_MODES
from saferace.safety.cbf.filter import INTERVENTION_TOLERANCE, SafetyFilter
from saferace.safety.cbf.filter_map import SPEED_LIMIT_LATERAL_MPS2
from saferace.safety.decision import SafetyDecision, record_args
from saferace.safety.predictive.plan import PREDICTIVE_HORIZON, PredictivePlanner
from saferace.safety.traffic import car_barriers
from saferace.safety.uncertainty.estimate import checked_action, estimate_state
from saferace.safety.uncertainty.fallback import FALLBACK_BRAKE_MPS2, fallback_steer_rad
from saferace.safety.uncertainty.state_sources import StateSource
from saferace.safety.vehicle_params import VehicleParams, load_params

if TYPE_CHECKING:  # for typing only: importing saferace.envs sets up MuJoCo's OpenGL
    from saferace.envs.racing_env import RacingEnv

#: How far (m, rad) the believed ``[e_y, e_psi]`` may be from where the last certified plan
#: expects the car, beyond the state's half-interval, for its tail to still be followed:
#: farther, the plan's guarantee is void and the filter replans from the car as it is.
TAIL_TOLERANCE = np.array([0.05, 0.1])
#: The constraints a decision reports, by name.
PREDICTIVE_CONSTRAINTS = ("lane_left", "lane_right", "speed", "terminal_heading")


class PredictiveSafetyFilter(SafetyFilter):
    """Keep any agent in its lane with a predictive safety filter (model predictive safety
    certification, Wabersich and Zeilinger 2018), behind the same wrapper and ``certify``
    interface as the CBF filter (:class:`~saferace.safety.cbf.filter.SafetyFilter`).

    Each step it plans from the believed state (the state source's samples' mean, or its
    interval's centre in the robust mode) the inputs over ``horizon`` stages whose first is
    closest to the agent's action (weighed by ``1 / std^2`` of the action's spread) with the
    predicted lane offset inside the lane less the car's half width, ``lane_margin_m`` and
    the state's uncertainty at every stage, the steering inside ``max_lateral_accel_mps2``
    and the last stage below the map's speed limit (``speed_limit_factor`` times the task's
    reference speed, braked for in time). A plan that keeps the lane with its margin (no
    more slack than the uncertainty's tightening and
    :data:`~saferace.safety.predictive.plan.CERTIFIED_SLACK`) is *certified*:
    its first input is applied and its tail kept. Where none is (the QP failed, needed slack, or the
    state source's monitor raised), the filter follows the tail of the last certified plan
    (the MPSC fallback) while it lasts and the car is where that plan expects it
    (``TAIL_TOLERANCE``), or else the least-violating plan's first input, and after a failed
    solve it brakes steering the lane's curvature. Each such step counts in
    ``fallbacks``. Its plan has no cars: behind an opponent in its line the acceleration is
    held to the CBF filter's following barrier
    (:func:`~saferace.safety.traffic.car_barriers.follow_bound_mps2`).

    Uncertainty: the state's interval (``mean +- z std`` of the samples at confidence
    ``eta``, or a calibrated source's own) tightens the lane by its offset half-width and
    by its heading half-width over the distance driven in
    :data:`~saferace.safety.predictive.plan.HEADING_CORRECTION_S`; ``probabilistic=False``
    plans from the samples' mean alone. ``map_curvature`` and ``uncertainty`` are the CBF
    filter's (the plan always takes the curvature from the map).
    """

    def __init__(
        self,
        env: gym.Env,
        state_source: StateSource | None = None,
        model: str = "kinematic",
        eta: float = 0.95,
        action_std: tuple[float, float] = (0.1, 1.0),
        min_action_std: tuple[float, float] = (0.02, 0.2),
        lane_margin_m: float = 0.05,
        speed_limit_factor: float | None = 1.1,
        max_lateral_accel_mps2: float = SPEED_LIMIT_LATERAL_MPS2,
        creep_speed_mps: float = 0.0,
        horizon: int = PREDICTIVE_HORIZON,
        probabilistic: bool = True,
        map_curvature: bool = False,
        params: VehicleParams | None = None,
        uncertainty: str = "chance",
    ) -> None:
        record_args(self, locals())
        if uncertainty not in UNCERTAINTY_MODES:
            raise ValueError(f"uncertainty must be one of {UNCERTAINTY_MODES}, got {uncertainty!r}")
        if horizon < 2:
            raise ValueError(f"horizon must be at least 2 stages, got {horizon}")
        params = params or load_params()
        super().__init__(
            env,
            state_source=state_source,
            model=model,
            eta=eta,
            action_std=action_std,
            min_action_std=min_action_std,
            lane_margin_m=lane_margin_m,
            speed_limit_factor=speed_limit_factor,
            max_lateral_accel_mps2=max_lateral_accel_mps2,
            creep_speed_mps=creep_speed_mps,
            params=params,
            uncertainty=uncertainty,
            probabilistic=probabilistic,
            map_curvature=map_curvature,
        )
        self.vehicle_params = params
        self.constraint_names = PREDICTIVE_CONSTRAINTS
        base = cast("RacingEnv", env.unwrapped)  # a SafeRace task
        self.planner = PredictivePlanner(
            self.track,
            base.reference,
            model,
            params,
            base.params,
            self.control_dt_s,
            lane_margin_m,
            max_lateral_accel_mps2,
            self.map.speed_limit,
            horizon,
        )
        self._tail_inputs = self._tail_states = np.empty((0, 2))  # the certified plan's rest

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        self.planner.reset()
        self._tail_inputs = self._tail_states = np.empty((0, 2))
        return super().reset(seed=seed, options=options)

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
        s_m = float(info["s_m"])
        curvature = self.track.centerline.curvature_scalar(s_m)
        estimate = estimate_state(
            self.state_source,
            observation,
            info,
            self.z,
            curvature if self.map_curvature else None,
            self.stale_frames.in_step(observation, info),
        )
        velocity = observation["velocity"]
        v_x = float(velocity[0])
        if self.robust and estimate.bounded:
            believed = 0.5 * (estimate.lower + estimate.upper)
        else:
            believed = estimate.mean
        half_interval = 0.5 * (estimate.upper - estimate.lower)
        tightened = estimate.bounded and (self.probabilistic or self.robust)
        offset_margin, heading_margin = half_interval[:2] if tightened else (0.0, 0.0)
        x0 = np.append(
            self.planner.model.state_from(
                believed[0], believed[1], v_x, float(velocity[1]), float(velocity[2])
            ),
            float(info["steer_angle_rad"]),
        )
        lower, upper = self._action_box(v_x, float(nominal[1]))
        solve_started = time.perf_counter()
        u, solved = self.planner.plan(
            x0,
            s_m,
            float(info["steer_rad"]),
            self._model_input(nominal, v_x),
            1.0 / spread**2,
            (self._model_input(lower, v_x), self._model_input(upper, v_x)),
            float(offset_margin),
            float(min(heading_margin, 0.5 * math.pi)),
        )
        solve_time = time.perf_counter() - solve_started
        certified = solved and self.planner.certified
        fallback = "" if certified and not estimate.alarm else "alarm" if estimate.alarm else (
            "infeasible" if solved else "solver"
        )  # fmt: skip
        tail_expected = self._tail_states[:1, :2]  # where the last certified plan is now
        on_tail = len(tail_expected) > 0 and (
            estimate.alarm
            or bool(
                np.all(
                    np.abs(tail_expected[0] - believed[:2]) <= TAIL_TOLERANCE + half_interval[:2]
                )
            )
        )
        mode = "certified" if not fallback else "propagated" if on_tail else "stopping"
        if not fallback:
            filtered = self._command(u, v_x)
            self._keep_tail()
        elif on_tail:
            filtered = self._tail_inputs[0]
            self._tail_inputs, self._tail_states = self._tail_inputs[1:], self._tail_states[1:]
        elif solved:
            filtered = self._command(u, v_x)
        else:
            feedforward = math.atan(self.wheelbase_m * curvature)
            steer = fallback_steer_rad(feedforward, believed[:2])
            filtered = np.array([steer, -FALLBACK_BRAKE_MPS2])
        box = self._action_box(v_x, -math.inf)
        filtered = np.clip(filtered, *box)
        cars = car_barriers.opponent_predictions(
            info.get("opponents", ()), self.track, s_m, self.opponent_noise_m, self._noise_rng
        )
        if cars:  # the plan has no cars: keep the following distance to one ahead
            along_mps = car_barriers.along_track_mps(v_x, believed[1], curvature, believed[0])
            follow = car_barriers.follow_bound_mps2(cars, float(believed[0]), along_mps)
            filtered[1] = max(min(filtered[1], follow), box[0][1])
        u0 = np.clip(nominal, self.lower, self.upper)
        intervened = bool(np.any(np.abs(filtered - u0) > INTERVENTION_TOLERANCE))
        self.steps += 1
        self.interventions += intervened
        self.failures += fallback == "solver"
        self.fallbacks += bool(fallback)
        return SafetyDecision(
            nominal_action=nominal.tolist(),
            filtered_action=filtered.tolist(),
            **estimate.fields(info, float(believed[2])),
            barriers=self._margins(s_m, believed[0], believed[1], v_x),
            constraints=self._plan_margins(),
            tightening={"lane_left": float(offset_margin), "lane_right": float(offset_margin)}
            | {"speed": 0.0, "terminal_heading": 0.0},
            slacks=self._slacks(),
            intervened=intervened,
            monitor_score=estimate.monitor_score,
            alarm=estimate.alarm,
            fallback=fallback,
            status="certified" if certified else "uncertified" if solved else "failed",
            iterations=1,
            solve_time_s=solve_time,
            filter_time_s=time.perf_counter() - started,
            n_samples=len(estimate.samples),
            mode=mode,
        )

    def _keep_tail(self) -> None:
        """Keep the certified plan's inputs after its first, the drivetrain's commands, with
        the states the plan expects the car in when each is applied."""
        states = self.planner.plan_states
        assert states is not None  # a certified plan solved
        speeds = states[1:-1, self.planner.model.speed_index]
        self._tail_inputs = self._command(self.planner.plan_inputs[1:], speeds)
        self._tail_states = states[1:-1, :2]

    def _command(self, u: np.ndarray, speed_mps: float | np.ndarray) -> np.ndarray:
        """The drivetrain's commands for the model's inputs ``u`` (``(..., 2)``) at
        ``speed_mps``."""
        params = self.vehicle_params
        command = np.array(u, dtype=float)
        command[..., 1] = (command[..., 1] + params.drag_per_s * speed_mps) / params.accel_gain
        return command

    def _model_input(self, command: np.ndarray, speed_mps: float) -> np.ndarray:
        """The model's inputs for the drivetrain's ``command`` at ``speed_mps``: the inverse
        of :meth:`_command` (the steering alike, the acceleration less the drag)."""
        params = self.vehicle_params
        u = np.array(command, dtype=float)
        u[..., 1] = u[..., 1] * params.accel_gain - params.drag_per_s * speed_mps
        return u

    def _margins(self, s_m: float, e_y_m: float, e_psi_rad: float, v_x: float) -> dict[str, float]:
        """Now: the lane margins of the believed offset, the speed limit's and the terminal
        set's heading bound's."""
        w_right, w_left = (float(w) for w in self.track.widths(s_m))
        limit = self.map.speed_limit(s_m, e_y_m) if self.map.speed_limit else math.inf
        return {
            "lane_left": w_left - e_y_m - self.half_width_m,
            "lane_right": w_right + e_y_m - self.half_width_m,
            "speed": limit - v_x,
            "terminal_heading": self._heading_bound(v_x) - abs(e_psi_rad),
        }

    def _plan_margins(self) -> dict[str, float]:
        """Over the plan: its least lane margins, its least margin to the speed caps it was
        held to (the map's limit and the grip's) and its last state's margin to the
        terminal heading bound."""
        states = self.planner.plan_states
        if states is None:
            return dict.fromkeys(PREDICTIVE_CONSTRAINTS, math.nan)
        speeds = states[:, self.planner.model.speed_index]
        w_right, w_left = self.track.widths(self.planner.plan_arc_lengths)
        e_y = states[:, 0]
        return {
            "lane_left": float(np.min(w_left - e_y)) - self.half_width_m,
            "lane_right": float(np.min(w_right + e_y)) - self.half_width_m,
            "speed": float(np.min(self.planner.speed_caps_mps - speeds[1:])),
            "terminal_heading": self._heading_bound(speeds[-1]) - abs(float(states[-1, 1])),
        }

    def _heading_bound(self, speed_mps: float) -> float:
        planner = self.planner
        return planner.terminal_heading_rad + planner.terminal_heading_per_mps * max(speed_mps, 0.0)

    def _slacks(self) -> dict[str, float]:
        slacks = self.planner.plan_slacks
        if slacks is None:
            return dict.fromkeys(PREDICTIVE_CONSTRAINTS, math.nan)
        lane = float(slacks["lane"].max())
        return {
            "lane_left": lane,
            "lane_right": lane,
            "speed": float(slacks["speed"].max()),
            "terminal_heading": float(slacks["heading"]),
        }
