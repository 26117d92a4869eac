"""The generic perception model calibrated on the user's own track: the quantiles and the
held-out report worked by hand, the cache by the track's fingerprint, and the option that
feeds it to a filter."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.errors import ConfigError
from saferace.eval.filter_config import FilterConfig
from saferace.eval.filters import apply_filter
from saferace.learning import track_calibration as calibration_module
from saferace.learning.perception import RECIPES
from saferace.learning.track_calibration import (
    calibration_file,
    calibration_from_drives,
    track_calibration,
)
from saferace.safety.uncertainty.conformal import ConformalCalibration
from saferace.safety.uncertainty.feature_monitor import FeatureMonitor
from saferace.track import Track
from saferace.track.random_track import write_random_track

#: A monitor on one feature whose score is the feature squared.
SQUARE = FeatureMonitor((0.0,), ((1.0,),), (1.0,), 1.0, threshold=4.0, alpha=0.1)


def drive(errors: np.ndarray, features: np.ndarray) -> dict[str, np.ndarray]:
    """Frames whose normalised score is ``errors`` (spread 1, the error on e_y)."""
    truth = np.zeros((len(errors), 2))
    return {
        "mean": truth + np.column_stack([errors, np.zeros(len(errors))]),
        "std": np.ones((len(errors), 2)),
        "truth": truth,
        "features": np.asarray(features, float)[:, None],
    }


def test_the_own_calibration_and_its_held_out_report_are_the_conformal_quantiles():
    """Even drives score 0.1 .. 4.0 (step 0.1), odd ones 1.05 .. 4.95; at alpha 0.1 the
    even drives' quantile is the ceil(41 * 0.9) = 37th score, 3.7, and all 80 scores' the
    73rd, 4.25 (10 even ones below 1.05, 60 of both up to 4.0, then 4.05, 4.15, 4.25).
    Held out (odd drives): 10 of 40 within the pooled scale 2.0, 27 within 3.7. The monitor
    scores the feature squared: even drives 1, odd ones 9 (10 frames) and 2.25 (30)."""
    even = np.arange(1, 41) / 10.0
    odd = even - 0.05 + 1.0
    drives = {
        0: drive(even[:20], np.ones(20)),
        1: drive(odd[:20], [3.0] * 10 + [1.5] * 10),
        2: drive(even[20:], np.ones(20)),
        3: drive(odd[20:], np.full(20, 1.5)),
    }
    pooled = ConformalCalibration(0.1, 2.0, 500, SQUARE)
    own, report = calibration_from_drives(pooled, drives)
    assert own.scale == pytest.approx(4.25)
    assert own.frames == 80 and own.alpha == 0.1
    assert isinstance(own.monitor, FeatureMonitor)
    assert own.monitor.threshold == pytest.approx(9.0)  # the 73rd of 40 x 1, 30 x 2.25, 10 x 9
    assert own.monitor.mean == SQUARE.mean  # the model's Gaussian, a new threshold
    assert report["held_out_frames"] == 40
    assert report["pooled"]["coverage"] == pytest.approx(10 / 40)
    assert report["own"]["coverage"] == pytest.approx(27 / 40)
    assert report["pooled"]["alarm_rate"] == pytest.approx(10 / 40)  # 9 > 4
    assert report["own"]["alarm_rate"] == pytest.approx(1.0)  # the even drives' threshold 1


def test_a_track_s_calibration_is_made_once_and_kept_by_its_fingerprint(
    quick_perception: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """Made on the first call; the next call on the same lane (loaded again) and the filter
    of ``--own-track-calibration`` take it from the cache; another lane, or other drives,
    make one anew."""
    monkeypatch.setattr(calibration_module, "DRIVES", 2)
    monkeypatch.setattr(calibration_module, "SECONDS_PER_DRIVE", 4.0)
    recipe = RECIPES["quick"]
    track = Track.load("lab")
    own, report = track_calibration(recipe, track, progress=False)
    assert calibration_file(recipe, track).exists()
    assert report["frames"] > 100 and 0.0 <= report["own"]["coverage"] <= 1.0
    assert np.isfinite(own.scale) and own.scale > 0.0

    def no_driving(*args, **kwargs):
        raise AssertionError("a cached calibration drove again")

    monkeypatch.setattr(calibration_module, "fit_track_calibration", no_driving)
    again, _ = track_calibration(recipe, Track.load("lab"), progress=False)
    assert again == own
    env = apply_filter(
        gym.make("saferace/CenterLine-v0", track="lab"),
        FilterConfig(kind="cbf", state_source="generic:quick", own_track_calibration=True),
        seed=0,
    )
    try:
        assert env.state_source.calibration == own
    finally:
        env.close()
    other = Track.load(str(write_random_track(tmp_path / "other.csv", 5, lane_width_m=1.5)))
    assert calibration_file(recipe, other) != calibration_file(recipe, track)
    with pytest.raises(AssertionError, match="drove again"):
        track_calibration(recipe, other, progress=False)
    with pytest.raises(AssertionError, match="drove again"):
        track_calibration(recipe, track, progress=False, drives=3)


def test_a_calibration_is_kept_by_the_lane_not_by_its_name(tmp_path: Path):
    """Two files of one name with other lanes are two calibrations; one lane loaded from
    two files of other names is one."""
    recipe = RECIPES["quick"]
    one = write_random_track(tmp_path / "a" / "mine.csv", 5, lane_width_m=1.5)
    wider = write_random_track(tmp_path / "b" / "mine.csv", 5, lane_width_m=2.0)
    copy = tmp_path / "copy.csv"
    copy.write_bytes(one.read_bytes())
    assert Track.load(str(one)).name == Track.load(str(wider)).name
    first = calibration_file(recipe, Track.load(str(one)))
    assert first != calibration_file(recipe, Track.load(str(wider)))
    assert first == calibration_file(recipe, Track.load(str(copy)))


def test_own_track_calibration_is_the_generic_model_s_only():
    with pytest.raises(ConfigError, match="use it with --state-source generic"):
        FilterConfig(kind="cbf", own_track_calibration=True)
    with pytest.raises(ConfigError, match="use it with --state-source generic"):
        FilterConfig(kind="cbf", state_source="learned:x.pt", own_track_calibration=True)
    assert FilterConfig(kind="cbf", state_source="generic:quick", own_track_calibration=True)
