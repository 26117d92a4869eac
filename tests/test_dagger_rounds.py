"""DAgger's per-round API: training and collecting an iteration one call at a time gives
the run that ``run()`` gives, and the calls refuse what they cannot do yet."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from saferace.errors import SafeRaceError
from saferace.learning.configs import DaggerConfig, EpisodeSettings, TrainConfig
from saferace.learning.dagger import DaggerRun
from saferace.learning.run_layout import RunLayout

ONE_ITERATION = DaggerConfig(
    task="CenterLine",
    track="lab",
    iterations=1,
    training=TrainConfig(epochs=1, val_stretch=None),
    collection=EpisodeSettings(
        laps=1, max_seconds=2.0, image_size=32, mc_samples=2, expert_model="kinematic"
    ),
)


def test_rounds_one_call_at_a_time_make_the_run_and_forks_link_them(tmp_path: Path):
    run = DaggerRun(tmp_path / "by_hand", ONE_ITERATION, progress=False)
    with pytest.raises(SafeRaceError, match="iteration 0 is the expert's"):
        run.train_iteration(0)
    with pytest.raises(SafeRaceError, match="rounds \\[0\\] not driven yet"):
        run.train_iteration(1)
    with pytest.raises(SafeRaceError, match="train it first"):
        run.collect_iteration(1)
    rows = run.collect_iteration(0)
    assert [row["iteration"] for row in rows] == [0] and rows[0]["driver"] == "expert"
    seconds = run.train_iteration(1)
    rows = run.collect_iteration(1, seconds)
    assert [row["iteration"] for row in rows] == [0, 1]
    assert rows[1]["train_seconds"] == seconds and rows[1]["collect_seconds"] > 0
    assert run.collect_iteration(1) == rows  # recorded once

    looped = DaggerRun(tmp_path / "looped", ONE_ITERATION, progress=False).run()
    keys = ("iteration", "completed", "lap_time_s", "duration_s", "mean_abs_deviation_m", "frames")
    assert [{k: r[k] for k in keys} for r in looped] == [{k: r[k] for k in keys} for r in rows]

    # A fork filtered from iteration 1 links the unfiltered run's shared files, no copies.
    paper_filter = replace(
        ONE_ITERATION.filter, kind="cbf", state_source="learned", uncertainty="chance", gains="grip"
    )
    fork_config = replace(ONE_ITERATION, filter_from=0, filter=paper_filter)
    fork = DaggerRun(tmp_path / "cbf", fork_config, fork_of=tmp_path / "looped", progress=False)
    fork.run()
    source, linked = RunLayout(tmp_path / "looped"), RunLayout(tmp_path / "cbf")
    for path in (linked.checkpoint(1), *linked.round(0).iterdir()):
        original = source.root / path.relative_to(linked.root)
        assert path.stat().st_ino == original.stat().st_ino, path  # the same file on disk
    rows = [json.loads(line) for line in linked.metrics_jsonl.read_text().splitlines()]
    assert [row["filtered"] for row in rows] == [False, True]
