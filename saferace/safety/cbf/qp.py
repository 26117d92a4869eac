"""The safety filter's QP (paper's final equation), solved exactly for its two controls.

    min_u  (u - u_mean)^T diag(u_std^2)^-1 (u - u_mean) + k_err * sum_j eps_j^2
    s.t.   a_j^T u - b_j + z sqrt(c(u)^T Sigma_j c(u)) <= eps_j   (one slack per constraint)
           lower <= u <= upper                                    (actuator limits)

with ``c(u) = [u; -1]`` (see :mod:`saferace.safety.cbf.chance`; ``z = 0`` or no covariance is
the deterministic filter). The best slack is ``eps_j = max(0, g_j(u))`` where ``g_j`` is the
constraint's left side, so the problem is the minimisation of a strictly convex,
continuously differentiable function of two variables over a box:

    F(u) = (u - u_mean)^T W (u - u_mean) + k_err * sum_j max(0, g_j(u))^2.

:func:`solve_filter_qp` minimises it by projected Newton steps with an Armijo search along
the projection arc (Bertsekas 1982); on the deterministic QP this is a semismooth Newton
method that ends after a few steps, and it handles the cone exactly. Plain Python floats:
at two variables and four constraints, array libraries and general QP solvers spend more
time on their own overhead than on the problem (``benchmarks/filter_speed.py``).

:func:`solve_filter_qp_linearised` is the other route of DESIGN.md Sec. 6: linearise the
square root and iterate. ``sqrt`` is concave, so its tangent at ``q_k = c(u_k)^T Sigma
c(u_k)`` is an upper bound, ``sqrt(q) <= (q + q_k) / (2 sqrt(q_k))``, tight at ``u_k``. Each
round solves the problem with that conservative constraint; the rounds are a
majorise-minimise sequence whose objective falls monotonically to the cone's optimum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ARMIJO_FRACTION = 1e-4
GRADIENT_TOLERANCE = 1e-9
#: Stop when the Newton decrement (the model's predicted decrease) is below this, relative:
#: large slack weights scale the gradient's rounding noise beyond GRADIENT_TOLERANCE.
NEWTON_DECREMENT_TOLERANCE = 1e-20
#: ... or when the full Newton step (the distance to the minimum of the local quadratic
#: model) is below this, relative to the control.
STEP_TOLERANCE = 1e-8
MAX_NEWTON_STEPS = 60
MAX_LINE_SEARCH_HALVINGS = 60
MAX_RESCUE_ROUNDS = 30
MIN_STD = 1e-12  # below this a constraint's spread counts as zero
MIN_ANCHOR_STD = 1e-9  # floor of the linearisation point of the square root


@dataclass(frozen=True)
class FilterProblem:
    """One step's filter QP. ``u_std`` must already carry its floor (see SafetyFilter)."""

    u_mean: np.ndarray  # (2,) nominal [steer_rad, accel_mps2]
    u_std: np.ndarray  # (2,)
    a: np.ndarray  # (B, 2) mean constraint rows
    b: np.ndarray  # (B,)
    lower: np.ndarray  # (2,)
    upper: np.ndarray  # (2,)
    k_err: float
    covariance: np.ndarray | None = None  # (B, 3, 3) of [a; b], or None: deterministic
    z: float = 0.0  # Phi^-1(eta)

    def __post_init__(self) -> None:
        if np.any(np.asarray(self.u_std) <= 0.0):
            raise ValueError(f"u_std must be positive, got {self.u_std}")
        if self.k_err <= 0.0:
            raise ValueError(f"k_err must be positive, got {self.k_err}")
        if np.any(np.asarray(self.lower) > np.asarray(self.upper)):
            raise ValueError(f"lower {self.lower} exceeds upper {self.upper}")


@dataclass(frozen=True)
class FilterSolution:
    """The filtered control, each constraint's slack, and how the solve ended."""

    u: np.ndarray
    slack: np.ndarray
    status: str  # "solved", "stalled", "max_iterations" or "non_finite"
    iterations: int

    @property
    def solved(self) -> bool:
        return self.status == "solved"


class PenaltyObjective:
    """``F(u)`` with its gradient and Hessian, in plain floats for speed."""

    def __init__(self, problem: FilterProblem, anchors: list[float] | None = None) -> None:
        self.mean = np.asarray(problem.u_mean, dtype=float).tolist()
        self.weight = (1.0 / np.asarray(problem.u_std, dtype=float) ** 2).tolist()
        self.k_err = float(problem.k_err)
        chance = problem.covariance is not None and problem.z > 0.0
        self.z = float(problem.z) if chance else 0.0
        a, b = np.asarray(problem.a, dtype=float).tolist(), np.asarray(problem.b).tolist()
        sigmas: list[list[float]] | list[None] = [None] * len(b)
        sigma_total = 0.0
        if chance:
            covariances: list[list[float]] = (
                np.asarray(problem.covariance, dtype=float).reshape(len(b), 9).tolist()
            )
            sigmas, sigma_total = covariances, sum(map(sum, covariances))
        anchor_stds: list[float] | list[None]
        if anchors is None:
            anchor_stds = [None] * len(b)
        else:
            anchor_stds = [max(anchor, MIN_ANCHOR_STD) for anchor in anchors]
        self.rows = [
            (row[0], row[1], offset, sigma, anchor)
            for row, offset, sigma, anchor in zip(a, b, sigmas, anchor_stds, strict=True)
        ]
        total = sum(self.mean) + sum(self.weight) + sum(map(sum, a)) + sum(b)
        total += sigma_total
        self.finite = math.isfinite(total)  # a NaN or inf anywhere makes the sum non-finite

    @staticmethod
    def spread(row, u0: float, u1: float) -> tuple[float, float, float, float, float, float]:
        """``s(u)`` (the constraint's std, or its upper bound), its gradient and Hessian."""
        s00, s01, s02, _, s11, s12, _, _, s22 = row[3]
        sc0 = s00 * u0 + s01 * u1 - s02  # (Sigma c)[:2]
        sc1 = s01 * u0 + s11 * u1 - s12
        q = max(sc0 * u0 + sc1 * u1 - (s02 * u0 + s12 * u1 - s22), 0.0)
        anchor = row[4]
        if anchor is not None:  # the square root's tangent in q at the anchor
            return (
                (q + anchor * anchor) / (2 * anchor),
                sc0 / anchor,
                sc1 / anchor,
                s00 / anchor,
                s01 / anchor,
                s11 / anchor,
            )
        s = math.sqrt(q)
        if s < MIN_STD:
            return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        g0, g1 = sc0 / s, sc1 / s
        return s, g0, g1, (s00 - g0 * g0) / s, (s01 - g0 * g1) / s, (s11 - g1 * g1) / s

    def constraint_values(self, u0: float, u1: float) -> list[float]:
        """``g_j(u)``: positive where constraint ``j`` needs slack."""
        z = self.z
        return [
            row[0] * u0 + row[1] * u1 - row[2] + (z * self.spread(row, u0, u1)[0] if z else 0.0)
            for row in self.rows
        ]

    def value(self, u0: float, u1: float) -> float:
        d0, d1 = u0 - self.mean[0], u1 - self.mean[1]
        total = self.weight[0] * d0 * d0 + self.weight[1] * d1 * d1
        for g in self.constraint_values(u0, u1):
            if g > 0.0:
                total += self.k_err * g * g
        return total

    def derivatives(self, u0: float, u1: float) -> tuple[float, float, float, float, float]:
        """Gradient ``(g0, g1)`` and Hessian ``(h00, h01, h11)`` of ``F``."""
        w0, w1, k, z = self.weight[0], self.weight[1], self.k_err, self.z
        g0 = 2 * w0 * (u0 - self.mean[0])
        g1 = 2 * w1 * (u1 - self.mean[1])
        h00, h01, h11 = 2 * w0, 0.0, 2 * w1
        for row in self.rows:
            value = row[0] * u0 + row[1] * u1 - row[2]
            d0, d1, c00, c01, c11 = row[0], row[1], 0.0, 0.0, 0.0
            if z:
                s, s0, s1, s00, s01, s11 = self.spread(row, u0, u1)
                value += z * s
                d0, d1 = d0 + z * s0, d1 + z * s1
                c00, c01, c11 = z * s00, z * s01, z * s11
            if value <= 0.0:
                continue
            kv = 2 * k * value
            g0 += kv * d0
            g1 += kv * d1
            h00 += 2 * k * d0 * d0 + kv * c00
            h01 += 2 * k * d0 * d1 + kv * c01
            h11 += 2 * k * d1 * d1 + kv * c11
        return g0, g1, h00, h01, h11


def _minimise(
    objective: PenaltyObjective, start: list[float], lower: list[float], upper: list[float]
) -> tuple[list[float], str, int]:
    u = [min(max(start[0], lower[0]), upper[0]), min(max(start[1], lower[1]), upper[1])]
    f = objective.value(*u)
    for iteration in range(1, MAX_NEWTON_STEPS + 1):
        g0, g1, h00, h01, h11 = objective.derivatives(*u)
        free0 = not ((u[0] <= lower[0] and g0 > 0.0) or (u[0] >= upper[0] and g0 < 0.0))
        free1 = not ((u[1] <= lower[1] and g1 > 0.0) or (u[1] >= upper[1] and g1 < 0.0))
        projected = max(abs(g0) if free0 else 0.0, abs(g1) if free1 else 0.0)
        if projected <= GRADIENT_TOLERANCE:
            return u, "solved", iteration
        if free0 and free1:
            det = h00 * h11 - h01 * h01
            step = [-(h11 * g0 - h01 * g1) / det, -(h00 * g1 - h01 * g0) / det]
        else:
            step = [-g0 / h00 if free0 else 0.0, -g1 / h11 if free1 else 0.0]
        if -(g0 * step[0] + g1 * step[1]) <= NEWTON_DECREMENT_TOLERANCE * (1.0 + abs(f)) or (
            abs(step[0]) <= STEP_TOLERANCE * (1.0 + abs(u[0]))
            and abs(step[1]) <= STEP_TOLERANCE * (1.0 + abs(u[1]))
        ):
            return u, "solved", iteration  # within rounding of the minimum
        t = 1.0
        for _ in range(MAX_LINE_SEARCH_HALVINGS):
            trial = [
                min(max(u[0] + t * step[0], lower[0]), upper[0]),
                min(max(u[1] + t * step[1], lower[1]), upper[1]),
            ]
            decrease = g0 * (trial[0] - u[0]) + g1 * (trial[1] - u[1])
            f_trial = objective.value(*trial)
            if f_trial <= f + ARMIJO_FRACTION * decrease:
                break
            t *= 0.5
        else:
            return u, "stalled", iteration  # no descent found along the Newton direction
        if not math.isfinite(f_trial):
            return u, "non_finite", iteration
        moved = abs(trial[0] - u[0]) + abs(trial[1] - u[1])
        u, f = trial, f_trial
        if moved <= 1e-15 * (1.0 + abs(u[0]) + abs(u[1])):
            return u, "stalled", iteration
    return u, "stalled", MAX_NEWTON_STEPS


def _active_set_minimum(
    objective: PenaltyObjective,
    rows: list[tuple[float, float, float]],
    lower: list[float],
    upper: list[float],
) -> list[float] | None:
    """The exact minimiser of ``F`` with affine constraints ``rows`` (``a0 u0 + a1 u1 <= b``).

    Tries every set of violated constraints and every box face, fewest violated first, and
    returns the one candidate that satisfies the optimality conditions (``F`` is strictly
    convex, so there is exactly one). Slow next to Newton (up to ``2^B * 9`` 2x2 solves),
    but immune to the ill-conditioning of nearly parallel constraints with a large slack
    weight, where Newton steps crawl.
    """
    w0, w1 = objective.weight
    m0, m1 = objective.mean
    k = objective.k_err
    scale = 1.0 + max(abs(b) for _, _, b in rows) + max(abs(a0) + abs(a1) for a0, a1, _ in rows)
    tolerance = 1e-9 * scale
    faces = (
        (None, None),
        (None, 0),
        (None, 1),
        (0, None),
        (1, None),
        (0, 0),
        (0, 1),
        (1, 0),
        (1, 1),
    )
    bounds = (lower, upper)
    masks = sorted(range(1 << len(rows)), key=lambda mask: bin(mask).count("1"))
    for mask in masks:
        h00, h01, h11 = 2 * w0, 0.0, 2 * w1
        r0, r1 = 2 * w0 * m0, 2 * w1 * m1
        for j, (a0, a1, b) in enumerate(rows):
            if mask >> j & 1:
                h00 += 2 * k * a0 * a0
                h01 += 2 * k * a0 * a1
                h11 += 2 * k * a1 * a1
                r0 += 2 * k * b * a0
                r1 += 2 * k * b * a1
        for face0, face1 in faces:
            if face0 is None:
                if face1 is None:
                    det = h00 * h11 - h01 * h01
                    u0, u1 = (h11 * r0 - h01 * r1) / det, (h00 * r1 - h01 * r0) / det
                else:
                    u1 = bounds[face1][1]
                    u0 = (r0 - h01 * u1) / h00
            elif face1 is None:
                u0 = bounds[face0][0]
                u1 = (r1 - h01 * u0) / h11
            else:
                u0, u1 = bounds[face0][0], bounds[face1][1]
            if not (lower[0] - 1e-12 <= u0 <= upper[0] + 1e-12):
                continue
            if not (lower[1] - 1e-12 <= u1 <= upper[1] + 1e-12):
                continue
            g0, g1 = h00 * u0 + h01 * u1 - r0, h01 * u0 + h11 * u1 - r1  # gradient of F
            gradient_tolerance = 1e-7 * (1.0 + abs(r0) + abs(r1) + abs(h00 * u0) + abs(h11 * u1))
            if (face0 == 0 and g0 < -gradient_tolerance) or (
                face0 == 1 and g0 > gradient_tolerance
            ):
                continue
            if (face1 == 0 and g1 < -gradient_tolerance) or (
                face1 == 1 and g1 > gradient_tolerance
            ):
                continue
            consistent = True
            for j, (a0, a1, b) in enumerate(rows):
                g = a0 * u0 + a1 * u1 - b
                if (g < -tolerance) if mask >> j & 1 else (g > tolerance):
                    consistent = False
                    break
            if consistent:
                return [u0, u1]
    return None


def linearised_rows(
    objective: PenaltyObjective, u: list[float]
) -> list[tuple[float, float, float]]:
    """The constraints as affine rows ``(a0, a1, b)``, ``a0 u0 + a1 u1 <= b``, the chance
    constraints' spread replaced by its tangent at ``u``."""
    rows = []
    for row in objective.rows:
        a0, a1, b = row[0], row[1], row[2]
        if objective.z and row[3] is not None:
            s, s0, s1, *_ = objective.spread(row, *u)
            a0, a1 = a0 + objective.z * s0, a1 + objective.z * s1
            b = b - objective.z * s + objective.z * (s0 * u[0] + s1 * u[1])
        rows.append((a0, a1, b))
    return rows


def _rescue(
    objective: PenaltyObjective, u: list[float], lower: list[float], upper: list[float]
) -> tuple[list[float], str]:
    """When Newton stalls: exact active-set solves of the constraints linearised at ``u``
    (exact at once for affine constraints; for the cone, repeated to a fixed point)."""
    for _ in range(MAX_RESCUE_ROUNDS):
        new_u = _active_set_minimum(objective, linearised_rows(objective, u), lower, upper)
        if new_u is None:
            return u, "stalled"
        moved = abs(new_u[0] - u[0]) + abs(new_u[1] - u[1])
        u = new_u
        if not objective.z or moved <= 1e-10 * (1.0 + abs(u[0]) + abs(u[1])):
            return u, "solved"
    return u, "max_iterations"


def packaged_solution(objective: PenaltyObjective, u: list[float], status: str, iterations: int):
    """Package ``u`` with the exact constraints' slacks (``objective`` without anchors)."""
    slack = [max(g, 0.0) for g in objective.constraint_values(*u)]
    if not math.isfinite(u[0] + u[1] + sum(slack)):
        status = "non_finite"
    return FilterSolution(
        u=np.array(u), slack=np.array(slack), status=status, iterations=iterations
    )


def failed_solution(problem: FilterProblem) -> FilterSolution:
    count = len(problem.b)
    return FilterSolution(np.asarray(problem.u_mean, dtype=float), np.zeros(count), "non_finite", 0)


def solve_filter_qp(problem: FilterProblem) -> FilterSolution:
    """The exact minimiser (to ``GRADIENT_TOLERANCE``), starting from the clipped nominal."""
    objective = PenaltyObjective(problem)
    if not objective.finite:
        return failed_solution(problem)
    lower, upper = problem.lower.tolist(), problem.upper.tolist()
    u, status, iterations = _minimise(objective, objective.mean, lower, upper)
    if status == "stalled":
        u, status = _rescue(objective, u, lower, upper)
    return packaged_solution(objective, u, status, iterations)


def solve_filter_qp_linearised(
    problem: FilterProblem, tolerance: float = 1e-10, max_rounds: int = 200
) -> FilterSolution:
    """The chance-constrained QP by linearising the square root and iterating (see above).

    ``iterations`` counts the rounds; each round is a smooth problem with quadratic
    constraints solved by the same Newton method.
    """
    exact = PenaltyObjective(problem)
    if not exact.finite:
        return failed_solution(problem)
    lower, upper = problem.lower.tolist(), problem.upper.tolist()
    if exact.z == 0.0:
        u, status, _ = _minimise(exact, exact.mean, lower, upper)
        return packaged_solution(exact, u, status, 1)
    u = [min(max(v, lo), hi) for v, lo, hi in zip(exact.mean, lower, upper, strict=True)]
    for round_index in range(1, max_rounds + 1):
        anchors = [exact.spread(row, *u)[0] for row in exact.rows]
        new_u, status, _ = _minimise(PenaltyObjective(problem, anchors), u, lower, upper)
        if status != "solved":
            return packaged_solution(exact, new_u, status, round_index)
        moved = max(abs(new_u[0] - u[0]), abs(new_u[1] - u[1]))
        u = new_u
        if moved <= tolerance:
            return packaged_solution(exact, u, "solved", round_index)
    return packaged_solution(exact, u, "max_iterations", max_rounds)
