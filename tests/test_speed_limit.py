"""The speed barrier's limit: the scaled reference profile, braked for at a gentle rate."""

from __future__ import annotations

import numpy as np
import pytest

from saferace.safety.speed_limit import braking_speed_limit
from saferace.track import Track
from saferace.track.raceline import racing_line


@pytest.mark.parametrize("decel", [1.0, 2.0, 4.0])
def test_limit_is_below_the_scaled_profile_and_brakes_gently(decel: float):
    track = Track.load("technical")
    reference = racing_line(track)
    limit = braking_speed_limit(reference, 1.1, decel)
    s = np.asarray(reference.center_s_m)
    v = limit(s)
    assert np.all(v <= 1.1 * reference.center_vx_mps + 1e-9)
    ahead = np.roll(v, -1)
    gaps = np.diff(np.append(s, s[0] + track.length_m))
    assert np.all(v**2 <= ahead**2 + 2 * decel * gaps + 1e-9)  # never brakes harder than decel
    # Where the profile itself brakes gently, the limit is the profile.
    assert np.mean(np.isclose(v, 1.1 * reference.center_vx_mps)) > 0.3
    # A gentler planned deceleration only lowers the limit.
    assert np.all(braking_speed_limit(reference, 1.1, decel / 2)(s) <= v + 1e-9)


def test_bad_settings_are_refused():
    reference = racing_line(Track.load("oval"))
    with pytest.raises(ValueError, match="positive"):
        braking_speed_limit(reference, 1.1, 0.0)
