"""Generate the built-in track CSVs in saferace/assets/tracks/ (how each track was made).

Each track is a closed curve through hand-placed anchor points (a periodic cubic
spline by chord length), or an analytic shape, sampled every 0.2 m, with lane
half-widths given as functions of the normalised arc length. Run it from the
repository root: ``python scripts/design_tracks.py``; it prints each track's length,
width range and tightest radius (the numbers in the tracks' READMEs).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from saferace.track import ClosedPath, Track
from saferace.track.track_io import write_track_csv

OUT_DIR = Path(__file__).resolve().parents[1] / "saferace" / "assets" / "tracks"
SAMPLE_STEP_M = 0.2

HalfWidth = Callable[[np.ndarray], np.ndarray]


def oval() -> np.ndarray:
    """Two 8 m straights joined by semicircles of radius 3 m; starts mid bottom straight."""
    straight, radius = 8.0, 3.0
    length = 2 * straight + 2 * np.pi * radius
    s = np.arange(0.0, length, SAMPLE_STEP_M)
    s = np.linspace(0.0, length, len(s), endpoint=False)
    points = np.empty((len(s), 2))
    for i, u in enumerate(s):
        u = (u + straight / 2) % length
        if u < straight:
            points[i] = (-straight / 2 + u, -radius)
        elif u < straight + np.pi * radius:
            a = -np.pi / 2 + (u - straight) / radius
            points[i] = (straight / 2 + radius * np.cos(a), radius * np.sin(a))
        elif u < 2 * straight + np.pi * radius:
            points[i] = (straight / 2 - (u - straight - np.pi * radius), radius)
        else:
            a = np.pi / 2 + (u - 2 * straight - np.pi * radius) / radius
            points[i] = (-straight / 2 + radius * np.cos(a), radius * np.sin(a))
    return points


LAB_ANCHORS = [
    (0.0, 0.0),
    (3.0, 0.0),
    (5.5, 0.1),
    (6.8, 0.9),
    (7.0, 2.4),
    (6.2, 3.4),
    (4.8, 3.4),
    (3.8, 2.6),
    (2.6, 2.5),
    (1.6, 3.4),
    (0.4, 4.2),
    (-1.2, 4.0),
    (-2.0, 2.8),
    (-2.0, 1.2),
    (-1.4, 0.2),
]

TECHNICAL_ANCHORS = [
    (0.0, 0.0),
    (8.0, 0.0),
    (16.0, 0.0),
    (18.4, 0.6),
    (19.4, 2.6),
    (19.4, 5.0),
    (18.9, 7.2),
    (17.6, 7.9),
    (16.4, 7.2),
    (16.2, 5.6),
    (15.4, 4.4),
    (13.5, 4.0),
    (11.8, 4.9),
    (10.0, 5.4),
    (8.2, 4.6),
    (6.4, 3.9),
    (4.6, 4.6),
    (3.0, 5.6),
    (1.0, 5.8),
    (-1.2, 5.0),
    (-2.4, 3.4),
    (-2.3, 1.4),
    (-1.4, 0.2),
]

VARYING_ANCHORS = [
    (0.0, 0.0),
    (6.0, -0.4),
    (10.0, 0.6),
    (12.2, 3.0),
    (11.8, 6.0),
    (9.6, 7.6),
    (7.0, 7.0),
    (5.6, 5.2),
    (3.6, 4.6),
    (1.0, 6.0),
    (-1.8, 6.4),
    (-3.6, 4.6),
    (-3.4, 1.8),
    (-2.0, 0.4),
]


def through_anchors(anchors: list[tuple[float, float]]) -> np.ndarray:
    """Points every SAMPLE_STEP_M along the periodic spline through ``anchors``."""
    path = ClosedPath(np.asarray(anchors, dtype=float))
    return path.position(path.sample(SAMPLE_STEP_M))


def constant(half_width_m: float) -> HalfWidth:
    return lambda u: np.full_like(u, half_width_m)


def varying(u: np.ndarray) -> np.ndarray:
    """Half width from 0.4 m to 0.75 m and back, twice per lap (lane 0.8-1.5 m)."""
    return 0.575 - 0.175 * np.cos(4 * np.pi * u)


DESIGNS: dict[str, tuple[Callable[[], np.ndarray], HalfWidth]] = {
    "oval": (oval, constant(0.6)),
    "lab": (lambda: through_anchors(LAB_ANCHORS), constant(0.4)),
    "technical": (lambda: through_anchors(TECHNICAL_ANCHORS), constant(0.5)),
    "varying": (lambda: through_anchors(VARYING_ANCHORS), varying),
}


def main() -> None:
    for name, (make_points, half_width) in DESIGNS.items():
        points = make_points()
        u = np.linspace(0.0, 1.0, len(points), endpoint=False)
        width = half_width(u)
        path = OUT_DIR / f"{name}.csv"
        write_track_csv(path, points[:, 0], points[:, 1], width, width)
        track = Track.load(path)
        lane = 2 * width
        print(
            f"{name}: {len(points)} points, length {track.length_m:.2f} m, "
            f"lane {lane.min():.2f}-{lane.max():.2f} m, "
            f"tightest radius {track.min_turn_radius_m():.2f} m"
        )


if __name__ == "__main__":
    main()
