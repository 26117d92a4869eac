"""Racing-line and speed-profile properties on built-in and never-seen tracks."""

from __future__ import annotations

import csv
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from saferace.errors import RacingLineError
from saferace.track import Track, VehicleEnvelope
from saferace.track.raceline import (
    CSV_COLUMNS,
    RacingLineSettings,
    center_line,
    min_curvature_offsets,
    offset_bounds,
    racing_line,
)
from saferace.track.speed_profile import speed_profile


def assert_better_line_inside_lane(track: Track) -> None:
    envelope, settings = VehicleEnvelope(), RacingLineSettings()
    center = center_line(track, envelope)
    racing = racing_line(track, envelope, settings)
    lower, upper = offset_bounds(track, racing.center_s_m, envelope.width_m, settings.margin_m)
    assert np.all(racing.offset_m >= lower - 1e-9)
    assert np.all(racing.offset_m <= upper + 1e-9)
    # The continuous line between samples, projected back onto the centerline.
    projector = track.projector()
    clearance = 0.5 * envelope.width_m
    for x, y in racing.path.position(np.linspace(0, racing.length_m, 3000, endpoint=False)):
        s, e_y = projector.project(x, y)
        w_right, w_left = track.widths(s)
        assert -w_right + clearance - 1e-3 <= e_y <= w_left - clearance + 1e-3
    assert racing.curvature_squared_integral < center.curvature_squared_integral
    assert racing.lap_time_s < center.lap_time_s


def test_racing_line_beats_center_line_on_builtin_tracks(builtin_track: Track):
    assert_better_line_inside_lane(builtin_track)


def test_racing_line_beats_center_line_on_unseen_tracks(unseen_track_csv: Path):
    assert_better_line_inside_lane(Track.load(unseen_track_csv))


def test_the_racing_line_says_why_it_stopped(caplog):
    track = Track.load("technical")
    with caplog.at_level(logging.WARNING, logger="saferace.track.raceline"):
        converged = min_curvature_offsets(track, track.centerline.sample(0.1), 0.3,
                                          RacingLineSettings())  # fmt: skip
    assert not caplog.records
    capped = RacingLineSettings(max_iterations=1)
    with caplog.at_level(logging.WARNING, logger="saferace.track.raceline"):
        first = min_curvature_offsets(track, track.centerline.sample(0.1), 0.3, capped)
    (warning,) = caplog.records
    moved = float(np.max(np.abs(first)))  # the first step, from the centre line
    assert "not converged after 1 iterations: offsets still move by" in warning.message
    assert f"{moved:.2e} m" in warning.message
    assert np.max(np.abs(converged - first)) > 1e-3  # capping it did change the line


def test_oval_racing_line_is_symmetric():
    track = Track.load("oval")
    racing = racing_line(track)
    points = racing.path.position(racing.s_m)
    dense = racing.path.position(np.linspace(0, racing.length_m, 20000, endpoint=False))
    for mirror in (np.array([-1.0, 1.0]), np.array([1.0, -1.0])):
        mirrored = points * mirror
        gaps = np.min(np.linalg.norm(dense[None, :, :] - mirrored[::7, None, :], axis=2), axis=1)
        assert gaps.max() < 5e-3
    # It hugs the inside of the semicircles and the outside of the straights.
    w_right, w_left = track.widths(racing.center_s_m)
    clearance = 0.5 * VehicleEnvelope().width_m + RacingLineSettings().margin_m
    assert racing.offset_m.max() == pytest.approx(w_left.max() - clearance, abs=1e-3)
    assert racing.offset_m.min() == pytest.approx(-w_right.max() + clearance, abs=1e-3)


def test_lane_too_narrow_for_margin_is_an_error():
    with pytest.raises(RacingLineError, match="narrower than the car plus margins"):
        racing_line(Track.load("lab"), settings=RacingLineSettings(margin_m=0.3))


def test_speed_profile_on_a_circle_is_the_lateral_limit():
    envelope = VehicleEnvelope(a_lat_max_mps2=4.0, v_max_mps=10.0)
    profile = speed_profile(np.full(200, 0.25), 0.1, envelope)
    np.testing.assert_allclose(profile.vx_mps, 4.0, rtol=1e-12)
    np.testing.assert_allclose(profile.ax_mps2, 0.0, atol=1e-9)
    assert profile.lap_time_s == pytest.approx(200 * 0.1 / 4.0)


def test_speed_profile_respects_friction_ellipse_and_top_speed(builtin_track: Track):
    envelope = VehicleEnvelope()
    center = center_line(builtin_track, envelope)
    v, a_x = center.vx_mps, center.ax_mps2
    a_y_start = v**2 * np.abs(center.kappa_radpm)
    drive = np.array([envelope.drive_accel_mps2(speed) for speed in v])
    a_long_max = np.where(a_x > 0, drive, envelope.a_brake_max_mps2)
    assert np.all(a_x <= drive + 1e-9)  # speeding up only as fast as the motor can
    for a_y in (a_y_start, np.roll(a_y_start, -1)):  # both ends of every segment
        usage = (a_x / a_long_max) ** 2 + (a_y / envelope.a_lat_max_mps2) ** 2
        assert usage.max() < 1.0 + 1e-9
    assert v.max() <= envelope.v_max_mps + 1e-12
    ds = center.length_m / len(center.s_m)
    assert center.lap_time_s == pytest.approx(np.sum(ds / v), rel=0.01)


def test_cli_writes_racing_line_csv_and_plot(tmp_path: Path):
    out, plot = tmp_path / "line.csv", tmp_path / "line.png"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "saferace",
            "raceline",
            "oval",
            "--out",
            str(out),
            "--plot",
            str(plot),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "| racing |" in result.stdout and "| center |" in result.stdout
    assert plot.stat().st_size > 10_000
    with open(out) as handle:
        rows = list(csv.reader(handle))
    assert tuple(rows[0]) == CSV_COLUMNS
    data = np.array(rows[1:], dtype=float)
    s, x, y, psi = data[:, 0], data[:, 1], data[:, 2], data[:, 3]
    assert np.all(np.diff(s) > 0)
    heading = np.arctan2(np.diff(y), np.diff(x))
    assert np.max(np.abs(np.angle(np.exp(1j * (heading - psi[:-1]))))) < 0.05
    assert np.all(data[:, 5] > 0)


def test_drafting_at_a_loose_tolerance_ends_on_the_tight_line():
    track = Track.load("technical")
    s = track.centerline.sample(0.1)
    drafted = min_curvature_offsets(track, s, 0.3, RacingLineSettings())
    tight = min_curvature_offsets(track, s, 0.3, RacingLineSettings(draft_tolerance=None))
    assert np.max(np.abs(drafted - tight)) < 2e-3
