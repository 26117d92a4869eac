"""The speed barrier's limit: the scaled reference profile, braked for within a friction ellipse."""

from __future__ import annotations

import numpy as np
import pytest

from saferace.safety.speed_limit import braking_speed_limit
from saferace.track import Track
from saferace.track.raceline import racing_line


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
