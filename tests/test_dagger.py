"""DAgger runs: iterations, the train split, the fork, refusal of other settings, resuming."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_helpers import first_line

from saferace.errors import SafeRaceError
from saferace.eval.filter_config import FilterConfig
from saferace.learning import training
from saferace.learning.calibration import inside_lane
from saferace.learning.checkpoint import load_checkpoint
from saferace.learning.configs import DaggerConfig, EpisodeSettings, TrainConfig
from saferace.learning.dagger import DaggerRun, episode_seed, episode_seeds
from saferace.learning.rounds import FrameSet, load_rounds
from saferace.learning.run_layout import RunLayout
from saferace.learning.training_data import network_data
from saferace.learning.validation import predict_frames
from saferace.track import Track

#: Two iterations of 3 s drives on small images: every stage runs in seconds.
TINY = DaggerConfig(
    task="CenterLine",
    track="lab",
    iterations=2,
    filter_from=1,
    training=TrainConfig(epochs=2, val_stretch=None),
    collection=EpisodeSettings(
        laps=1,
        max_seconds=3.0,
        image_size=32,
        expert_model="kinematic",
        mc_samples=3,
        train_fraction=0.3,
    ),
    filter=FilterConfig(state_source="learned", uncertainty="chance"),  # the paper's filter
)


def with_filter(config: DaggerConfig, **settings) -> DaggerConfig:
    """``config`` with these settings of its filter changed."""
    return replace(config, filter=replace(config.filter, **settings))


@pytest.fixture(scope="module")
def unfiltered(tmp_path_factory: pytest.TempPathFactory) -> DaggerRun:
    run = DaggerRun(tmp_path_factory.mktemp("dagger") / "none", TINY, progress=False)
    run.run()
    return run


def rounds_equal(first: Path, second: Path) -> bool:
    a, b = load_rounds([first]), load_rounds([second])
    return len(a) == len(b) and all(
        np.array_equal(a[name], b[name]) for name in ("image", "expert", "state", "applied_action")
    )


def weights_equal(first: Path, second: Path) -> bool:
    a, b = load_checkpoint(first), load_checkpoint(second)
    return all(
        torch.equal(weights, getattr(b, name).state_dict()[key])
        for name in ("control", "state")
        for key, weights in getattr(a, name).state_dict().items()
    )


def test_iterations_rounds_and_metrics(unfiltered: DaggerRun):
    rows = unfiltered.metrics()
    assert [row["iteration"] for row in rows] == [0, 1, 2]
    assert [row["driver"] for row in rows] == ["expert", "learned", "learned"]
    assert not any(row["filtered"] for row in rows)
    assert rows[0]["train_seconds"] is None and rows[1]["train_seconds"] > 0
    assert rows[0]["held_out_mean_abs_deviation_m"] is not None  # the drive passed 0.3 L
    for iteration in (1, 2):
        checkpoint = load_checkpoint(unfiltered.layout.checkpoint(iteration))
        assert checkpoint.metadata["frames"]["train"] == sum(r["frames"] for r in rows[:iteration])
    for row in rows:  # a standstill while the driver asks to move is a stop
        assert 0.0 <= row["longest_standstill_s"] <= row["longest_stop_s"]
    assert rows[0]["longest_standstill_s"] == 0.0  # the expert never stands still
    csv_lines = (unfiltered.out_dir / "metrics.csv").read_text().splitlines()
    assert len(csv_lines) == 4 and csv_lines[0].startswith("iteration,driver,filtered")
    assert ",longest_stop_s,longest_standstill_s," in csv_lines[0]


def test_the_train_split_keeps_no_frame_past_it(unfiltered: DaggerRun):
    frames = load_rounds([unfiltered.layout.data_dir])
    assert frames.lap_fraction.max() < TINY.collection.train_fraction
    expert_round = load_rounds([unfiltered.layout.round(0)])
    drive_steps = unfiltered.metrics()[0]["trajectory"]["s_m"]
    lap_m = Track.load(TINY.track).length_m
    assert max(drive_steps) > TINY.collection.train_fraction * lap_m  # drove past, kept none
    assert len(expert_round) < 60


def test_fork_shares_iterations_up_to_k_bit_for_bit(unfiltered: DaggerRun, tmp_path: Path):
    filtered = with_filter(TINY, kind="cbf")
    forked = DaggerRun(tmp_path / "fork", filtered, fork_of=unfiltered.out_dir, progress=False)
    recomputed = DaggerRun(tmp_path / "alone", filtered, progress=False)
    forked_rows, alone_rows = forked.run(), recomputed.run()
    for iteration in range(TINY.filter_from + 1):
        for run in (forked, recomputed):
            assert rounds_equal(unfiltered.layout.round(iteration), run.layout.round(iteration))
    for iteration in (1, 2):  # iteration K+1's networks are trained on 0..K too
        assert weights_equal(
            unfiltered.layout.checkpoint(iteration), forked.layout.checkpoint(iteration)
        )
        assert weights_equal(
            unfiltered.layout.checkpoint(iteration), recomputed.layout.checkpoint(iteration)
        )
    assert [row["filtered"] for row in forked_rows] == [False, False, True]
    assert forked_rows[2]["intervention_rate"] is not None
    assert not rounds_equal(unfiltered.layout.round(2), forked.layout.round(2))  # filtered now
    assert rounds_equal(forked.layout.round(2), recomputed.layout.round(2))
    assert forked_rows[2]["lap_time_s"] == alone_rows[2]["lap_time_s"]


def test_a_folder_refuses_a_run_with_other_settings(unfiltered: DaggerRun):
    more_epochs = replace(TINY, training=replace(TINY.training, epochs=3))
    with pytest.raises(SafeRaceError, match="differing: epochs"):
        DaggerRun(unfiltered.out_dir, more_epochs, progress=False)
    stored = {path: path.stat().st_mtime_ns for path in unfiltered.out_dir.rglob("*")}
    shorter = DaggerRun(unfiltered.out_dir, replace(TINY, iterations=1), progress=False)
    assert shorter.run()[:2] == unfiltered.metrics()[:2]  # the same run, one iteration less
    assert {path: path.stat().st_mtime_ns for path in stored} == stored  # nothing redone
    other_forks = replace(with_filter(TINY, state_source=None, gains="tuned"), filter_from=2)
    same = DaggerRun(unfiltered.out_dir, other_forks, progress=False)  # no filter settings
    assert same.run() == unfiltered.metrics()  # nothing driven or trained again


def test_the_true_state_fork_keeps_the_state_network_it_forked_with(
    unfiltered: DaggerRun, tmp_path: Path
):
    oracle = replace(with_filter(TINY, kind="cbf", state_source=None), filter_from=0)
    forked = DaggerRun(tmp_path / "oracle", oracle, fork_of=unfiltered.out_dir, progress=False)
    forked.run()
    shared, trained = (load_checkpoint(forked.layout.checkpoint(i)) for i in (1, 2))
    for name, weights in shared.state.state_dict().items():
        assert torch.equal(weights, trained.state.state_dict()[name]), name
    assert not torch.equal(shared.control.output_layer.weight, trained.control.output_layer.weight)
    assert oracle.fingerprint["trained_networks"] == ["control"]
    both = (TINY, with_filter(oracle, state_source="learned"), replace(oracle, warm_start=False))
    for config in both:
        assert "trained_networks" not in config.fingerprint  # both, as before the option
    with pytest.raises(SafeRaceError, match="above max_steps"):
        replace(TINY, training=replace(TINY.training, min_steps=8, max_steps=4))


def test_odometry_fusion_belongs_to_the_perceived_state_forks_only():
    """Runs made before the option existed, and the forks it does nothing to, keep their
    fingerprint; a perceived-state fork that fuses is another run."""
    fused = with_filter(TINY, fuse_odometry=True)
    oracle = with_filter(TINY, kind="cbf", state_source=None)  # the truth cannot be fused
    for config in (TINY, fused, oracle):
        assert "fuse_odometry" not in config.fingerprint
    learned = with_filter(fused, kind="cbf", state_source="learned")
    assert learned.fingerprint["fuse_odometry"] is True
    assert "fuse_odometry" not in with_filter(learned, fuse_odometry=False).fingerprint


def test_a_calibrated_fork_widens_the_spread_fitted_on_the_held_out_part_of_the_lap(
    unfiltered: DaggerRun, tmp_path: Path
):
    calibrated = replace(with_filter(TINY, kind="cbf"), calibrate_spread=True)
    run = DaggerRun(tmp_path / "cbf", calibrated, fork_of=unfiltered.out_dir, progress=False)
    rows = run.run()
    record = json.loads(RunLayout(run.out_dir).spread_scale(2).read_text())
    fitted_on = next(i for i in (1, 0) if len(held_out_inside(unfiltered, i)) >= 20)
    assert record["fitted_on"] == f"round_{fitted_on:04d} (held_out.npz)"
    frames = held_out_inside(unfiltered, fitted_on)
    assert frames.lap_fraction.min() >= TINY.collection.train_fraction  # never trained on
    network = load_checkpoint(run.layout.checkpoint(2)).state  # the network about to drive
    # Variance scaling by hand: the RMS of the error in spreads per output, floored at 1.
    data = network_data(frames)["state"]
    prediction = predict_frames(network, data, TINY.collection.mc_samples, seed=TINY.seed)
    errors_in_spreads = (prediction.mean - data.targets) / prediction.std
    expected = np.maximum(np.sqrt(np.mean(errors_in_spreads**2, axis=0)), 1.0)
    assert record["spread_scale"] == pytest.approx(expected.tolist(), rel=1e-5)
    assert rows[2]["spread_scale_e_y"] == record["spread_scale"][0] >= 1.0
    assert rows[1]["spread_scale_e_y"] is None  # unfiltered: nothing to calibrate
    manifest = json.loads(run.layout.manifest(2).read_text())
    assert manifest["config"]["safety"]["spread_scale"] == record["spread_scale"]
    oracle = with_filter(calibrated, state_source=None)
    DaggerRun(tmp_path / "oracle", oracle, fork_of=unfiltered.out_dir, progress=False).run()
    assert not RunLayout(tmp_path / "oracle").spread_scale(2).exists()  # the truth has no spread
    with pytest.raises(SafeRaceError, match="train_fraction < 1"):
        replace(calibrated, collection=replace(calibrated.collection, train_fraction=1.0))


def held_out_inside(run: DaggerRun, iteration: int) -> FrameSet | list:
    """The held-out frames of a round with the car inside the lane (none: an empty list)."""
    manifest = json.loads(run.layout.manifest(iteration).read_text())
    if not manifest["held_out_frame_count"]:
        return []
    frames = load_rounds([run.layout.round(iteration)], held_out=True)
    return frames.subset(inside_lane(frames, Track.load(TINY.track)))


RUNNER = """
import sys
sys.path.insert(0, {tests!r})
from test_dagger import TINY, stop_at
from saferace.learning.dagger import DaggerRun
stop_at({point!r}, {out!r})
DaggerRun({out!r}, TINY, progress=False).run()
"""
#: Printed by a run stopped at its point, where it waits to be killed.
STOPPED = "stopped"
#: Frames a killed drive had recorded (iteration 1 of TINY drives 10 to 20).
FRAMES_BEFORE_THE_KILL = 5


def stop_at(point: str, out: str) -> None:
    """Make this process's DAgger run in ``out`` print :data:`STOPPED` and wait at ``point``:
    ``driving 1`` (iteration 1's car :data:`FRAMES_BEFORE_THE_KILL` steps into its drive)
    or ``resume 2`` (the first epoch of iteration 2's training saved to its resume file),
    so a kill lands there."""
    from saferace.learning import collect, training
    from saferace.learning.rounds import next_round_index

    layout = RunLayout(out)

    def wait() -> None:
        print(STOPPED, flush=True)
        time.sleep(3600)

    after_step, save_atomically = collect.LabellingDriver.after_step, training.save_atomically

    def after_step_then(driver, *args, **kwargs):
        after_step(driver, *args, **kwargs)
        driving_1 = point == "driving 1" and next_round_index(layout.data_dir) == 1
        if driving_1 and len(driver.frames["image"]) == FRAMES_BEFORE_THE_KILL:
            wait()

    def save_then(state, path):
        save_atomically(state, path)
        if point == "resume 2" and Path(path) == layout.resume(2):
            wait()

    collect.LabellingDriver.after_step = after_step_then
    training.save_atomically = save_then


def kill_at(point: str, out: Path) -> None:
    """Run TINY in ``out`` in another process and kill it at ``point`` (see :func:`stop_at`)."""
    script = RUNNER.format(tests=str(Path(__file__).parent), point=point, out=str(out))
    process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert first_line(process) == STOPPED, f"the run never reached {point}"
    finally:
        os.kill(process.pid, signal.SIGKILL)
        process.wait()


def test_killed_while_driving_and_while_training_it_ends_with_the_same_rounds(
    unfiltered: DaggerRun, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    out = tmp_path / "killed"
    run = DaggerRun(out, TINY, progress=False)
    kill_at("driving 1", out)
    assert run.layout.checkpoint(1).exists() and not run.layout.round(1).exists()
    assert not list(run.layout.data_dir.glob(".partial-*"))  # killed before any write
    kill_at("resume 2", out)
    assert run.layout.resume(2).exists() and not run.layout.checkpoint(2).exists()
    losses = []  # one per gradient step the finishing run takes
    loss = training.training_loss
    monkeypatch.setattr(training, "training_loss", lambda *a: losses.append(1) or loss(*a))
    rows = run.run()
    # The control network's first epoch was done: its second and the state network's two.
    frames = len(load_rounds([run.layout.round(0), run.layout.round(1)]))
    batches = math.ceil(frames / TINY.training.batch_size)
    assert TINY.training.steps_for(frames) == 2 * batches  # two epochs per network
    assert len(losses) == 3 * batches
    assert [row["iteration"] for row in rows] == [0, 1, 2]
    for iteration in range(3):
        assert rounds_equal(unfiltered.layout.round(iteration), run.layout.round(iteration))
    assert weights_equal(unfiltered.layout.checkpoint(2), run.layout.checkpoint(2))
    assert sorted(p.name for p in run.layout.data_dir.iterdir()) == [
        "round_0000",
        "round_0001",
        "round_0002",
    ]


def test_an_iterations_episodes_on_two_workers_add_frames_and_keep_the_first(
    unfiltered: DaggerRun, tmp_path: Path
):
    wider = replace(TINY, iterations=0, episodes=2)
    run = DaggerRun(tmp_path / "two", wider, progress=False, workers=2)
    run.run()
    both = load_rounds([run.layout.round(0)])
    first = load_rounds([unfiltered.layout.round(0)])
    assert set(both["episode"]) == {0, 1}
    shared = both["episode"] == 0
    np.testing.assert_array_equal(both["image"][shared], first["image"])  # episode 0 as before
    assert run.metrics()[0]["frames"] == len(both)
    assert episode_seeds(0, 0, 2)[0] == episode_seed(0, 0)
