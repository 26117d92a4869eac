"""Track geometry against analytic cases: circle and ellipse, Frenet round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ellipe

from saferace.track import ClosedPath, Track
from saferace.track.frenet import wrap_arc


def circle_track(radius_m: float = 5.0, count: int = 60, clockwise: bool = False) -> Track:
    theta = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    if clockwise:
        theta = -theta
    return Track.from_arrays(radius_m * np.cos(theta), radius_m * np.sin(theta), 0.5, 0.5)


def test_circle_length_curvature_heading():
    track = circle_track(radius_m=5.0)
    assert track.length_m == pytest.approx(2.0 * np.pi * 5.0, rel=1e-5)
    s = track.centerline.sample(0.05)
    np.testing.assert_allclose(track.centerline.curvature(s), 0.2, rtol=2e-3)
    np.testing.assert_allclose(
        np.cos(track.centerline.heading(s) - (s / 5.0 + np.pi / 2)), 1.0, atol=1e-6
    )


def test_clockwise_circle_turns_right():
    track = circle_track(clockwise=True)
    s = track.centerline.sample(0.5)
    np.testing.assert_allclose(track.centerline.curvature(s), -0.2, rtol=2e-3)


@pytest.mark.parametrize("angle", [0.1, 1.3, 2.9, 4.4, 6.0])
@pytest.mark.parametrize("radius_point", [4.6, 5.0, 5.45])
def test_circle_projection_is_analytic(angle: float, radius_point: float):
    track = circle_track(radius_m=5.0)
    projector = track.projector()
    yaw = angle + np.pi / 2 + 0.2
    s, e_y, e_psi = projector.to_frenet(
        radius_point * math.cos(angle), radius_point * math.sin(angle), yaw
    )
    assert s == pytest.approx(5.0 * angle, abs=1e-4)
    assert e_y == pytest.approx(5.0 - radius_point, abs=1e-5)  # left of a CCW circle is inside
    assert e_psi == pytest.approx(0.2, abs=1e-4)


def test_ellipse_arc_length_and_vertex_curvature():
    a, b = 6.0, 3.5
    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    path = ClosedPath(np.column_stack([a * np.cos(t), b * np.sin(t)]))
    exact_length = 4.0 * a * ellipe(1.0 - b**2 / a**2)
    assert path.length_m == pytest.approx(exact_length, rel=1e-6)
    assert path.curvature(0.0) == pytest.approx(a / b**2, rel=1e-3)  # at (a, 0)
    quarter = path.length_m / 4.0
    assert path.curvature(quarter) == pytest.approx(b / a**2, rel=1e-3)  # at (0, b)
    np.testing.assert_allclose(path.position(quarter), [0.0, b], atol=1e-6)


def test_ellipse_projection_matches_brute_force():
    a, b = 6.0, 3.5
    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False)
    track = Track.from_arrays(a * np.cos(t), b * np.sin(t), 0.6, 0.6)
    rng = np.random.default_rng(0)
    dense_s = np.linspace(0.0, track.length_m, 400_000, endpoint=False)
    dense_xy = track.centerline.position(dense_s)
    projector = track.projector()
    for _ in range(20):
        s0 = rng.uniform(0, track.length_m)
        point = track.centerline.position(s0) + rng.uniform(-0.55, 0.55) * track.centerline.normal(
            s0
        )
        projector.reset()
        s, e_y = projector.project(*point)
        distances = np.linalg.norm(dense_xy - point, axis=1)
        nearest = int(np.argmin(distances))
        assert abs(e_y) == pytest.approx(distances[nearest], abs=1e-6)
        assert s == pytest.approx(dense_s[nearest], abs=2e-4)


def test_round_trip_under_a_millimetre_everywhere_in_the_lane(builtin_track: Track):
    rng = np.random.default_rng(1)
    projector = builtin_track.projector()
    s_values = np.sort(rng.uniform(0, builtin_track.length_m, 300))
    w_right, w_left = builtin_track.widths(s_values)
    e_y_values = rng.uniform(-w_right, w_left)
    e_psi_values = rng.uniform(-1.0, 1.0, len(s_values))
    for s, e_y, e_psi in zip(s_values, e_y_values, e_psi_values, strict=True):
        x, y, yaw = projector.from_frenet(s, e_y, e_psi)
        s2, e_y2, e_psi2 = projector.to_frenet(x, y, yaw)
        x2, y2, _ = projector.from_frenet(s2, e_y2, e_psi2)
        assert math.hypot(x2 - x, y2 - y) < 1e-3
        assert abs(wrap_arc(s2 - s, builtin_track.length_m)) < 1e-3
        assert e_y2 == pytest.approx(e_y, abs=1e-3)
        assert e_psi2 == pytest.approx(e_psi, abs=1e-6)


def test_local_search_agrees_with_global_scan_while_driving(builtin_track: Track):
    """A car moving 0.35 m per step (7 m/s at 20 Hz) weaving inside the lane."""
    local = builtin_track.projector()
    s_path = np.arange(0.0, 2 * builtin_track.length_m, 0.35)
    w_right, w_left = builtin_track.widths(s_path)
    e_y_path = 0.8 * np.sin(s_path / 3.0) * np.where(np.sin(s_path / 3.0) > 0, w_left, w_right)
    points = builtin_track.centerline.position(s_path) + e_y_path[
        :, None
    ] * builtin_track.centerline.normal(s_path)
    for point, e_y in zip(points, e_y_path, strict=True):
        global_projector = builtin_track.projector()
        s_local, e_y_local = local.project(*point)
        s_global, e_y_global = global_projector.project(*point)
        assert e_y_local == pytest.approx(e_y, abs=1e-6)
        assert e_y_global == pytest.approx(e_y_local, abs=1e-9)
        assert s_global == pytest.approx(s_local, abs=1e-6)


def test_projector_recovers_after_a_teleport():
    track = circle_track()
    projector = track.projector()
    projector.project(5.0, 0.0)
    s, e_y = projector.project(-5.2, 0.0)  # the opposite side of the circle
    assert s == pytest.approx(np.pi * 5.0, abs=1e-4)
    assert e_y == pytest.approx(-0.2, abs=1e-6)


def test_widths_follow_the_file_between_points(unseen_track_csv):
    track = Track.load(unseen_track_csv)
    data = np.loadtxt(unseen_track_csv, delimiter=",")
    right, left = track.widths(track.centerline.point_s_m)
    np.testing.assert_allclose(right, data[:, 2], atol=1e-9)
    np.testing.assert_allclose(left, data[:, 3], atol=1e-9)
