"""Collection rounds on disk: round trip, aggregation, atomic writes under a kill."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import first_line

from saferace.errors import SafeRaceError
from saferace.learning.rounds import (
    FRAME_FIELDS,
    load_rounds,
    next_round_index,
    round_dirs,
    write_round,
)


def fake_frames(count: int, channels: int = 3, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "image": rng.integers(0, 256, (count, 16, 16, channels), np.uint8),
        "velocity": rng.normal(size=(count, 3)),
        "driver_action": rng.normal(size=(count, 2)),
        "applied_action": rng.normal(size=(count, 2)),
        "expert": rng.normal(size=(count, 3)),
        "state": rng.normal(size=(count, 3)),
        "s_m": np.linspace(0.0, 9.0, count),
        "time_s": np.arange(count) * 0.05,
        "episode": np.zeros(count, int),
        "intervened": rng.random(count) < 0.5,
    }


def config(track: str = "lab", task: str = "CenterLine") -> dict:
    return {"track": track, "task": task, "track_length_m": 24.13}


def test_round_trip_with_per_frame_round_data(tmp_path: Path):
    first, second = fake_frames(5), fake_frames(7, seed=1)
    assert write_round(tmp_path, first, config()).name == "round_0000"
    assert write_round(tmp_path, second, config(task="RacingLine")).name == "round_0001"
    frames = load_rounds([tmp_path])
    assert len(frames) == 12
    for name, (dtype, _) in FRAME_FIELDS.items():
        expected = np.concatenate([first[name], second[name]]).astype(dtype)
        assert np.array_equal(frames[name], expected), name
    assert frames["round"].tolist() == [0] * 5 + [1] * 7
    assert set(frames["task"][5:]) == {"RacingLine"} and set(frames["track"]) == {"lab"}
    assert [m["frame_count"] for m in frames.manifests] == [5, 7]
    only_second = load_rounds([tmp_path / "round_0001"])
    assert len(only_second) == 7 and only_second["round"][0] == 1


def test_held_out_frames_are_kept_apart_from_the_training_frames(tmp_path: Path):
    train, held_out = fake_frames(5), fake_frames(3, seed=1)
    write_round(tmp_path, train, config(), held_out)
    write_round(tmp_path, fake_frames(4, seed=2), config())  # none held out
    frames, apart = load_rounds([tmp_path]), load_rounds([tmp_path], held_out=True)
    assert len(frames) == 9 and len(apart) == 3
    assert np.array_equal(apart["image"], held_out["image"])
    assert np.array_equal(frames["image"][:5], train["image"])
    assert [m["held_out_frame_count"] for m in apart.manifests] == [3, 0]
    with pytest.raises(SafeRaceError, match="no held-out frames"):
        load_rounds([tmp_path / "round_0001"], held_out=True)


def test_aggregates_folders_without_duplicates(tmp_path: Path):
    write_round(tmp_path / "a", fake_frames(3), config())
    write_round(tmp_path / "b", fake_frames(4), config(track="oval"))
    frames = load_rounds([tmp_path / "a", tmp_path / "b", tmp_path / "a" / "round_0000"])
    assert len(frames) == 7 and frames["track"].tolist() == ["lab"] * 3 + ["oval"] * 4


def test_bad_rounds_are_refused(tmp_path: Path):
    with pytest.raises(SafeRaceError, match="needs the arrays"):
        write_round(tmp_path, {"s_m": np.zeros(3)}, config())
    broken = fake_frames(4)
    broken["state"] = broken["state"][:3]
    with pytest.raises(SafeRaceError, match="'state' has shape"):
        write_round(tmp_path, broken, config())
    with pytest.raises(SafeRaceError, match="no complete collection round"):
        load_rounds([tmp_path / "nothing"])
    write_round(tmp_path / "mixed", fake_frames(2), config())
    write_round(tmp_path / "mixed", fake_frames(2, channels=6), config())
    with pytest.raises(SafeRaceError, match="different image shapes"):
        load_rounds([tmp_path / "mixed"])


def test_interrupted_write_leaves_no_round(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    write_round(tmp_path, fake_frames(3), config())

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez_compressed", interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_round(tmp_path, fake_frames(3), config())
    assert [p.name for p in tmp_path.iterdir()] == ["round_0000"]


WRITER = """
import sys
import time
import numpy as np
from saferace.learning.rounds import next_round_index, write_round
sys.path.insert(0, {tests!r})
from test_rounds import config, fake_frames
save = np.savez_compressed


def save_then_stop(*args, **kwargs):
    save(*args, **kwargs)
    if next_round_index({dataset!r}) == 1:  # the second round half written: stop here
        print("stopped", flush=True)
        time.sleep(3600)


np.savez_compressed = save_then_stop
frames = fake_frames(6000, seed=2)
while True:
    write_round({dataset!r}, frames, config())
"""


def test_a_kill_mid_write_leaves_only_complete_rounds(tmp_path: Path):
    dataset = tmp_path / "data"
    script = WRITER.format(tests=str(Path(__file__).parent), dataset=str(dataset))
    writer = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert first_line(writer) == "stopped"
    finally:
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait()
    partials = list(dataset.glob(".partial-*"))
    complete = round_dirs(dataset)
    assert len(partials) == len(complete) == 1  # one finished round, one half written
    frames = load_rounds([dataset])  # every earlier round loads ...
    assert len(frames) == 6000 * len(complete)
    assert next_round_index(dataset) == len(complete)  # ... and the half-written one is no round
    with pytest.raises(SafeRaceError, match="no complete collection round"):
        load_rounds([partials[0]])
    write_round(dataset, fake_frames(2), config())  # the next writer clears the dead one's mess
    assert not list(dataset.glob(".partial-*"))
    assert len(round_dirs(dataset)) == len(complete) + 1
