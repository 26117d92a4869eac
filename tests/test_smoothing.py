"""Smoothing a noisy centre line: less curvature to steer, the lane's widths or boundaries kept."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

from saferace.errors import TrackError
from saferace.names import SMOOTHING_KEEPS
from saferace.track import Track, smoothing
from saferace.track.track_io import write_track_csv

RADIUS_M, NOISE_M, HALF_WIDTH_M = 10.0, 0.02, 1.0


def noisy_circle(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A 10 m circle traced every 0.3 m with 2 cm of radial noise, as a map trace would be."""
    theta = np.linspace(0.0, 2.0 * np.pi, 210, endpoint=False)
    radius = RADIUS_M + NOISE_M * np.random.default_rng(seed).standard_normal(theta.size)
    return radius * np.cos(theta), radius * np.sin(theta)


def boundary_offsets_m(track: Track, x: np.ndarray, y: np.ndarray) -> list[np.ndarray]:
    """How far each boundary point of ``track`` lies radially from the given (noisy) points'
    radius at its angle: ``-HALF_WIDTH_M`` inside, ``+HALF_WIDTH_M`` outside, if kept."""
    given_angle, given_radius = np.arctan2(y, x), np.hypot(x, y)
    offsets = []
    for side in track.boundaries(0.02):
        angle = np.arctan2(side[:, 1], side[:, 0])
        radius_there = np.interp(angle, given_angle, given_radius, period=2.0 * np.pi)
        offsets.append(np.hypot(*side.T) - radius_there)
    return offsets


def test_smoothing_removes_the_noise_and_keeps_the_boundaries():
    x, y = noisy_circle()
    given = Track.from_arrays(x, y, HALF_WIDTH_M, HALF_WIDTH_M)
    smooth = Track.from_arrays(
        x, y, HALF_WIDTH_M, HALF_WIDTH_M, smooth_rms_m=NOISE_M, smooth_keeps="boundaries"
    )
    circle = 2.0 * np.pi / RADIUS_M  # integral of kappa^2 ds of the noiseless circle
    assert given.centerline.curvature_squared_integral() > 5.0 * circle
    assert smooth.centerline.curvature_squared_integral() == pytest.approx(circle, rel=0.1)
    assert smooth.smoothing.rms_shift_m == pytest.approx(NOISE_M, rel=0.5)
    assert smooth.smoothing.max_shift_m < 5.0 * NOISE_M
    left, right = boundary_offsets_m(smooth, x, y)  # where the given points put them
    assert np.abs(left + HALF_WIDTH_M).max() < 0.25 * NOISE_M
    assert np.abs(right - HALF_WIDTH_M).max() < 0.25 * NOISE_M
    assert given.narrowing.points > 0 and smooth.narrowing.points == 0  # noise folded the lane
    assert given.smoothing is None and smooth.point_count == given.point_count


def noisy_hairpins(radius_m: float = 1.6, straight_m: float = 100.0) -> np.ndarray:
    """A 100 m stadium with 1.6 m hairpins, traced every 0.35 m with 2 cm of noise: the shape
    of a 1/10-scale circuit's long straights and tight turns."""
    step_m = 0.35
    along = np.arange(0.0, straight_m, step_m)
    turn = np.linspace(-0.5 * np.pi, 0.5 * np.pi, int(np.pi * radius_m / step_m), endpoint=False)
    points = np.vstack(
        [
            np.column_stack([along, np.full(along.size, -radius_m)]),
            np.column_stack([straight_m + radius_m * np.cos(turn), radius_m * np.sin(turn)]),
            np.column_stack([straight_m - along, np.full(along.size, radius_m)]),
            np.column_stack([-radius_m * np.cos(turn), -radius_m * np.sin(turn)]),
        ]
    )
    return points + NOISE_M * np.random.default_rng(0).standard_normal(points.shape)


def test_smoothing_keeps_the_widths_by_default():
    """The lane of a circuit given by its centre line and widths (F1TENTH's) moves with the
    smoothed centre line: its widths stay as given, so its boundaries lose the noise too."""
    x, y = noisy_circle()
    angle = np.arctan2(y, x)
    w_left = HALF_WIDTH_M + 0.3 * np.sin(3.0 * angle)
    smooth = Track.from_arrays(x, y, HALF_WIDTH_M, w_left, smooth_rms_m=NOISE_M)
    s = smooth.centerline.sample(0.05)
    x_s, y_s = smooth.centerline.position(s).T
    w_right_s, w_left_s = smooth.widths(s)
    assert np.allclose(w_right_s, HALF_WIDTH_M) and smooth.smoothing.keeps == "widths"
    assert np.abs(w_left_s - (HALF_WIDTH_M + 0.3 * np.sin(3.0 * np.arctan2(y_s, x_s)))).max() < 0.01
    outer = np.hypot(*smooth.boundaries(0.02)[1].T)  # the circle turns left: right is outside
    assert np.ptp(outer) < 0.25 * np.ptp(np.hypot(x, y))  # the noise left the boundary too
    with pytest.raises(TrackError, match="keeps one of"):
        Track.from_arrays(x, y, 1.0, 1.0, smooth_rms_m=NOISE_M, smooth_keeps="edges")


def test_smoothing_spaces_its_points_evenly():
    """A trace whose points alternate 5 and 55 mm apart (a map traced at varying speed) is
    smoothed into evenly spaced points, each given point weighing the stretch it covers."""
    gaps = np.where(np.arange(200) % 2 == 0, 0.05, 0.55)
    theta = 2.0 * np.pi * np.concatenate([[0.0], np.cumsum(gaps[:-1])]) / gaps.sum()
    radius = RADIUS_M + NOISE_M * np.random.default_rng(0).standard_normal(theta.size)
    x, y = radius * np.cos(theta), radius * np.sin(theta)
    smooth = Track.from_arrays(x, y, HALF_WIDTH_M, HALF_WIDTH_M, smooth_rms_m=NOISE_M)
    spacing = np.diff(smooth.point_s_m)
    assert np.ptp(spacing) < 0.05 * spacing.mean()  # even in chord length, not quite arc length
    assert smooth.min_turn_radius_m() > 0.9 * RADIUS_M


def test_a_tolerance_smoothing_cannot_reach_is_refused():
    x, y = noisy_circle()
    with pytest.raises(TrackError, match=r"outside what smoothing this centre line can move"):
        Track.from_arrays(x, y, 1.0, 1.0, smooth_rms_m=50.0)


def test_smoothing_keeps_the_hairpins_of_a_long_circuit():
    """The penalised spline follows a 1.6 m hairpin between 100 m straights; FITPACK's
    smoothing spline (``splprep``, few knots on a long lap) cut it to a 1.13 m radius (and
    Yas Marina's 0.42 m turn to 0.32 m, where the loader then narrowed the lane)."""
    x, y = noisy_hairpins().T
    smooth = Track.from_arrays(x, y, 1.1, 1.1, smooth_rms_m=NOISE_M)
    assert smooth.min_turn_radius_m() > 0.75 * 1.6 and smooth.narrowing.points == 0
    assert smooth.centerline.curvature_squared_integral() == pytest.approx(
        2.0 * np.pi / 1.6, rel=0.15
    )


def test_a_non_positive_tolerance_is_refused():
    with pytest.raises(TrackError, match="smoothing tolerance must be positive"):
        Track.from_arrays(*noisy_circle(), 1.0, 1.0, smooth_rms_m=0.0)


def test_track_info_compares_the_smoothed_track_and_saves_it(tmp_path: Path):
    path, saved = tmp_path / "noisy.csv", tmp_path / "smoothed.csv"
    write_track_csv(path, *noisy_circle(), HALF_WIDTH_M, HALF_WIDTH_M)
    result = run_cli(
        "track-info", str(path), "--smooth-rms-m", str(NOISE_M), "--save-track", str(saved)
    )
    assert result.returncode == 0, result.stderr
    assert "| as given" in result.stdout and "centre line smoothed: RMS moved [m]" in result.stdout
    assert re.search(r"smoothed lane keeps the given\s*\|\s*-\s*\|\s*widths", result.stdout)
    reloaded = Track.load(saved)
    smooth = Track.load(path, smooth_rms_m=NOISE_M)
    assert reloaded.length_m == pytest.approx(smooth.length_m, rel=1e-4)
    assert reloaded.centerline.curvature_squared_integral() == pytest.approx(
        smooth.centerline.curvature_squared_integral(), rel=0.02
    )


def test_track_info_keeps_the_boundaries_when_asked_and_only_when_smoothing(tmp_path: Path):
    assert SMOOTHING_KEEPS == smoothing.SMOOTHING_KEEPS
    path = tmp_path / "noisy.csv"
    write_track_csv(path, *noisy_circle(), HALF_WIDTH_M, HALF_WIDTH_M)
    kept = run_cli(
        "track-info", str(path), "--smooth-rms-m", str(NOISE_M), "--smooth-keeps", "boundaries"
    )
    assert kept.returncode == 0, kept.stderr
    assert re.search(r"smoothed lane keeps the given\s*\|\s*-\s*\|\s*boundaries", kept.stdout)
    alone = run_cli("track-info", str(path), "--smooth-keeps", "boundaries")
    assert alone.returncode != 0 and "add --smooth-rms-m" in alone.stderr
