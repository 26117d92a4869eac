"""Time one Frenet projection per control step: local search against a global scan.

Target: under 20 microseconds per call with the local search. The baseline, measured
in the same run, projects the same points with a fresh projector each time (a global
scan of the track's knots, then the same Newton refinement).

    python benchmarks/frenet_speed.py
"""

from __future__ import annotations

import time

import numpy as np

from saferace.eval.tables import markdown_table
from saferace.track import Track, builtin_track_names

TARGET_US = 20.0
STEP_M = 0.35  # 7 m/s at 20 Hz


def driven_poses(track: Track) -> np.ndarray:
    s = np.arange(0.0, 3.0 * track.length_m, STEP_M)
    e_y = 0.3 * np.sin(s / 2.0)
    xy = track.centerline.position(s) + e_y[:, None] * track.centerline.normal(s)
    yaw = track.centerline.heading(s) + 0.1
    return np.column_stack([xy, yaw])


def per_call_us(track: Track, poses: np.ndarray, fresh_each_call: bool) -> float:
    projector = track.projector()
    rows = poses.tolist()
    start = time.perf_counter()
    for x, y, yaw in rows:
        if fresh_each_call:
            projector.reset()
        projector.to_frenet(x, y, yaw)
    return (time.perf_counter() - start) / len(rows) * 1e6


def main() -> None:
    rows = []
    for name in builtin_track_names():
        track = Track.load(name)
        poses = driven_poses(track)
        local = min(per_call_us(track, poses, False) for _ in range(3))
        scan = min(per_call_us(track, poses, True) for _ in range(3))
        rows.append(
            [
                name,
                len(track.centerline.knot_xy),
                local,
                scan,
                f"{scan / local:.1f}x",
                "met" if local < TARGET_US else "MISSED",
            ]
        )
    print(
        markdown_table(
            [
                "track",
                "knots",
                "local [us/call]",
                "global scan [us/call]",
                "speed-up",
                f"< {TARGET_US:.0f} us",
            ],
            rows,
        )
    )


if __name__ == "__main__":
    main()
