"""The predictive safety filter's plan: the expert's LTV QP with the agent's action as target.

Model predictive safety certification (Wabersich and Zeilinger 2018; safe-control-gym's
MPSC): over a short horizon along the map, the control sequence closest in its *first*
input to the agent's action whose predicted states stay inside the lane at every predicted
arc length and whose last state lies in a safe terminal set. The QP is the expert MPC's
(:class:`~saferace.safety.ltv_mpc.FrenetMPC`: the Frenet model with the steering servo's lag,
linearised along the previous plan, stages discretised exactly, lane bounds looked up at
the arc length each stage reaches), condensed to its inputs and solved by DAQP
(:mod:`~saferace.safety.predictive.condensed_qp`), with:

- the cost ``(u_0 - u_agent)^T diag(w) (u_0 - u_agent)``, plus a faint pull of the plan's
  lateral offsets towards the task's reference line (so the plan's tail, the fallback,
  drives on along the line);
- the lane bounds tightened by the state's uncertainty: its offset half-interval, and its
  heading half-interval times the distance driven until the next estimate corrects it;
- each stage's steering inside the tyres' grip at the speed the stage is linearised at;
- the terminal set: the last stage no faster than the map's speed limit there (off the
  racing line, the lower of the line's and the parallel's), which is braked for in time
  (:mod:`saferace.safety.cbf.speed_limit`), so the car can take what lies beyond the horizon.
  The other stages are held to the map's limit where they lie, but never below what the
  last step's plan held the same arc lengths to, so that plan's tail stays feasible.

The lane and terminal bounds are soft with an exact (linear) and a squared penalty: the
QP always has a solution, and it is *certified* where no slack is needed.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from saferace.envs.drivetrain import DrivetrainParams
from saferace.safety.cbf.speed_limit import LaneSpeedLimit
from saferace.safety.ltv_mpc import FrenetMPC, MPCSettings
from saferace.safety.predictive.condensed_qp import CondensedPlanQP, SoftPrices
from saferace.safety.stage_qp import StageQP
from saferace.safety.vehicle_params import VehicleParams
from saferace.track import Track
from saferace.track.raceline import ReferenceLine

#: The plan's stages: 20 of 0.05 s, 1 s ahead (5 m at 5 m/s: a kink is seen 1 s early).
PREDICTIVE_HORIZON = 20
#: How long a heading error of the estimate acts before the next estimate corrects it (s).
HEADING_CORRECTION_S = 0.2
#: How fast the car's lateral offset may drift from the model's prediction (m/s): the lane
#: tightens by this times each stage's time, as in tube MPC (the lane margin covers the
#: first steps). The weave agent at full lock on ``varying`` left the lane by a hair when
#: the lane was tightened only by the margin.
MODEL_ERROR_MPS = 0.05
#: The terminal set's heading error: at most this at a standstill (rad), and this much more
#: per m/s of speed (at 3 m/s 0.5 rad). A plan may not end stopped across the lane, where
#: no way forward is left: the weave agent, braked to a stop heading 0.75 rad for the edge
#: in a kink of Austin, stood there for good. With 0.15 rad per m/s (0.8 rad at 3 m/s, the
#: CBF's heading barrier's) plans ended heading too far off the lane at the F1TENTH
#: circuits' kinks of 1-1.4 1/m, where the lane turns about as fast as the car can: a few
#: steps later no plan brought the car back, and the weave agent left the lane on 5 of 23
#: circuits (0.15-0.7 s).
TERMINAL_HEADING_RAD = 0.35
TERMINAL_HEADING_PER_MPS = 0.05
#: The speed caps' and terminal heading's slack penalties, relative to the lane's: with
#: equal ones the speeding agent on Catalunya kept its speed and steered too little, since
#: the grip's speed cap made every hard turn cost speed slack (0.5 s outside the lane).
OTHER_SLACK_WEIGHT = 3.0
#: A plan that needs slack is solved again, linearised about itself, up to this many times:
#: the last step's plan, shifted, is far from the car after a swerve, and a model linearised
#: there judged accelerating towards the edge to be a way back (weave on Austin's kinks).
RELINEARISATIONS = 2
#: A plan whose slacks are at most this (m; m/s for the speeds, rad for the terminal
#: heading), beyond its uncertainty's tightening, is certified: a fifth of the lane margin,
#: which absorbs what the model mispredicts of the car.
CERTIFIED_SLACK = 1e-2
#: Weights of the plan's inputs beyond the first (per rad and per m/s^2; squared size and
#: squared change per stage): they make the tail smooth and unique, and are far too small
#: to bend the first input (weighed by ``1 / std^2``: 100 per rad^2 at the default spread).
TAIL_EFFORT_WEIGHTS = (1e-2, 0.1)
TAIL_RATE_WEIGHTS = (1.0, 1e-2)
#: Weight of the plan's lateral offset from the task's reference line (per m^2, each
#: stage): a faint pull that keeps the tail on the line, where the map's speed limit is
#: the line's. Without it the tail ran straight on in the Frenet frame, into a chicane's
#: parallels whose limit is 3 m/s where the line's is 7.7, and the plan braked at 4 m/s^2
#: inside it: the speeding agent left the lane at Monza's s = 165 m chicane and on four
#: more F1TENTH circuits as given.
TAIL_OFFSET_WEIGHT = 1.0


class PredictivePlanner(FrenetMPC):
    """The plan closest in its first input to a target action that keeps the lane (see the
    module's docstring). Inputs and states are the model's (acceleration in m/s^2 of the
    model, not the drivetrain's command)."""

    speed_rows = True
    terminal_heading_rad = TERMINAL_HEADING_RAD
    terminal_heading_per_mps = TERMINAL_HEADING_PER_MPS
    other_slack_weight = OTHER_SLACK_WEIGHT

    def __init__(
        self,
        track: Track,
        reference: ReferenceLine,
        model: str,
        params: VehicleParams,
        drivetrain: DrivetrainParams,
        dt_s: float,
        lane_margin_m: float,
        max_lateral_accel_mps2: float,
        speed_limit: LaneSpeedLimit | None,
        horizon: int = PREDICTIVE_HORIZON,
    ) -> None:
        self.max_lateral_accel_mps2 = max_lateral_accel_mps2
        self.speed_limit = speed_limit
        self.target = np.zeros(2)
        self.target_weight = np.ones(2)
        self.first_bounds = (np.full(2, -np.inf), np.full(2, np.inf))
        self.offset_margin_m = self.heading_margin_rad = 0.0
        self._replanning = False
        self.plan_arc_lengths = np.zeros(horizon + 1)  # where the stages of the plan lie (m)
        self.speed_caps_mps = np.full(horizon, np.inf)  # the stages' speed caps (m/s)
        self.tightening_m = np.zeros(horizon)  # each stage's lane tightening for uncertainty
        settings = MPCSettings(
            horizon=horizon,
            dt_s=dt_s,
            weight_e_y=TAIL_OFFSET_WEIGHT,
            weight_e_psi=0.0,
            weight_speed=0.0,
            weight_steer=TAIL_EFFORT_WEIGHTS[0],
            weight_accel=TAIL_EFFORT_WEIGHTS[1],
            weight_steer_rate=TAIL_RATE_WEIGHTS[0],
            weight_accel_rate=TAIL_RATE_WEIGHTS[1],
            lane_margin_m=lane_margin_m,
        )
        super().__init__(
            track, reference, model=model, params=params, settings=settings, drivetrain=drivetrain
        )

    def reset(self) -> None:
        super().reset()
        self._qp.reset()
        self._stage_limits: tuple[np.ndarray, np.ndarray] | None = None  # this solve's
        self._held_limits: tuple[np.ndarray, np.ndarray] | None = None  # the last step's

    def plan(
        self,
        x0: np.ndarray,
        s0_m: float,
        previous_steer_rad: float,
        target: np.ndarray,
        target_weight: np.ndarray,
        first_bounds: tuple[np.ndarray, np.ndarray],
        offset_margin_m: float,
        heading_margin_rad: float,
    ) -> tuple[np.ndarray, bool]:
        """The first input of the plan from ``x0`` (the model's state and the wheels'
        angle) at ``s0_m``, and whether the QP solved. ``target_weight`` weighs the first
        input's squared distance to ``target``; ``first_bounds`` bound it; the margins
        tighten the lane. :attr:`plan_inputs`, :attr:`plan_states` and :attr:`plan_slacks`
        hold the plan."""
        self.target, self.target_weight = np.asarray(target, float), np.asarray(target_weight)
        self.first_bounds = first_bounds
        self.offset_margin_m, self.heading_margin_rad = offset_margin_m, heading_margin_rad
        self._previous_u[0] = previous_steer_rad
        failures = self.stats.failures
        self._replanning = False
        u = self._solve(x0, s0_m)
        for _ in range(RELINEARISATIONS):
            if self._plan_x is None or self.certified:
                break
            self._replanning = True  # linearise about this plan, not the last step's
            u = self._solve(x0, s0_m)
        self._previous_u = u
        self._x0 = x0
        self._held_limits = self._stage_limits
        return u, self.stats.failures == failures

    @property
    def certified(self) -> bool:
        """Whether the last plan solved and keeps the lane with its margin (no more slack
        than the uncertainty's tightening and :data:`CERTIFIED_SLACK`: the tightening is a
        confidence's margin, not a bound) and the speed and heading of the terminal set."""
        slacks = self.plan_slacks
        if slacks is None:
            return False
        lane = slacks["lane"] <= CERTIFIED_SLACK + self.tightening_m
        return bool(
            np.all(lane) and max(slacks["speed"].max(), slacks["heading"]) <= CERTIFIED_SLACK
        )

    def _linearisation_trajectory(self, x0: np.ndarray, s0: float) -> tuple[np.ndarray, np.ndarray]:
        if self._replanning and self._plan_x is not None:
            return np.vstack([x0, self._plan_x[1:]]), self._plan_u.copy()
        return super()._linearisation_trajectory(x0, s0)

    @property
    def plan_inputs(self) -> np.ndarray:
        return self._plan_u

    @property
    def plan_states(self) -> np.ndarray | None:
        """The plan's states ``x_0 .. x_N`` (None after a failed solve)."""
        return self._plan_x

    @property
    def plan_slacks(self) -> dict[str, np.ndarray] | None:
        """The plan's slacks (None after a failed solve): the lane's per stage (m), the
        speed caps' per stage (m/s) and the terminal heading's (rad)."""
        if self._plan_slack is None:
            return None
        N = self.settings.horizon
        slack = self._plan_slack
        return {"lane": slack[:N], "speed": slack[N : 2 * N], "heading": slack[2 * N]}

    def _input_weights(self) -> np.ndarray:
        weights = super()._input_weights()
        weights[0] = self.target_weight
        return weights

    def _rate_anchor(self) -> np.ndarray:
        """The target: the rate penalty must not bend the first input from it (the rate
        limit still starts from the last command)."""
        return self.target

    def _first_input_pull(self) -> np.ndarray:
        return self.target_weight * self.target

    def _build(self) -> None:
        self._built_weight = self.target_weight.copy()
        super()._build()
        L, s = self._layout, self.settings
        P = self._P
        columns = np.repeat(np.arange(P.shape[1]), np.diff(P.indptr))
        if np.any((P.indices < L.N * L.n) & (columns != P.indices)):
            raise ValueError("the condensed plan needs a diagonal state cost")
        inputs = slice(L.u(0), L.eps(0))
        self._input_hessian = (P + sp.triu(P, 1).T).toarray()[inputs, inputs]
        prices = SoftPrices(
            lane=(s.slack_linear, s.slack_quadratic),
            other=(s.slack_linear * self.other_slack_weight,
                   s.slack_quadratic * self.other_slack_weight),
        )  # fmt: skip
        self._qp = CondensedPlanQP(
            L.N,
            L.m,
            2.0 * self._q_state,
            self.model.speed_index,
            self.terminal_heading_per_mps,
            prices,
        )

    def _solve_qp(self, qp: StageQP) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The plan from the QP condensed to its inputs (:mod:`.condensed_qp`), the first
        input weighed by the target's weight."""
        input_hessian = self._input_hessian.copy()
        first = np.arange(self.model.n_control)
        input_hessian[first, first] += 2.0 * (self.target_weight - self._built_weight)
        return self._qp.solve(qp, input_hessian)

    def sparse_problem(
        self, qp: StageQP
    ) -> tuple[sp.csc_matrix, np.ndarray, sp.csc_matrix, np.ndarray, np.ndarray]:
        """``qp`` as the sparse QP the condensed form stands for, to check it against
        another solver: ``min 1/2 z^T P z + q^T z`` s.t. ``lo <= A z <= hi`` over the
        states, inputs and slacks (``P``'s upper triangle, with the target's weight)."""
        q, lo, hi, a_values = self.sparse_vectors(qp)
        A = self._A_template.copy()
        A.data = a_values
        first = self._layout.u(0) + np.arange(self.model.n_control)
        change = 2.0 * (self.target_weight - self._built_weight)
        P = (self._P + sp.csc_matrix((change, (first, first)), shape=self._P.shape)).tocsc()
        return P, q, A, lo, hi

    def _lane_bounds(
        self, s_stage: np.ndarray, plan_x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        self.plan_arc_lengths = s_stage
        upper, lower = super()._lane_bounds(s_stage, plan_x)
        speed = float(plan_x[0, self.model.speed_index])  # at least MIN_SPEED_MPS (_solve)
        driven_m = np.minimum(s_stage[1:] - s_stage[0], speed * HEADING_CORRECTION_S)
        stage_times_s = self.settings.dt_s * np.arange(1, len(driven_m) + 1)
        self.tightening_m = (
            self.offset_margin_m
            + np.sin(self.heading_margin_rad) * driven_m
            + MODEL_ERROR_MPS * stage_times_s
        )
        return upper - self.tightening_m, lower + self.tightening_m

    def _input_bounds(self, plan_x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u_min, u_max = super()._input_bounds(plan_x)
        speeds = plan_x[:-1, self.model.speed_index]  # at least MIN_SPEED_MPS (_solve)
        grip = np.arctan(self.max_lateral_accel_mps2 * self.params.wheelbase_m / speeds**2)
        u_min[:, 0], u_max[:, 0] = np.maximum(u_min[:, 0], -grip), np.minimum(u_max[:, 0], grip)
        u_min[0] = np.maximum(u_min[0], self.first_bounds[0])
        u_max[0] = np.maximum(np.minimum(u_max[0], self.first_bounds[1]), u_min[0])
        return u_min, u_max

    def _speed_caps_mps(self, s_m: np.ndarray, states: np.ndarray) -> np.ndarray:
        """The map's speed limit, and the speed at which the wheels' angle the stage is
        linearised at reaches the tyres' grip: the models' tyres have no friction limit,
        and a plan left free to speed up while turning hard turned harder by accelerating
        (a weave on BrandsHatch accelerated at 4 m/s^2 towards the edge).

        The last stage, the terminal set's, is held to the map's invariant limit
        (:meth:`~saferace.safety.cbf.speed_limit.LaneSpeedLimit.invariant_limit`): off the
        racing line, the parallel's where it is lower than the line's, not the blend of
        the two. Held to the blend, plans certified into a corner a little off the line,
        while the agent steered the car further off, met limits 2-3 m/s lower a few steps
        later, where the line moves away from the car's offset, and the speeding agent on
        noisy state left the lane (Melbourne as given, seed 0, 0.55 s and 29 cm; Shanghai
        as given, seed 2, 0.3 s).

        The other stages' map limits are at least what the last step's plan held the same
        arc lengths to (:meth:`_held_limit`), so the last plan, shifted by a step, stays
        feasible (MPSC's recursive feasibility). Each stage's limit is looked up where the
        last plan put it, and a few tenths of a metre off the line the blend falls by
        2-3 m/s: at a kink, a plan whose far end swung off the line met limits no plan could
        brake for, and the speeding agent left the lane (Shanghai as given at s = 474 m,
        0.25-0.35 s, on the true or the noisy state as the last digits of the plans fell)."""
        tangent = np.maximum(np.abs(np.tan(states[:, -1])), 1e-6)
        caps = np.sqrt(self.max_lateral_accel_mps2 * self.params.wheelbase_m / tangent)
        if self.speed_limit is not None:
            limits = self.speed_limit.along(s_m, states[:, 0])
            limits[:-1] = np.maximum(limits[:-1], self._held_limit(s_m[:-1]))
            limits[-1] = self.speed_limit.invariant_limit(float(s_m[-1]), float(states[-1, 0]))
            caps = np.minimum(caps, limits)
            self._stage_limits = (s_m, limits)
        self.speed_caps_mps = caps
        return caps

    def _held_limit(self, s_m: np.ndarray) -> np.ndarray:
        """The map's limit the last step's plan held its stages to, at ``s_m`` (-inf beyond
        that plan's stages)."""
        if self._held_limits is None:
            return np.full(len(s_m), -np.inf)
        held_s_m, held = self._held_limits
        length = self.track.length_m
        s_m = s_m + length * np.round((held_s_m[0] - s_m[0]) / length)
        return np.interp(s_m, held_s_m, held, left=-np.inf, right=-np.inf)
