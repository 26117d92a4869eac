"""The generic perception model: calibrated by track, cached with a manifest, resumable, and
named as a state source by every command."""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.cache import CACHE_VARIABLE
from saferace.errors import SafeRaceError
from saferace.eval.agents import RECKLESS_AGENT_NAMES, make_agent
from saferace.eval.filter_config import FilterConfig
from saferace.eval.filters import apply_filter
from saferace.eval.runner import make_task_env, run_episode
from saferace.experiments.safety_table import RECKLESS_TASKS, filter_label, run_table
from saferace.learning import perception
from saferace.learning.agent import (
    check_generic_image_shape,
    learned_agent,
    learned_state_source,
)
from saferace.learning.checkpoint import CONFORMAL_KEY, load_checkpoint
from saferace.learning.configs import DaggerConfig
from saferace.learning.perception import (
    MANIFEST_FILE,
    RECIPES,
    build_perception_model,
    collect_all,
    ensure_perception_model,
    generic_state_source,
    model_folder,
    recipe_named,
    round_dirs_of,
    rounds_folder,
    sha256,
    targets_of,
    track_size,
    write_tracks,
)
from saferace.learning.rounds import load_rounds
from saferace.learning.training_data import network_data
from saferace.learning.validation import predict_frames
from saferace.names import TASKS
from saferace.safety.cbf.filter import SafetyFilter
from saferace.safety.uncertainty.conformal import (
    ConformalCalibration,
    conformal_quantile,
    group_calibration,
)
from saferace.safety.uncertainty.feature_monitor import feature_monitor
from saferace.safety.uncertainty.intervals import ConformalStateSource
from saferace.safety.uncertainty.lane_middle import (
    LaneMiddleStateSource,
    centre_line_offset_m,
    lane_middle_offset_m,
    lane_middle_state,
)
from saferace.track import Track
from saferace.track.random_track import write_random_track
from tests.cli_helpers import run_cli

#: The quick recipe: a build takes about half a minute.
TINY = RECIPES["quick"]


@pytest.fixture
def built(quick_perception: Path) -> Path:
    """The session's quick model (``conftest.quick_perception``), rebuilt where a test
    took it apart."""
    return build_perception_model(TINY, progress=False)


def by_rank(scores: np.ndarray, level: float) -> float:
    """The ``ceil((n + 1) level)``-th smallest of ``n`` scores, by sorting."""
    return float(np.sort(scores)[int(np.ceil((len(scores) + 1) * level)) - 1])


def test_a_calibration_by_track_covers_the_hard_track_that_pooling_leaves_out():
    rng = np.random.default_rng(0)
    easy, hard = 1800, 200
    truth = np.zeros((easy + hard, 2))
    sigma = np.ones_like(truth)
    mean = np.concatenate([rng.normal(0, 1, (easy, 2)), rng.normal(0, 3, (hard, 2))])
    groups = np.array(["easy"] * easy + ["hard"] * hard)
    scores = np.abs(mean).max(axis=1)
    pooled = conformal_quantile(scores, 0.05)
    assert np.mean(scores[groups == "hard"] <= pooled) < 0.85  # pooling fails the hard track
    calibration, rows = group_calibration(mean, sigma, truth, groups, 0.05)
    by_group = {row["group"]: row for row in rows}
    # worked apart from the code: the ceil((n + 1) 0.95)-th smallest score of each track
    own = {name: by_rank(scores[groups == name], 0.95) for name in ("easy", "hard")}
    assert by_group["easy"]["own scale"] == own["easy"]
    assert by_group["hard"]["own scale"] == own["hard"] > 2 * own["easy"]
    assert calibration.scale == own["hard"]  # the largest track's, not the pooled one
    assert min(row["coverage"] for row in rows) >= 0.95
    assert calibration.frames == easy + hard


def test_the_monitor_threshold_by_track_is_the_largest_of_the_tracks():
    rng = np.random.default_rng(1)
    reference = rng.normal(0, 1, (500, 8))
    features = np.concatenate([rng.normal(0, 1, (300, 8)), rng.normal(0.8, 1, (300, 8))])
    groups = np.repeat(["near", "far"], 300)
    monitor = feature_monitor(reference, 0.05)
    truth = np.zeros((600, 2))
    calibration, rows = group_calibration(
        truth, np.ones_like(truth), truth, groups, 0.05, monitor, features
    )
    assert calibration.monitor is not None
    scores = monitor.scores(features)
    own = [by_rank(scores[groups == name], 0.95) for name in ("near", "far")]
    assert [row["own threshold"] for row in rows] == own
    assert calibration.monitor.threshold == max(own)
    assert all(row["alarm rate"] <= 0.05 for row in rows)
    assert rows[0]["own threshold"] < rows[1]["own threshold"]  # the far track sets it


def test_a_calibration_by_track_refuses_one_track_and_a_monitor_without_features():
    truth = np.zeros((40, 2))
    with pytest.raises(SafeRaceError, match="at least 2 groups"):
        group_calibration(truth, np.ones_like(truth), truth, np.zeros(40), 0.05)
    monitor = feature_monitor(np.random.default_rng(0).normal(size=(50, 4)), 0.05)
    with pytest.raises(SafeRaceError, match="features"):
        group_calibration(truth, np.ones_like(truth), truth, np.arange(40) % 2, 0.05, monitor)


def test_the_build_writes_a_manifest_of_its_recipe_seeds_commit_and_hashes(built: Path):
    folder = model_folder(TINY)
    manifest = json.loads((folder / MANIFEST_FILE).read_text())
    assert manifest["recipe"]["train_track_seeds"] == list(TINY.train_track_seeds)
    assert manifest["track_seeds"]["calibration"] == list(TINY.calibration_track_seeds)
    assert set(manifest["seconds"]) == {"collect", "train", "calibrate"}
    assert manifest["git_revision"] and manifest["packages"]["torch"]
    assert manifest["files"]["model.pt"] == sha256(built)
    assert any(name.endswith("frames.npz") for name in manifest["files"])
    for name, digest in manifest["files"].items():
        assert sha256(folder / name) == digest, name
    rows = manifest["calibration_by_track"]
    assert [row["group"] for row in rows] == [
        f"calibration_{s}" for s in TINY.calibration_track_seeds
    ]
    assert all(row["coverage"] >= 0.95 and row["alarm rate"] <= 0.05 for row in rows)


def test_the_model_perceives_only_and_its_calibration_is_by_track(built: Path):
    loaded = load_checkpoint(built)
    assert loaded.control is None
    assert loaded.state.config.log_variance and loaded.state.config.subnetworks == 1
    record = loaded.metadata[CONFORMAL_KEY]
    assert record["scale"] == max(row["own scale"] for row in record["groups"])
    env = gym.make("saferace/CenterLine-v0", track="lab")
    try:
        with pytest.raises(SafeRaceError, match="perception model"):
            learned_agent(env, built)
    finally:
        env.close()


def test_the_lane_middle_lies_left_of_the_centre_line_where_the_lane_is_wider_on_the_left():
    assert lane_middle_offset_m(0.6, 0.4) == pytest.approx(0.1)
    assert lane_middle_offset_m(np.array([0.4, 0.5]), np.array([0.6, 0.5])) == pytest.approx(
        [-0.1, 0.0]
    )


def test_an_offset_in_half_widths_is_the_same_on_a_lane_of_any_width():
    """Left half width 1.2 m, right 0.8 m: the middle lies 0.2 m left of the centre line and
    the half width is 1.0 m, so a car 0.5 m left of the centre line is 0.3 m, or 0.3 half
    widths, left of the middle; on the same lane twice as wide, a car at the same place
    relative to the edges (1.0 m) is at the same 0.3 half widths."""
    assert lane_middle_state(0.5, 1.2, 0.8) == pytest.approx(0.3)
    assert lane_middle_state(0.5, 1.2, 0.8, per_half_width=True) == pytest.approx(0.3)
    assert lane_middle_state(1.0, 2.4, 1.6, per_half_width=True) == pytest.approx(0.3)
    assert lane_middle_state(0.5, 0.6, 0.4, per_half_width=True) == pytest.approx(0.8)
    for e_y, left, right in [(0.5, 1.2, 0.8), (-0.3, 0.35, 0.45), (1.0, 2.4, 1.6)]:
        for fraction in (False, True):
            there = lane_middle_state(e_y, left, right, per_half_width=fraction)
            assert centre_line_offset_m(there, left, right, fraction) == pytest.approx(e_y)


def test_the_default_recipe_trains_on_lanes_from_the_narrowest_to_a_circuit_s():
    """Lane widths drawn log-uniformly in 0.7-2.5 m (lab's 0.8 m and the F1TENTH circuits'
    2.2 m inside, both ends reached by the 48 training tracks), sizes in 2.5-40 m."""
    recipe = RECIPES["default"]
    sizes = [track_size(recipe, seed) for seed in recipe.train_track_seeds]
    widths = np.array([width for _, width in sizes])
    assert recipe.lane_width_range_m == (0.7, 2.5)
    assert widths.min() >= 0.7 and widths.max() <= 2.5
    assert widths.min() < 0.8 and widths.max() > 2.2
    assert np.median(widths) == pytest.approx(np.sqrt(0.7 * 2.5), rel=0.25)  # log-uniform
    radii = np.array([radius for radius, _ in sizes])
    assert radii.min() >= 2.5 and radii.max() <= 40.0
    assert radii.min() < 4.0 and radii.max() > 25.0  # hairpins and a circuit's bends
    assert np.median(radii) == pytest.approx(np.sqrt(2.5 * 40.0), rel=0.35)  # log-uniform
    assert track_size(recipe, 90001) != track_size(recipe, 90002)
    assert track_size(recipe, 90001) == track_size(recipe, 90001)


def test_the_default_recipe_drives_every_driver_the_filter_judges_in_both_lane_tasks():
    """The expert and every reckless driver (those the safety table puts behind the generic
    model) in both lane tasks: a driver left out is a way of leaving the lane, and a task
    left out a line, that the model never saw."""
    recipe = RECIPES["default"]
    assert sorted(recipe.drivers) == sorted(("expert", *RECKLESS_AGENT_NAMES))
    assert sorted(recipe.tasks) == sorted(TASKS)


def test_the_model_is_built_for_the_generic_source_only_and_only_once(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
):
    monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path))
    builds: list[str] = []
    monkeypatch.setattr(
        perception, "build_perception_model", lambda recipe, workers: builds.append(recipe.name)
    )
    for source in (None, "oracle", "learned"):
        ensure_perception_model(source)
    assert builds == []
    ensure_perception_model("generic:quick")
    assert builds == ["quick"]
    model_folder(TINY).mkdir(parents=True)
    (model_folder(TINY) / MANIFEST_FILE).write_text("{}")
    ensure_perception_model("generic:quick")
    assert builds == ["quick"]


def test_a_random_track_is_scaled_to_the_lane_width_asked_for(tmp_path: Path):
    plain = np.loadtxt(write_random_track(tmp_path / "a.csv", 7), delimiter=",", skiprows=1)
    wide = np.loadtxt(
        write_random_track(tmp_path / "b.csv", 7, lane_width_m=2.2), delimiter=",", skiprows=1
    )
    assert np.array_equal(plain[:, :2], wide[:, :2])  # the same centre line
    assert np.mean(wide[:, 2] + wide[:, 3]) == pytest.approx(2.2, abs=1e-5)  # 6 decimals
    scale = 2.2 / np.mean(plain[:, 2] + plain[:, 3])
    assert wide[:, 2:] == pytest.approx(scale * plain[:, 2:], abs=1e-5)
    with pytest.raises(ValueError, match="lane_width_m"):
        write_random_track(tmp_path / "c.csv", 7, lane_width_m=0.0)


class _Replay:
    """A state source that returns given rows one by one, with features."""

    def __init__(self, rows: np.ndarray) -> None:
        self.rows, self.index, self.last_features = rows, 0, np.ones(4)

    def reset(self, seed: int | None = None) -> None:
        self.index = 0

    def samples(self, observation: dict, info: dict) -> np.ndarray:
        self.index += 1
        return self.rows[self.index - 1][None]


def test_the_model_learns_the_offset_from_the_lane_middle_and_the_map_moves_it_back(
    built: Path,
):
    """The targets are the true offsets less where the lane's middle lies by the track's
    widths at each frame (the random tracks' lanes are lopsided by centimetres), in half
    widths of the lane there, and the source moves them back by the widths the env
    reports: the truth again, exactly."""
    track_path = model_folder(TINY) / "tracks" / "train_90001.csv"
    frames = load_rounds([rounds_folder(TINY, track_path)])
    targets = targets_of(TINY, frames)["state"]
    w_right, w_left = Track.load(str(track_path)).widths(frames["s_m"])
    half_width = 0.5 * (w_left + w_right)
    moved = frames["state"][:, 0] - targets[:, 0] * half_width
    assert moved == pytest.approx(0.5 * (w_left - w_right), abs=1e-6)
    assert np.abs(moved).max() > 0.01
    assert np.array_equal(targets[:, 1:], frames["state"][:, 1:])
    in_metres = targets_of(replace(TINY, lane_fraction=False), frames)["state"]
    assert in_metres[:, 0] == pytest.approx(targets[:, 0] * half_width, abs=1e-6)
    assert targets_of(replace(TINY, lane_middle=False), frames) is frames
    source = LaneMiddleStateSource(_Replay(targets.astype(float)), per_half_width=True)
    back = np.array(
        [
            source.samples({}, {"w_left_m": left, "w_right_m": right})[0]
            for left, right in zip(w_left, w_right, strict=True)
        ]
    )
    assert back == pytest.approx(frames["state"], abs=1e-5)
    assert source.last_features is not None
    with pytest.raises(SafeRaceError, match="name it --state-source generic:quick"):
        learned_state_source(built, (64, 64, 3))
    env = apply_filter(
        gym.make("saferace/CenterLine-v0", track="lab"),
        FilterConfig(kind="cbf", state_source="generic:quick"),
        seed=0,
    )
    try:
        assert isinstance(env.state_source, ConformalStateSource)
        assert isinstance(env.state_source.source, LaneMiddleStateSource)
    finally:
        env.close()


def test_a_second_build_reuses_the_model_and_an_interrupted_one_resumes(built: Path):
    folder = model_folder(TINY)
    rounds = sorted(folder.glob("rounds/*/round_*/frames.npz"))
    stamps = {path: path.stat().st_mtime_ns for path in [*rounds, built, folder / MANIFEST_FILE]}
    assert build_perception_model(TINY, progress=False) == built
    assert all(path.stat().st_mtime_ns == stamp for path, stamp in stamps.items())
    trained = folder / "state_uncalibrated.pt"
    trained_stamp = trained.stat().st_mtime_ns
    built.unlink()
    (folder / MANIFEST_FILE).unlink()
    build_perception_model(TINY, progress=False)  # calibrates again, nothing else
    assert trained.stat().st_mtime_ns == trained_stamp
    assert all(path.stat().st_mtime_ns == stamps[path] for path in rounds)
    assert load_checkpoint(built).metadata[CONFORMAL_KEY]["groups"]


def test_a_build_refuses_a_folder_of_another_recipe(built: Path):
    with pytest.raises(SafeRaceError, match="another 'quick' recipe"):
        build_perception_model(replace(TINY, epochs=3), progress=False)


def test_generic_names_the_built_model_as_a_calibrated_state_source(built: Path):
    env = apply_filter(
        gym.make("saferace/CenterLine-v0", track="lab"),
        FilterConfig(kind="cbf", state_source="generic:quick"),
        seed=0,
    )
    try:
        source = env.state_source
        assert isinstance(source, ConformalStateSource)
        assert env.robust
        env.reset(seed=0)
        _, _, _, _, info = env.step(np.zeros(2))
        safety = info["safety"]
        assert safety["mode"] in ("certified", "propagated", "stopping")
        assert np.all(np.asarray(safety["state_upper"]) >= np.asarray(safety["state_lower"]))
    finally:
        env.close()


def test_an_unbuilt_or_unknown_recipe_says_what_to_run(quick_perception: Path):
    with pytest.raises(SafeRaceError, match="saferace perception --recipe default"):
        generic_state_source("", (64, 64, 3))
    with pytest.raises(SafeRaceError, match="no perception recipe 'nope'"):
        recipe_named("generic:nope")


def test_every_command_with_a_filter_takes_the_generic_model_by_name():
    from saferace.cli import build_parser
    from saferace.cli.experiments import dagger_config
    from saferace.cli.safety import robustness_config

    parser = build_parser()
    generic = ("--filter", "cbf", "--state-source", "generic")
    dagger = dagger_config(parser.parse_args(["dagger", *generic, "--out", "x"]))
    assert dagger.filter.state_source == "generic" and dagger.filter.uncertainty == "robust"
    assert dagger.training.state_uncertainty == "mc-dropout"  # its own network feeds nothing
    assert dagger.trained_networks == ("control",)
    own = DaggerConfig(filter=FilterConfig(kind="cbf", state_source="learned"))
    assert own.training.state_uncertainty == "ensemble"
    with pytest.raises(SafeRaceError, match="own state network"):
        DaggerConfig(filter=FilterConfig(kind="cbf", state_source="generic"), calibrate_spread=True)
    robust = robustness_config(parser.parse_args(["robustness", *generic, "--out", "x"]))
    assert robust.safety.state_source == "generic" and robust.safety.uncertainty == "robust"
    table = parser.parse_args(["safety-table", "--state-source", "generic:quick"])
    assert table.state_source == "generic:quick"
    assert DaggerConfig().filter.state_source == "generic"  # the default
    assert parser.parse_args(["safety-table"]).state_source == "generic"


def test_the_command_line_refuses_an_unknown_recipe():
    done = run_cli("drive", "--filter", "cbf", "--state-source", "generic:nope", "--track", "lab")
    assert done.returncode != 0
    assert "no perception recipe 'nope'" in done.stderr


@pytest.mark.slow  # 15-30 s (the table's perceived rows: tests/test_safety_table.py)
def test_the_safety_table_runs_the_reckless_agents_behind_the_generic_model(
    quick_perception: Path, tmp_path: Path
):
    rows = run_table(
        ["lab"], tmp_path, laps=1, max_seconds=3.0, progress=False, state_source="generic:quick"
    )
    generic = [row for row in rows if row["filter"].get("state_source") == "generic:quick"]
    assert sorted(filter_label(row) for row in generic) == sorted(
        ["generic-robust", "generic-prob", "generic-det"] * len(RECKLESS_TASKS)
    )
    robust = [row for row in generic if filter_label(row) == "generic-robust"]
    assert all(row["summary"]["coverage"] is not None for row in robust)
    assert all(row["summary"]["time_outside_lane_s"] == 0.0 for row in robust)


def test_another_camera_is_refused_in_one_line_naming_what_works():
    check_generic_image_shape("default", (64, 64, 3), (64, 64, 3))  # the model's: no error
    with pytest.raises(SafeRaceError, match=r"reads mono 64x64 images, not \(64, 64, 6\): drop"):
        check_generic_image_shape("default", (64, 64, 3), (64, 64, 6))
    with pytest.raises(SafeRaceError, match="not \\(48, 48, 3\\): use --image-size 64, or"):
        check_generic_image_shape("default", (64, 64, 3), (48, 48, 3))
    with pytest.raises(SafeRaceError, match="drop --stereo and use --image-size 64"):
        check_generic_image_shape("quick", (64, 64, 3), (96, 96, 6))


def frames_digest(round_dir: Path) -> str:
    """A digest of a round's frames: its arrays' bytes, in order."""
    with np.load(round_dir / "frames.npz") as arrays:
        content = b"".join(arrays[name].tobytes() for name in sorted(arrays))
    return hashlib.sha256(content).hexdigest()


def test_a_build_interrupted_part_way_through_a_track_resumes_to_the_same_frames(built: Path):
    """A drive cut off before its round was complete (no manifest: the collector writes it
    last) is driven again on resume, with its own seed: the track's rounds end as an
    uninterrupted build's, drive by drive."""
    track = write_tracks(TINY, "train")[0]
    folder = rounds_folder(TINY, track)
    rounds = round_dirs_of(folder)
    assert len(rounds) == len(TINY.drives("train", 0)) >= 2
    before = [frames_digest(round_dir) for round_dir in rounds]
    (rounds[-1] / "manifest.json").unlink()  # interrupted while writing the last drive
    assert len(round_dirs_of(folder)) == len(rounds) - 1
    collect_all(TINY, {"train": [track]}, workers=1, progress=False)
    after = round_dirs_of(folder)
    assert [frames_digest(round_dir) for round_dir in after] == before


def test_the_monitor_raises_on_a_look_the_model_trained_on_but_was_not_calibrated_for(
    built: Path,
):
    """The monitor's Gaussian is fitted on the calibration look's training frames only: on
    the training frames of the other look it raises far more often (fitted on both looks,
    it would take the strong look for the usual: 5.8% and 88% of the frames measured)."""
    loaded = load_checkpoint(built)
    monitor = ConformalCalibration.from_dict(loaded.metadata[CONFORMAL_KEY]).monitor
    assert monitor is not None
    training = load_rounds([rounds_folder(TINY, track) for track in write_tracks(TINY, "train")])
    looks = np.array([manifest["config"]["randomize"] for manifest in training.manifests])
    frame_looks = looks[training["source"]]
    features = predict_frames(loaded.state, network_data(training)["state"], 1).features
    alarms = np.array([monitor.raises(feature)[1] for feature in features])
    (calibrated,) = TINY.calibration_looks
    other = next(look for look in TINY.looks if look != calibrated)
    assert alarms[frame_looks == other].mean() > 0.5
    assert alarms[frame_looks == calibrated].mean() < 0.1


#: What a step's ``info`` knows that a car does not: where it is in the lane and in the
#: world, and whether it is out. The map at its arc length and its odometry it may read.
TRUTH_FIELDS = ("e_y_m", "e_psi_rad", "deviation_m", "reward_deviation", "cost")


def blinded(info: dict) -> dict:
    """``info`` with its truth unreadable: the lane state NaN, the exits unset, the pose
    moved 100 m (the odometry's steps between poses, all the carried set reads of them,
    are the same)."""
    return (
        info
        | dict.fromkeys(TRUTH_FIELDS, math.nan)
        | {
            "outside_lane": None,
            "fully_outside_lane": None,
            "x_m": info["x_m"] + 100.0,
            "y_m": info["y_m"] - 100.0,
        }
    )


@pytest.mark.parametrize("kind", ["cbf", "mpsf"])
def test_our_filters_fed_the_generic_model_decide_alike_with_the_truth_blinded(
    quick_perception: Path, kind: str
):
    """Nothing of ours reads the truth in a perceived run (the filter protocol hands a
    filter of one's own none): with every field of the truth unreadable in what our filter
    is handed, it sends the same actions (to rounding), the perception's in-doubt carried set
    included."""

    def filtered_actions(blind: bool) -> list[list[float]]:
        config = FilterConfig(kind=kind, state_source="generic:quick")
        env = make_task_env("RacingLine", "lab", 1, config, 0, max_steps=80)
        wrapper = env
        while not isinstance(wrapper, SafetyFilter):
            wrapper = wrapper.env
        if blind:  # what certify and the carried set's start are handed
            certify, start = wrapper.certify, wrapper.last_trusted.reset
            wrapper.certify = lambda observation, info, *rest: certify(  # type: ignore[method-assign]
                observation, blinded(info), *rest
            )
            wrapper.last_trusted.reset = lambda info=None: start(  # type: ignore[method-assign]
                None if info is None else blinded(info)
            )
        actions: list[list[float]] = []
        try:
            run_episode(
                env,
                make_agent("weave", env, seed=0),
                seed=0,
                on_step=lambda obs, info, action: actions.append(info["safety"]["filtered_action"]),
            )
        finally:
            env.close()
        return actions

    seen = filtered_actions(blind=False)
    assert len(seen) == 80
    # the moved pose rounds its last bits: the steps between poses differ by about 1e-14
    np.testing.assert_allclose(filtered_actions(blind=True), seen, rtol=0.0, atol=1e-9)
