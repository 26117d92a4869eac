"""The speed barrier's limit: the scaled reference profile, braked for within a friction ellipse."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.cbf.speed_limit import LaneSpeedLimit, braking_speed_limit
from saferace.track import Track
from saferace.track.raceline import ReferenceLine, racing_line


@pytest.mark.parametrize("decel", [1.0, 2.0, 4.0])
def test_limit_is_below_the_scaled_profile_and_brakes_within_the_ellipse(decel: float):
    track = Track.load("technical")
    reference = racing_line(track)
    lateral = 7.0
    limit = braking_speed_limit(reference, 1.1, decel, lateral)
    s = np.asarray(reference.center_s_m)
    v = limit(s)
    assert np.all(v <= 1.1 * reference.center_vx_mps + 1e-9)
    ahead = np.roll(v, -1)
    gaps = np.diff(np.append(s, s[0] + track.length_m))
    kappa_ahead = np.abs(np.roll(reference.center_kappa_radpm, -1))
    grip_used = np.minimum(1.0, ahead**2 * kappa_ahead / lateral)
    braking = decel * np.sqrt(1.0 - grip_used**2)
    assert np.all(v**2 <= ahead**2 + 2 * braking * gaps + 1e-9)
    # Where the profile itself brakes gently, the limit is the profile.
    assert np.mean(np.isclose(v, 1.1 * reference.center_vx_mps)) > 0.25
    # A gentler planned deceleration, or less grip to brake with, only lowers the limit.
    assert np.all(braking_speed_limit(reference, 1.1, decel / 2, lateral)(s) <= v + 1e-9)
    assert np.all(braking_speed_limit(reference, 1.1, decel, lateral / 2)(s) <= v + 1e-9)


def test_limit_does_not_fall_where_it_turns_with_all_the_lateral_grip():
    """Braking ends before the turn-in: nowhere does the limit fall while it uses all the grip."""
    reference = racing_line(Track.load("oval"))
    lateral = 6.0  # below the limit's own 6.05 m/s^2 in the corners
    s = np.asarray(reference.center_s_m)
    v = braking_speed_limit(reference, 1.1, 2.0, lateral)(s)
    ahead = np.roll(v, -1)
    at_the_grip = ahead**2 * np.abs(np.roll(reference.center_kappa_radpm, -1)) >= lateral
    assert at_the_grip.sum() > 10  # the oval's corners
    assert np.all(v[at_the_grip] <= ahead[at_the_grip] + 1e-9)
    # Without the lateral term the same limit would brake in the corners.
    straight_rule = braking_speed_limit(reference, 1.1, 2.0, 1e9)(s)
    assert np.any(straight_rule[at_the_grip] > np.roll(straight_rule, -1)[at_the_grip] + 1e-3)


def test_bad_settings_are_refused():
    reference = racing_line(Track.load("oval"))
    with pytest.raises(ValueError, match="positive"):
        braking_speed_limit(reference, 1.1, 0.0, 7.0)
    with pytest.raises(ValueError, match="positive"):
        braking_speed_limit(reference, 1.1, 2.0, -1.0)


def rounded_square(radius_m: float = 2.0, side_m: float = 15.0) -> Track:
    """Four straights joined by quarter turns, in a 2.2 m lane like the F1TENTH circuits':
    the racing line cuts each turn, turning several times more gently than the centre."""
    points, position = [], np.zeros(2)
    for heading in np.arange(4) * np.pi / 2:
        direction = np.array([np.cos(heading), np.sin(heading)])
        left = np.array([-direction[1], direction[0]])
        points += [position + d * direction for d in np.arange(0.0, side_m, 0.2)]
        centre = position + side_m * direction + radius_m * left
        angles = np.arange(0.0, np.pi / 2, 0.2 / radius_m)
        points += [centre + radius_m * (np.sin(a) * direction - np.cos(a) * left) for a in angles]
        position = centre + radius_m * direction
    x, y = np.array(points).T
    return Track.from_arrays(x, y, 1.1, 1.1, name="rounded-square")


@pytest.fixture(scope="module")
def cut_turn_limit() -> tuple[Track, ReferenceLine, LaneSpeedLimit]:
    track = rounded_square()
    reference = racing_line(track)
    return track, reference, LaneSpeedLimit(track, reference, 1.1, 2.0, 7.0, 6.05)


def test_on_the_reference_line_the_lane_limit_is_the_reference_limit(cut_turn_limit):
    """A car on its line is not slowed, not even at apexes, where the parallels are tighter."""
    _, reference, limit = cut_turn_limit
    s = np.asarray(reference.center_s_m)[::7]
    on_line = [limit(float(x), float(reference.offset_at(x))) for x in s]
    expected = braking_speed_limit(reference, 1.1, 2.0, 7.0)(s)
    np.testing.assert_allclose(on_line, expected, atol=1e-12)
    # The centre's parallel through an apex is tighter than the line there: without the
    # blend, the car on the line would be held below the reference's limit.
    apex = s[np.abs(reference.offset_at(s)) > 0.25]
    parallel_at_line = [limit.parallel_limit(float(x), float(reference.offset_at(x))) for x in apex]
    assert np.min(parallel_at_line - limit.reference_limit(apex)) < -0.3


def test_riding_the_centre_of_a_turn_the_line_cuts_is_limited_to_the_centre(cut_turn_limit):
    """Far from the line, the car is held to what the lane's own curve allows."""
    track, reference, limit = cut_turn_limit
    s = np.asarray(reference.center_s_m)
    kappa = np.abs(track.centerline.curvature(s))
    far = np.abs(reference.offset_at(s)) > limit.far_m + 0.05
    tightest = s[far][np.argmax(kappa[far])]
    centre_corner_speed = math.sqrt(6.05 / kappa[far].max())
    assert limit(float(tightest), 0.0) <= centre_corner_speed + 1e-6
    assert float(limit.reference_limit(tightest)) > centre_corner_speed + 0.5
    # The limit blends continuously: no step where the blend starts or ends.
    offset = float(reference.offset_at(tightest))
    toward_centre = -np.sign(offset)
    for edge in (limit.near_m, limit.far_m):
        inner, outer = (
            limit(float(tightest), offset + toward_centre * (edge + sign * 1e-6))
            for sign in (-1, 1)
        )
        assert outer == pytest.approx(inner, abs=1e-4)
    assert limit(float(tightest), offset) == float(limit.reference_limit(tightest))


def test_a_plans_stages_get_the_limits_one_lookup_each_gives(cut_turn_limit):
    """``along`` (every stage of a plan at once) is the pointwise limit, on the line, near
    it, in the blend and beyond the lane, over the whole lap and past its end."""
    track, _, limit = cut_turn_limit
    rng = np.random.default_rng(3)
    s = rng.uniform(-5.0, track.length_m + 5.0, 200)
    e_y = rng.uniform(-1.5, 1.5, 200)
    expected = [limit(float(a), float(b)) for a, b in zip(s, e_y, strict=True)]
    assert np.ptp(expected) > 1.0  # the points span slow turns and fast straights
    np.testing.assert_allclose(limit.along(s, e_y), expected, rtol=0, atol=1e-12)


def test_parallel_limits_are_slower_inside_a_turn_and_braked_for(cut_turn_limit):
    track, reference, limit = cut_turn_limit
    s = np.asarray(reference.center_s_m)
    kappa = track.centerline.curvature(s)
    turn = s[np.argmax(np.abs(kappa))]
    inside = math.copysign(0.3, kappa[np.argmax(np.abs(kappa))])
    assert limit.parallel_limit(turn, inside) < limit.parallel_limit(turn, 0.0)
    assert limit.parallel_limit(turn, 0.0) < limit.parallel_limit(turn, -inside)
    # Along each parallel the limit falls no faster than braking at 2 m/s^2 allows.
    gaps = np.diff(np.append(s, s[0] + track.length_m))
    for offset, row in zip(limit.offsets_m, limit.parallel_limits, strict=True):
        v = row(s)
        stretch = np.maximum(1.0 - offset * kappa, 0.05)
        assert np.all(v**2 <= np.roll(v, -1) ** 2 + 2 * 2.0 * stretch * gaps + 1e-9)


def test_the_invariant_limit_is_the_lines_near_it_and_the_lowest_blend_beyond(cut_turn_limit):
    """Within ``near_m`` of the line the invariant limit is the line's; beyond, the lower of
    the line's and the parallel's: never above the blended limit, and below it in the blend
    where the parallel is slower, so that a plan's last stage held to it is not caught by
    the blend's drop a few metres on."""
    track, reference, limit = cut_turn_limit
    rng = np.random.default_rng(7)
    s = rng.uniform(0.0, track.length_m, 300)
    e_y = rng.uniform(-1.1, 1.1, 300)
    pairs = list(zip(s.tolist(), e_y.tolist(), strict=True))
    invariant = np.array([limit.invariant_limit(a, b) for a, b in pairs])
    blended = limit.along(s, e_y)
    assert np.all(invariant <= blended + 1e-12)
    away = np.abs(e_y - reference.offset_at(s))
    near = away <= limit.near_m
    np.testing.assert_allclose(invariant[near], limit.reference_limit(s[near]), atol=1e-12)
    off_line = [pair for pair, close in zip(pairs, near, strict=True) if not close]
    lowest = [min(float(limit.reference_limit(a)), limit.parallel_limit(a, b)) for a, b in off_line]
    np.testing.assert_allclose(invariant[~near], lowest, atol=1e-12)
    in_blend = (away > limit.near_m) & (away < limit.far_m)
    assert np.any(invariant[in_blend] < blended[in_blend] - 0.1)


def test_along_an_offset_the_lower_of_the_lines_and_the_parallels_limit_is_braked_for(
    cut_turn_limit,
):
    """What makes the invariant limit invariant off the line: the minimum of two profiles
    that each fall no faster than braking at 2 m/s^2 allows (the line's per metre of the
    centre line, the parallel's per metre of itself) falls no faster either, where the
    blend at the same offset drops far faster."""
    track, reference, limit = cut_turn_limit
    s = np.asarray(reference.center_s_m)
    kappa = track.centerline.curvature(s)
    gaps = np.diff(np.append(s, s[0] + track.length_m))
    steepest_blend_drop_mps2 = 0.0
    for offset in (-0.8, -0.4, 0.0, 0.4, 0.8):
        parallel = np.array([limit.parallel_limit(float(x), offset) for x in s])
        lowest = np.minimum(limit.reference_limit(s), parallel)
        step_m = np.maximum(1.0, np.maximum(1.0 - offset * kappa, 0.05)) * gaps
        assert np.all(lowest**2 - np.roll(lowest, -1) ** 2 <= 2 * 2.0 * step_m + 1e-9)
        blend = limit.along(s, np.full(len(s), offset))
        drop_mps2 = np.max((blend**2 - np.roll(blend, -1) ** 2) / (2 * step_m))
        steepest_blend_drop_mps2 = max(steepest_blend_drop_mps2, drop_mps2)
    assert steepest_blend_drop_mps2 > 3.0  # the blend alone asks for more than 2 m/s^2


def test_lane_limit_settings_are_checked(cut_turn_limit):
    track, reference, _ = cut_turn_limit
    with pytest.raises(ValueError, match="positive"):
        LaneSpeedLimit(track, reference, 1.1, 2.0, 7.0, 0.0)
    with pytest.raises(ValueError, match="near_m < far_m"):
        LaneSpeedLimit(track, reference, 1.1, 2.0, 7.0, 6.05, near_m=0.6, far_m=0.3)


def test_the_filter_brakes_a_car_riding_the_centre_of_a_cut_turn(tmp_path: Path):
    """The speed barrier reads the car's offset: at the racing line's speed, the same car is
    left alone on the line and braked at the centre, where the turn is tighter. (The backup
    plan is off: it brakes both, for an action that does not steer in a turn.)"""
    track_csv = tmp_path / "rounded_square.csv"
    rounded_square().to_csv(track_csv)
    env = SafetyFilter(
        gym.make("saferace/RacingLine-v0", track=str(track_csv), max_laps=1), backup_plan=False
    )
    reference = env.unwrapped.reference
    s = np.asarray(reference.center_s_m)
    kappa = np.abs(env.unwrapped.track.centerline.curvature(s))
    turn = float(s[np.argmax(kappa * (np.abs(reference.offset_at(s)) > 0.65))])
    observation, info = env.reset(seed=0, options={"start_s_m": turn})
    on_line = env.certify(observation, info, np.array([0.0, 0.0]))
    centred = env.certify(observation, {**info, "e_y_m": 0.0}, np.array([0.0, 0.0]))
    assert on_line.barriers["speed"] > 0.0 > centred.barriers["speed"] + 0.5
    assert centred.filtered_action[1] < on_line.filtered_action[1] - 1.0
    env.close()


def test_a_parallels_limit_is_its_circles_and_braked_for_on_the_straight_before_it(
    tmp_path: Path,
):
    """In the middle of a 1.5 m half circle (left turn), the parallel ``e`` from the centre
    runs on a circle of ``1.5 - e``: its limit is ``sqrt(a (1.5 - e))``, worked out here by
    hand, not by the code that plans with it. On the straight before the turn no parallel
    asks for more than braking at ``decel`` to the middle reaches. (The predictive filter's
    tests check that its plans are held to these limits.)"""
    from saferace.track.track_io import write_track_csv
    from tests.track_shapes import paperclip

    path = tmp_path / "paperclip.csv"
    write_track_csv(path, *paperclip(legs_apart_m=3.0, straight_m=12.0), 0.6, 0.6)
    env = gym.make("saferace/RacingLine-v0", track=str(path))
    base = env.unwrapped
    lateral_mps2, decel_mps2, radius_m = 4.0, 3.0, 1.5
    limit = LaneSpeedLimit(base.track, base.reference, 1.0, decel_mps2, 5.0, lateral_mps2)
    middle_s_m, entry_s_m = 12.0 + 0.5 * math.pi * radius_m, 12.0
    for offset_m in (-0.5, -0.2, 0.0, 0.3, 0.5):
        circle = math.sqrt(lateral_mps2 * (radius_m - offset_m))
        assert limit.parallel_limit(middle_s_m, offset_m) == pytest.approx(circle, rel=1e-3)
        to_middle_m = 2.0 + 0.5 * math.pi * (radius_m - offset_m)  # along the parallel
        reach = math.sqrt(circle**2 + 2.0 * decel_mps2 * to_middle_m)
        assert circle < limit.parallel_limit(entry_s_m - 2.0, offset_m) <= reach, offset_m
    env.close()
