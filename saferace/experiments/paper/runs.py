"""The paper's tables and figures from one command (paper Sec. 5: Tables 1-2, Figs. 5-9).

For each setting (Table 1: the paper's CARLA setting on ``technical``, dynamic model, mono;
Table 2: its RC-car setting on ``lab``, kinematic model, stereo) and each reference line,
five DAgger runs per seed: without the filter, the filtered fork (iterations after k fed
the state network's perceived state, the paper's chance constraints), the same fork behind
the robust filter fed the state network's conformal interval (what honest uncertainty
costs), fed the generic perception model (mono frames of its size only), and fed the true
state (what perception costs). Written to ``OUT``:
``{setting}.md``/``.csv`` in the layout of the paper's tables with the claims measured
below them, ``{setting}_trajectories.png`` (every iteration's path, without and with the
filter, one row per line), ``unseen_tracks.md`` (the final policies on tracks they never
saw, without and with the filter) and ``timings.md`` (wall-clock seconds per stage). Every
run resumes where it stopped.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import torch

from saferace.eval.drive import drive
from saferace.eval.filters import FilterConfig
from saferace.eval.runner import evaluate, max_steps_for
from saferace.experiments.paper.presets import (
    PERCEPTION_MODES,
    PRESETS,
    RUN_LABELS,
    Preset,
    TableSetting,
    dagger_config,
    run_config,
    run_kinds,
)
from saferace.experiments.paper.report import write_summaries, write_table
from saferace.learning.calibration import conformal_of, spread_scale_of
from saferace.learning.checkpoint import NETWORK_NAMES, load_checkpoint
from saferace.learning.dagger import DaggerRun
from saferace.learning.perception import ensure_perception_model
from saferace.learning.run_layout import RunLayout
from saferace.names import CONFORMAL_ALPHA, TASKS
from saferace.track.random_track import write_random_tracks


def run_dir(out_dir: Path, setting: TableSetting, task: str, seed: int, kind: str) -> Path:
    """The folder of one DAgger run: ``OUT/SETTING/TASK/seedN/KIND``."""
    return out_dir / setting.name / task / f"seed{seed}" / kind


def run_lines(
    preset: Preset, setting: TableSetting, seeds: list[int], out_dir: Path, progress: bool
) -> dict[tuple[str, int, str], list[dict]]:
    """The runs of each line and seed (:func:`~saferace.experiments.paper.presets.run_kinds`);
    their metric rows by (task, seed, kind)."""
    rows = {}
    for task in TASKS:
        for seed in seeds:
            base = dagger_config(preset, setting, task, seed)
            unfiltered = run_dir(out_dir, setting, task, seed, "none")
            for kind in run_kinds(preset, setting):
                config = run_config(base, kind, preset.perception)
                label = f"{setting.name} {task} seed {seed} {kind}"
                fork_of = None if kind == "none" else unfiltered
                run = DaggerRun(
                    run_dir(out_dir, setting, task, seed, kind), config, fork_of, progress, label
                )
                rows[(task, seed, kind)] = run.run()
    return rows


def from_1_name(kind: str) -> str:
    """The folder of the one-iteration fork filtered from iteration 1 behind the filter of
    perception mode ``kind`` (see :func:`filtered_from_1`)."""
    return f"{kind}_from_1"


def filtered_from_1(
    preset: Preset, setting: TableSetting, seeds: list[int], out_dir: Path, progress: bool
) -> dict[tuple[str, int, str], dict]:
    """Iteration 1 of each line driven behind the filter of each perception mode (a fork
    with ``k = 0``, one iteration long): the paper's headline asks whether the filter lets
    the learned driver lap earlier, and the forks of the table start after ``k``. Its
    networks are the unfiltered run's of iteration 1, so this drive is exactly the first of
    a fork filtered from the start. Its metric row by (task, seed, kind), for lines with
    ``k >= 1``."""
    rows = {}
    modes = [kind for kind in PERCEPTION_MODES if kind in run_kinds(preset, setting)]
    for task in TASKS:
        if setting.filter_from[task] < 1:
            continue
        for seed in seeds:
            for kind in modes:
                config = replace(
                    run_config(dagger_config(preset, setting, task, seed), kind, preset.perception),
                    filter_from=0,
                    iterations=1,
                )
                run = DaggerRun(
                    run_dir(out_dir, setting, task, seed, from_1_name(kind)),
                    config,
                    run_dir(out_dir, setting, task, seed, "none"),
                    progress,
                    f"{setting.name} {task} seed {seed} {kind} filtered from 1",
                )
                rows[(task, seed, kind)] = run.run()[1]
    return rows


def final_policy(
    preset: Preset, setting: TableSetting, run: Path, seed: int, kind: str = "cbf"
) -> tuple[str, FilterConfig]:
    """The agent spec of a run's final networks, and the setting's filter fed the perceived
    state as the run of ``kind`` feeds it (the spread calibrated as in its filtered
    iterations; for ``robust``, the conformal interval stored in the checkpoint; for
    ``generic``, the generic perception model)."""
    layout = RunLayout(run)
    checkpoint = layout.final_checkpoint()
    spec = f"learned:{checkpoint}"
    iteration = int(checkpoint.stem.removeprefix("iteration_"))
    robust = kind in ("robust", "generic")
    if kind == "robust":
        conformal_of(layout, iteration, CONFORMAL_ALPHA, preset.mc_samples, seed)
    scale = (
        spread_scale_of(layout, iteration, preset.mc_samples, seed)
        if preset.calibrate_spread and not robust
        else None
    )
    safety = FilterConfig(
        kind="cbf",
        model=setting.filter_model,
        gains=preset.filter_gains,
        state_source=preset.perception if kind == "generic" else spec,
        samples=preset.mc_samples,
        map_curvature=preset.map_curvature,
        spread_scale=scale,
        fuse_odometry=preset.fuse_odometry,
        uncertainty="robust" if robust else "chance",
        slack=preset.slack,
    )
    return spec, safety


def env_settings(preset: Preset, setting: TableSetting) -> dict:
    """The task's keyword arguments for driving a policy of this preset and setting."""
    return {
        "max_steps": max_steps_for(preset.max_seconds),
        "stereo": setting.stereo,
        "image_size": (preset.image_size, preset.image_size),
    }


#: How the unseen tracks' table names the filter a run's policy drives behind, by run.
UNSEEN_FILTER_LABELS = {
    "cbf": "perceived state",
    "robust": "perceived, conformal",
    "generic": "perceived, generic",
}


def same_networks(first: Path, second: Path, names: tuple[str, ...] = NETWORK_NAMES) -> bool:
    """Whether two checkpoints hold the same weights of the networks ``names`` (whatever
    else their metadata says)."""
    a, b = (
        {k: v for k, v in load_checkpoint(path).networks().items() if k in names}
        for path in (first, second)
    )
    return a.keys() == b.keys() and all(
        left.keys() == right.keys() and all(torch.equal(left[k], right[k]) for k in left)
        for left, right in ((a[name].state_dict(), b[name].state_dict()) for name in a)
    )


def unseen_track_rows(
    preset: Preset, setting: TableSetting, seeds: list[int], out_dir: Path, tracks: list[str]
) -> list[list]:
    """The final policies of the unfiltered run and of the perceived-state forks on tracks
    they never saw, one lap, without and with the filter fed their own state network as
    their run fed it (the generic fork: behind the generic model). A fork whose final
    networks are the unfiltered run's (it trained nothing of its own; for the generic fork,
    whose own state network feeds nothing, its control network) is not scored twice: only
    behind a filter of its own (the robust fork's conformal one, the generic model)."""
    lines = []
    kinds = [kind for kind in run_kinds(preset, setting) if kind != "oracle"]
    for task in TASKS:
        for seed in seeds:
            unfiltered = RunLayout(run_dir(out_dir, setting, task, seed, "none")).final_checkpoint()
            for kind in kinds:
                run = run_dir(out_dir, setting, task, seed, kind)
                driving = ("control",) if kind == "generic" else NETWORK_NAMES  # its own state
                inherited = kind != "none" and same_networks(  # network feeds nothing
                    RunLayout(run).final_checkpoint(), unfiltered, driving
                )
                if inherited and kind == "cbf":
                    continue
                spec, perceived = final_policy(preset, setting, run, seed, kind)
                owner = "none" if inherited else kind
                for track in tracks:
                    for safety in [perceived] if inherited else [FilterConfig(), perceived]:
                        (row,) = evaluate(
                            spec,
                            task,
                            track,
                            [seed],
                            progress=False,
                            env_kwargs=env_settings(preset, setting),
                            safety=safety,
                            mc_samples=preset.mc_samples,
                        )
                        summary = row["summary"]
                        lines.append(
                            [
                                setting.name,
                                task,
                                seed,
                                f"final of {RUN_LABELS[owner]} run",
                                Path(track).stem,
                                "none"
                                if safety.kind == "none"
                                else UNSEEN_FILTER_LABELS["cbf" if kind == "none" else kind],
                                summary["laps_completed"],
                                summary["mean_lap_time_s"] or "-",
                                summary["time_outside_lane_s"],
                                summary["longest_standstill_s"],
                            ]
                        )
    return lines


def record_final_filtered_lap(
    preset: Preset, setting: TableSetting, seed: int, out_dir: Path
) -> Path:
    """A Rerun recording of the final perceived-state racing-line policy's lap: what the
    filter believed against the truth, its corrections and its barriers."""
    task = "RacingLine"
    run = run_dir(out_dir, setting, task, seed, "cbf")
    spec, perceived = final_policy(preset, setting, run, seed)
    path = out_dir / f"{setting.name}_final_filtered_racingline.rrd"
    drive(
        task,
        setting.track,
        agent=spec,
        rerun=path,
        seed=seed,
        mc_samples=preset.mc_samples,
        safety=perceived,
        progress=False,
        **env_settings(preset, setting),
    )
    return path


def run_paper_tables(
    preset: str | Preset, seeds: list[int], out_dir: str | Path, progress: bool = True
) -> list[Path]:
    """Run (or resume) everything the preset (a name of :data:`PRESETS` or one's own) asks
    for and write the tables and figures; the paths written. ``unseen_tracks.md`` and
    ``timings.md`` are rewritten after each setting, so a long run shows what it has."""
    if isinstance(preset, str):
        preset = PRESETS[preset]
    if any("generic" in run_kinds(preset, setting) for setting in preset.settings):
        ensure_perception_model(preset.perception)  # built once, before any run needs it
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    timings = dict.fromkeys(("collection", "training", "unseen tracks", "recording"), 0.0)
    tracks = [*preset.unseen_tracks, *write_random_tracks(out_dir / "tracks", preset.random_tracks)]
    unseen = []
    for setting in preset.settings:
        rows = run_lines(preset, setting, seeds, out_dir, progress)
        from_1 = filtered_from_1(preset, setting, seeds, out_dir, progress)
        timings["collection"] += sum(row["collect_seconds"] or 0.0 for row in from_1.values())
        for (task, _, kind), runs in rows.items():
            shared = -1 if kind == "none" else setting.filter_from[task]
            for row in runs:
                if row["iteration"] <= shared:
                    continue  # a fork's shared rows are the unfiltered run's
                timings["collection"] += row["collect_seconds"] or 0.0
                timings["training"] += row["train_seconds"] or 0.0
        written += write_table(preset, setting, rows, from_1, seeds, out_dir)
        started = time.perf_counter()
        unseen += unseen_track_rows(preset, setting, seeds, out_dir, tracks)
        timings["unseen tracks"] += time.perf_counter() - started
        started = time.perf_counter()
        written.append(record_final_filtered_lap(preset, setting, seeds[0], out_dir))
        timings["recording"] += time.perf_counter() - started
        summaries = write_summaries(preset, unseen, timings, out_dir)
    return [*written, *summaries]
