"""Time the minimum-curvature racing line on a 1000-point track, and on a 560 m circuit.

Target: under 2 s on a 2-core CPU. As a baseline measured in the same run, the first
of its QPs is also solved through cvxpy with the interior-point solver Clarabel (the
reference formulation); the table gives how far OSQP's offsets are from it. The same track
scaled to 560 m with the F1TENTH collection's 2.2 m lane (the longest of its circuits) is
timed at the default 0.1 m step: what a user waits for the first time a real circuit's
``RacingLine-v0`` is made (the line is then kept for the process).

    python benchmarks/raceline_speed.py
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import cvxpy as cp
import numpy as np

from saferace.eval.tables import markdown_table
from saferace.track import Track, VehicleEnvelope
from saferace.track.raceline import (
    RacingLineSettings,
    center_line,
    curvature_qp,
    min_curvature_offsets,
    offset_bounds,
    racing_line,
)

TARGET_S = 2.0
POINTS = 1000
LONG_TRACK_M = 560.0


def thousand_point_track(scale: float = 1.0, half_width_m: float = 0.6) -> Track:
    theta = np.linspace(0.0, 2.0 * np.pi, POINTS, endpoint=False)
    radius = scale * (9.0 + 1.2 * np.cos(3 * theta) + 0.6 * np.sin(5 * theta + 0.4))
    return Track.from_arrays(
        1.3 * radius * np.cos(theta),
        radius * np.sin(theta),
        half_width_m,
        half_width_m,
        name=f"blob{POINTS}" if scale == 1.0 else f"blob{POINTS} x{scale:.1f}",
    )


def best_of(repeats: int, work) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    start = time.perf_counter()
    track = thousand_point_track()
    load_s = time.perf_counter() - start
    settings = RacingLineSettings(step_m=track.length_m / POINTS)
    envelope = VehicleEnvelope()
    racing_s = best_of(3, lambda: racing_line(track, envelope, settings))
    center_s = best_of(3, lambda: center_line(track, envelope, settings.step_m))

    center_s_m = track.centerline.sample(settings.step_m)
    P, q, _ = curvature_qp(track, center_s_m, np.zeros(len(center_s_m)))
    lower, upper = offset_bounds(track, center_s_m, envelope.width_m, settings.margin_m)
    alpha = cp.Variable(len(center_s_m))
    problem = cp.Problem(
        cp.Minimize(0.5 * cp.quad_form(alpha, cp.psd_wrap(P)) + q @ alpha),
        [alpha >= lower, alpha <= upper],
    )
    logging.getLogger("saferace").setLevel(logging.ERROR)  # one iteration on purpose
    cvxpy_s = best_of(1, lambda: problem.solve(solver=cp.CLARABEL))
    osqp_offsets = min_curvature_offsets(
        track,
        center_s_m,
        envelope.width_m,
        replace(settings, max_iterations=1, draft_tolerance=None),
    )
    gap_m = float(np.max(np.abs(osqp_offsets - alpha.value)))
    long_track = thousand_point_track(scale=LONG_TRACK_M / track.length_m, half_width_m=1.1)
    long_s = best_of(1, lambda: racing_line(long_track, envelope))
    long_offsets = round(long_track.length_m / RacingLineSettings().step_m)

    rows = [
        ["load + validate 1000-point track", load_s, "-"],
        ["center line + speed profile", center_s, "-"],
        [
            f"racing line ({len(center_s_m)} offsets, all iterations)",
            racing_s,
            f"{racing_s / TARGET_S:.2f} of target",
        ],
        [
            "one QP, cvxpy + Clarabel (baseline)",
            cvxpy_s,
            f"racing line = {racing_s / cvxpy_s:.1f}x this",
        ],
        ["  max |OSQP - Clarabel| offset [m]", gap_m, "-"],
        [
            f"racing line, {long_track.length_m:.0f} m circuit, 2.2 m lane "
            f"({long_offsets} offsets)",
            long_s,
            "-",
        ],
    ]
    print(markdown_table(["step", "time [s]", "ratio"], rows))
    print(
        f"target: racing line under {TARGET_S:.1f} s -> "
        f"{'met' if racing_s < TARGET_S else 'MISSED'}"
    )


if __name__ == "__main__":
    main()
