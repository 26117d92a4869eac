"""Linear time-varying MPC on a Frenet vehicle model (paper eq. 2), with OSQP: the QP that the
expert (:mod:`saferace.agents.mpc`) and the predictive safety filter
(:mod:`saferace.safety.predictive.plan`) solve, each with its own cost and bounds.

Each control step linearises the model along the previous plan (shifted by one step),
discretises every stage exactly (zero-order hold), and solves one sparse QP:

    min  sum_k |x_k - x_ref,k|_Q^2 + |u_k|_R^2 + |u_k - u_{k-1}|_Rd^2 + w eps_k + W eps_k^2
    s.t. x_{k+1} = A_k x_k + B_k u_k + c_k,     x_0 = measured state
         u_min <= u_k <= u_max,  |steer_k - steer_{k-1}| <= rate * dt
         lower_k - eps_k <= e_y,k <= upper_k + eps_k,  eps_k >= 0   (soft lane: never infeasible)

References (lateral offset, heading and speed of the task's reference line) and lane
bounds are looked up at the arc length the plan predicts for each stage. Each step's QP is
first a :class:`~saferace.safety.stage_qp.StageQP`; the expert solves it as the sparse QP
above, built once: every step only its vectors and the values of the dynamics blocks
change, with the sparsity pattern fixed (OSQP cannot take new non-zeros), and it is
warm-started. The predictive filter's planner condenses it to its inputs instead
(:mod:`saferace.safety.predictive.condensed_qp`).
The steering servo's lag (identified
time constant, about one control step) is part of the model: the state gains the wheels'
angle (``info["steer_angle_rad"]``), which follows the commanded angle as a first-order lag
(:meth:`~saferace.safety.models.FrenetModel.discretize_stages_with_steering_lag`). Without it the
plan is late by the lag, and above about 5 m/s the car weaves and spins on straights. The
steering-rate limit and penalty start from the steering target the car has
(``info["steer_rad"]``), whoever chose it: the expert's own last command, or a filter's, a
perturbation's or another driver's when it only labels the frames
(:mod:`saferace.learning.collect`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import osqp
import scipy.sparse as sp

from saferace.envs.drivetrain import DrivetrainParams
from saferace.safety.frenet_stages import stages_along_map
from saferace.safety.models import MIN_SPEED_MPS, FrenetModel
from saferace.safety.stage_qp import StageQP
from saferace.safety.vehicle_params import VehicleParams, load_params
from saferace.track import Track, VehicleEnvelope
from saferace.track.raceline import ReferenceLine


@dataclass(frozen=True)
class MPCSettings:
    """Horizon, weights and margins of the LTV MPC (its defaults are the expert's)."""

    horizon: int = 20
    dt_s: float = 0.05
    weight_e_y: float = 40.0
    weight_e_psi: float = 4.0
    weight_speed: float = 1.0
    weight_steer: float = 0.1
    weight_accel: float = 0.01
    weight_steer_rate: float = 20.0
    weight_accel_rate: float = 0.05
    slack_linear: float = 1e3
    slack_quadratic: float = 1e4
    lane_margin_m: float = 0.03
    speed_scale: float = 1.0


@dataclass
class SolveStats:
    """Per-step timings (s) and counts, for benchmarks and reports."""

    solve_times_s: list[float] = field(default_factory=list)
    step_times_s: list[float] = field(default_factory=list)
    failures: int = 0


class FrenetMPC:
    """The LTV MPC's QP along a track's Frenet frame, built once and updated every step;
    subclasses give the cost and bounds (the hooks below the solver)."""

    def __init__(
        self,
        track: Track,
        reference: ReferenceLine,
        model: str = "dynamic",
        params: VehicleParams | None = None,
        settings: MPCSettings | None = None,
        drivetrain: DrivetrainParams | None = None,
    ) -> None:
        self.track = track
        self.reference = reference
        self.params = params or load_params()
        self.model = FrenetModel(model, self.params)
        self.settings = settings or MPCSettings()
        self.drivetrain = drivetrain or DrivetrainParams()
        self.half_width_m = 0.5 * VehicleEnvelope().width_m
        self.stats = SolveStats()
        horizon = self.settings.horizon
        extra_slacks = horizon * self.speed_rows + (self.terminal_heading_rad is not None)
        self._layout = _Layout(self.model.n_state + 1, self.model.n_control, horizon, extra_slacks)
        self._build()
        self.reset()

    def reset(self) -> None:
        """Forget the previous plan (call at the start of an episode)."""
        self._plan_x: np.ndarray | None = None
        self._plan_slack: np.ndarray | None = None  # the lane's slack per stage, then any others
        self._plan_u = np.zeros((self.settings.horizon, self.model.n_control))
        self._previous_u = np.zeros(self.model.n_control)
        self._x0 = np.zeros(self._layout.n)

    # ------------------------------------------------------------------ QP
    def _build(self) -> None:
        s, L = self.settings, self._layout
        n, m, N = L.n, L.m, L.N
        state_weights = {
            "e_y": s.weight_e_y,
            "e_psi": s.weight_e_psi,
            "v": s.weight_speed,
            "v_x": s.weight_speed,
        }
        names = (*self.model.state_names, "steer_angle")
        q_state = np.array([state_weights.get(name, 0.0) for name in names])
        self._q_state = q_state
        slack_weights = self._slack_weights()
        self._slack_costs = s.slack_linear * slack_weights  # the slacks' linear costs
        p_diag = np.concatenate(
            [np.tile(q_state, N), np.zeros(N * m), s.slack_quadratic * slack_weights]
        )
        rate = np.array([s.weight_steer_rate, s.weight_accel_rate])
        effort = self._input_weights()
        rows, cols, vals = list(range(L.size)), list(range(L.size)), list(p_diag)
        for k in range(N):
            for j in range(m):
                i = L.u(k) + j
                vals[i] += effort[k, j] + rate[j] * (2.0 if k < N - 1 else 1.0)
                if k > 0:
                    rows.append(L.u(k - 1) + j)
                    cols.append(i)
                    vals.append(-rate[j])
        self._rate_weights = rate
        p = self.drivetrain
        self._drivetrain_bounds = (
            np.tile([-p.max_steer_rad, -p.max_brake_mps2], (N, 1)),
            np.tile([p.max_steer_rad, p.max_accel_mps2], (N, 1)),
        )
        P = sp.coo_matrix((2.0 * np.asarray(vals), (rows, cols)), shape=(L.size, L.size))
        self._P = sp.triu(P + sp.triu(P, 1).T, format="csc")

        # Constraint rows: dynamics, input bounds, steering rate, lane (upper, lower), slack >= 0.
        self._A_rows: list[int] = []
        self._A_cols: list[int] = []
        self._A_constants: list[float] = []
        b_entries = np.empty((N, n, m), dtype=int)  # where each stage's -B_k and -A_k go
        a_entries = np.empty((max(N - 1, 0), n, n), dtype=int)
        row = 0
        self._dyn_rows = row
        for k in range(N):
            for i in range(n):
                self._entry(row + i, L.x(k) + i, 1.0)  # x_{k+1}
                for j in range(m):
                    b_entries[k, i, j] = self._entry(row + i, L.u(k) + j)  # -B_k u_k
                if k > 0:
                    for j in range(n):
                        a_entries[k - 1, i, j] = self._entry(row + i, L.x(k - 1) + j)  # -A_k x_k
            row += n
        self._input_rows = row
        for k in range(N):
            for j in range(m):
                self._entry(row, L.u(k) + j, 1.0)
                row += 1
        self._rate_rows = row
        for k in range(N):
            self._entry(row, L.u(k), 1.0)
            if k > 0:
                self._entry(row, L.u(k - 1), -1.0)
            row += 1
        self._lane_rows = row
        for k in range(N):
            for eps_sign in (-1.0, 1.0):  # e_y - eps <= upper ; e_y + eps >= lower
                self._entry(row, L.x(k), 1.0)  # e_y is the first state
                self._entry(row, L.eps(k), eps_sign)
                row += 1
        self._slack_rows = row
        for k in range(L.slacks):
            self._entry(row, L.eps(k), 1.0)
            row += 1
        self._speed_rows = row  # each with its own slack: a speeding stage frees no lane
        for k in range(N if self.speed_rows else 0):  # 0 <= v_k - eps_{N+k} <= the speed cap
            self._entry(row, L.x(k) + self.model.speed_index, 1.0)
            self._entry(row, L.eps(N + k), -1.0)
            row += 1
        self._heading_rows = row
        if self.terminal_heading_rad is not None:  # |e_psi_N| - c v_N - eps_last <= bound
            for sign in (-1.0, 1.0):
                self._entry(row, L.x(N - 1) + 1, 1.0)  # e_psi is the second state
                speed_gain = sign * self.terminal_heading_per_mps
                self._entry(row, L.x(N - 1) + self.model.speed_index, speed_gain)
                self._entry(row, L.eps(L.slacks - 1), sign)
                row += 1
        self._n_rows = row
        nnz = len(self._A_rows)
        order = sp.coo_matrix(
            (np.arange(1, nnz + 1, dtype=float), (self._A_rows, self._A_cols)), shape=(row, L.size)
        )
        pattern = order.tocsc()
        csc_order = pattern.data.astype(int) - 1  # CSC slot -> our entry index
        slot_of_entry = np.empty(nnz, dtype=int)
        slot_of_entry[csc_order] = np.arange(nnz)
        self._constant_values = np.asarray(self._A_constants)[csc_order]
        self._b_slots, self._a_slots = slot_of_entry[b_entries], slot_of_entry[a_entries]
        self._A_template = pattern
        self._solver: osqp.OSQP | None = None

    def _entry(self, row: int, col: int, constant: float = 0.0) -> int:
        """Add a constraint entry (a ``constant`` one, or one a stage's matrices fill); its
        index in the order of entries."""
        self._A_rows.append(row)
        self._A_cols.append(col)
        self._A_constants.append(constant)
        return len(self._A_rows) - 1

    def _constraint_values(self, A_stages: np.ndarray, B_stages: np.ndarray) -> np.ndarray:
        """Values of every constraint entry, in the CSC order of the constraint matrix: the
        constants of the pattern with the stages' ``-B_k`` and ``-A_k`` written into their
        slots."""
        values = self._constant_values.copy()
        values[self._b_slots] = -B_stages
        values[self._a_slots] = -A_stages[1:]
        return values

    def _solve(self, x0: np.ndarray, s0: float) -> np.ndarray:
        st, L, model = self.settings, self._layout, self.model
        n, N, dt = L.n, L.N, st.dt_s
        plan_x, plan_u = self._linearisation_trajectory(x0, s0)
        # The models raise a lower speed to MIN_SPEED_MPS inside: linearised at a standstill
        # they moved the car at that speed whatever its own, a stopped plan turned the car in
        # place (the expert stood in Shanghai's hairpin; the predictive filter certified a
        # car standing still in Melbourne's kink). Linearised at the raised speed, the terms
        # linear in speed vanish at zero: a plan turns the car only by driving it.
        plan_x[:, model.speed_index] = np.maximum(plan_x[:, model.speed_index], MIN_SPEED_MPS)
        s_stage, kappas = self._stages_along_map(plan_x[:N, : model.n_state], s0, dt)
        A_stages, B_stages, c_stages = model.discretize_stages_with_steering_lag(
            plan_x[:N], plan_u, kappas, dt, self.params.steer_time_constant_s
        )
        s_ref = s_stage[1:]
        upper, lower = self._lane_bounds(s_stage, plan_x)
        reference = np.zeros((N, n))  # looked up where a state is weighed
        reference[:, 0] = self._offset_reference(s_ref)
        if st.weight_e_psi:
            reference[:, 1] = self.reference.heading_offset_at(s_ref)
        if st.weight_speed:
            reference[:, model.speed_index] = st.speed_scale * self.reference.speed_at(s_ref)
        p = self.drivetrain
        u_min, u_max = self._input_bounds(plan_x)
        step = p.max_steer_rate_radps * dt
        rate_lower, rate_upper = np.full(N, -step), np.full(N, step)
        rate_lower[0] += self._previous_u[0]
        rate_upper[0] += self._previous_u[0]
        stage_qp = StageQP(
            x0=x0,
            A=A_stages,
            B=B_stages,
            c=c_stages,
            reference=reference,
            first_input_linear=-2.0
            * (self._rate_weights * self._rate_anchor() + self._first_input_pull()),
            input_lower=u_min,
            input_upper=u_max,
            rate_lower=rate_lower,
            rate_upper=rate_upper,
            lane_lower=lower,
            lane_upper=upper,
            speed_caps=self._speed_caps_mps(s_ref, plan_x[1:]) if self.speed_rows else None,
            heading_bound=self.terminal_heading_rad,
        )
        start = time.perf_counter()
        solution = self._solve_qp(stage_qp)
        self.stats.solve_times_s.append(time.perf_counter() - start)
        if solution is None:
            self.stats.failures += 1
            u = plan_u[0]
            self._plan_x = self._plan_slack = None
            return np.clip(
                u, [-p.max_steer_rad, -p.max_brake_mps2], [p.max_steer_rad, p.max_accel_mps2]
            )
        states, self._plan_u, self._plan_slack = solution
        self._plan_x = np.vstack([x0, states])
        return self._plan_u[0].copy()

    def _solve_qp(self, qp: StageQP) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The plan's states ``x_1 .. x_N``, inputs and slacks (None if OSQP failed): the
        sparse QP over all three, warm-started from the last."""
        L = self._layout
        N, n, m = L.N, L.n, L.m
        q, lo, hi, a_values = self.sparse_vectors(qp)
        if self._solver is None:
            A = self._A_template.copy()
            A.data = a_values
            self._solver = osqp.OSQP()
            self._solver.setup(
                P=self._P,
                q=q,
                A=A,
                l=lo,
                u=hi,
                eps_abs=1e-4,
                eps_rel=1e-4,
                max_iter=4000,
                warm_starting=True,
                polishing=False,
                verbose=False,
            )
        else:
            self._solver.update(q=q, l=lo, u=hi, Ax=a_values)
        result = self._solver.solve(raise_error=False)
        solved = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)
        if result.info.status_val not in solved:
            return None
        z = result.x
        return z[: N * n].reshape(N, n), z[L.u(0) : L.eps(0)].reshape(N, m), z[L.eps(0) :]

    def sparse_vectors(self, qp: StageQP) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The sparse QP's linear cost, row bounds (lower, upper) and the values of its
        constraint matrix (in the CSC order of ``_A_template``) for ``qp``: its variables
        are ``x_1 .. x_N``, ``u_0 .. u_{N-1}``, then the slacks."""
        L = self._layout
        N, n, m = L.N, L.n, L.m
        q = np.zeros(L.size)
        q[: N * n] = -2.0 * (qp.reference * self._q_state).ravel()
        q[L.u(0) : L.u(0) + m] = qp.first_input_linear
        q[L.eps(0) :] = self._slack_costs
        lo = np.empty(self._n_rows)
        hi = np.empty(self._n_rows)
        lo[: N * n] = hi[: N * n] = qp.dynamics_offsets.ravel()
        inputs = slice(self._input_rows, self._rate_rows)
        lo[inputs], hi[inputs] = qp.input_lower.ravel(), qp.input_upper.ravel()
        rates = slice(self._rate_rows, self._lane_rows)
        lo[rates], hi[rates] = qp.rate_lower, qp.rate_upper
        lane = slice(self._lane_rows, self._slack_rows)
        lo[lane] = np.column_stack([np.full(N, -np.inf), qp.lane_lower]).ravel()
        hi[lane] = np.column_stack([qp.lane_upper, np.full(N, np.inf)]).ravel()
        lo[self._slack_rows : self._speed_rows] = 0.0
        hi[self._slack_rows : self._speed_rows] = np.inf
        if qp.speed_caps is not None:
            lo[self._speed_rows : self._heading_rows] = 0.0  # the models drive forward only
            hi[self._speed_rows : self._heading_rows] = qp.speed_caps
        if qp.heading_bound is not None:
            lo[self._heading_rows :] = [-np.inf, -qp.heading_bound]
            hi[self._heading_rows :] = [qp.heading_bound, np.inf]
        return q, lo, hi, self._constraint_values(qp.A, qp.B)

    # ------------------------------------------------ what a planner on this QP changes
    #: Whether the QP caps each stage's speed (rows ``v_k - eps_k <= cap_k``).
    speed_rows = False
    #: A bound on the last stage's heading error, growing with its speed (rad, rad per m/s;
    #: rows ``|e_psi_N| - terminal_heading_per_mps v_N - eps_N <= terminal_heading_rad``).
    terminal_heading_rad: float | None = None
    terminal_heading_per_mps = 0.0
    #: The speed caps' and terminal heading's slack penalties relative to the lane's.
    other_slack_weight = 1.0

    def _slack_weights(self) -> np.ndarray:
        """Each slack's weight relative to the settings' penalties: the lane's per stage,
        then the speed caps' and the terminal heading's, at ``other_slack_weight``."""
        N, slacks = self.settings.horizon, self._layout.slacks
        return np.concatenate([np.ones(N), np.full(slacks - N, self.other_slack_weight)])

    def _input_weights(self) -> np.ndarray:
        """Weights ``(N, m)`` of each input's squared size: the settings' effort weights."""
        s = self.settings
        return np.tile([s.weight_steer, s.weight_accel], (s.horizon, 1))

    def _rate_anchor(self) -> np.ndarray:
        """What the first input's change is penalised from: the last command."""
        return self._previous_u

    def _first_input_pull(self) -> np.ndarray:
        """``w u_target``: the first input's linear cost is ``-2 w u_target`` (none here)."""
        return np.zeros(self.model.n_control)

    def _lane_bounds(
        self, s_stage: np.ndarray, plan_x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(upper, lower)`` of each stage's lateral offset at the stages' predicted arc
        lengths (:meth:`lane_limits`)."""
        return self.lane_limits(s_stage[1:])

    def lane_limits(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(upper, lower)`` of the car's lateral offset at arc lengths ``s_m``: the lane
        less the car's half width and the settings' margin."""
        w_right, w_left = self.track.widths(s_m)
        clearance = self.half_width_m + self.settings.lane_margin_m
        return w_left - clearance, -(w_right - clearance)

    def _offset_reference(self, s_ref: np.ndarray) -> np.ndarray:
        """Each stage's reference lateral offset at its arc length (after
        :meth:`_lane_bounds`): the reference line's."""
        return np.asarray(self.reference.offset_at(s_ref), dtype=float)

    def _input_bounds(self, plan_x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(u_min, u_max)`` of each stage ``(N, m)``: the drivetrain's limits (copies, for
        a planner to narrow)."""
        return self._drivetrain_bounds[0].copy(), self._drivetrain_bounds[1].copy()

    def _speed_caps_mps(self, s_m: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Each stage's speed cap at its arc length and state (with ``speed_rows``)."""
        return np.full(len(s_m), np.inf)

    def _stages_along_map(
        self, states: np.ndarray, s0_m: float, dt_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The arc length each stage starts at (and the last ends at), and the centre
        line's mean curvature over the stretch each stage covers.

        The mean curvature is the centre line's heading change over the stretch divided
        by its length: a kink shorter than a stage (real circuits' centre lines have some,
        1-2 m of 1/m curvature) turns the Frenet frame by what it really turns, where a
        point sample could miss it or see only its peak. The stretch is the model's
        ``s_dot`` at the curvature where the stage starts; the stage then moves on by
        ``s_dot`` at the mean curvature.
        """
        centerline = self.track.centerline
        return stages_along_map(
            self.model.along_track_speeds_mps(states) * dt_s,
            np.ascontiguousarray(states[:, 0]),
            float(s0_m),
            centerline.piece_array,
            centerline.knot_spacing_m,
            centerline.length_m,
        )

    def _linearisation_trajectory(self, x0: np.ndarray, s0: float) -> tuple[np.ndarray, np.ndarray]:
        """States and inputs to linearise about: the last plan shifted by one step.

        Only the first step of an episode, with no plan yet, rolls the nonlinear model
        out from ``x0`` with the curvature's feed-forward steering.
        """
        N, dt, n = self.settings.horizon, self.settings.dt_s, self.model.n_state
        if self._plan_x is not None:
            x = np.vstack([x0, self._plan_x[2:], self._plan_x[-1:]])
            u = np.vstack([self._plan_u[1:], self._plan_u[-1:]])
            return x, u
        u = np.zeros((N, self.model.n_control))
        x = np.empty((N + 1, n + 1))
        x[0] = x0
        s = s0
        for k in range(N):
            kappa = self.track.centerline.curvature_scalar(s)
            u[k, 0] = np.arctan(self.params.wheelbase_m * kappa)
            x[k + 1, :n] = self.model.step(x[k, :n], u[k], kappa, dt)
            x[k + 1, n] = u[k, 0]
            s += self.model.s_dot(x[k, :n], kappa) * dt
        return x, u


class _Layout:
    """Positions of the decision variables: states x_1..x_N, inputs u_0..u_{N-1}, then a
    lane slack per stage and ``extra_slacks`` more (the speed caps', the terminal heading's)."""

    def __init__(self, n: int, m: int, horizon: int, extra_slacks: int = 0) -> None:
        self.n, self.m, self.N = n, m, horizon
        self.slacks = horizon + extra_slacks
        self.size = horizon * (n + m) + self.slacks

    def x(self, k: int) -> int:
        """Index of x_{k+1} (the state after input k)."""
        return k * self.n

    def u(self, k: int) -> int:
        return self.N * self.n + k * self.m

    def eps(self, k: int) -> int:
        return self.N * (self.n + self.m) + k
