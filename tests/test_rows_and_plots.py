"""What a result row says and what the plots show: the filter and its state source in
every table and label, a row's track found from any folder, legends off the track,
captioned snapshots, GradCAM titles with units and a colour bar, and reckless paths drawn
as large as a circuit needs."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run_cli

from saferace.errors import SafeRaceError
from saferace.eval.filter_config import FilterConfig
from saferace.eval.leaderboard import (
    COLUMNS,
    filter_words,
    group_label,
    leaderboard_markdown,
    leaderboard_rows,
    plot_trajectories,
    row_label,
    same_paths,
    state_source_words,
)
from saferace.eval.runner import row_track, track_reference
from saferace.eval.track_plots import legend_outside, plot_track, plt
from saferace.track import Track
from saferace.track.random_track import write_random_track


def summary(lap_s: float | None, outside_s: float = 0.0, rate: float | None = None) -> dict:
    return {
        "laps_completed": 0 if lap_s is None else 1,
        "best_lap_time_s": lap_s,
        "mean_lap_time_s": lap_s,
        "mean_abs_deviation_m": 0.1,
        "max_abs_deviation_m": 0.3,
        "time_outside_lane_s": outside_s,
        "steering_rate_rms_radps": 0.2,
        **({} if rate is None else {"intervention_rate": rate}),
    }


def fake_row(seed: int, safety: FilterConfig | None, track: str = "lab", **summary_args) -> dict:
    """A drift row on ``track``; ``safety`` None: a row written before rows named a filter."""
    row = {
        "agent": "drift",
        "task": "CenterLine",
        "track": Path(track).stem,
        "seed": seed,
        "summary": summary(**summary_args),
        "config": track_reference(track),
        "trajectory": {"x_m": [0.0, 1.0, 2.0], "y_m": [0.0, 0.1, 0.2], "s_m": [0.0, 1.0, 2.0],
                       "v_x_mps": [1.0, 2.0, 2.5]},
    }  # fmt: skip
    if safety is not None:
        row["filter"] = safety.as_dict()
    return row


def test_leaderboard_keeps_filtered_and_unfiltered_runs_apart(tmp_path: Path):
    cbf = FilterConfig(kind="cbf")
    rows = [
        fake_row(0, FilterConfig(), lap_s=None, outside_s=0.25),
        fake_row(1, None, lap_s=None, outside_s=0.5),  # an old row: no filter recorded
        fake_row(0, cbf, lap_s=8.75, rate=0.9),
    ]
    lines = leaderboard_rows(rows)
    assert len(lines) == 2  # never one row of "seeds 2" mixing the filter in
    by_filter = {line[COLUMNS.index("filter")]: line for line in lines}
    assert set(by_filter) == {"none", "cbf"}
    unfiltered, filtered = by_filter["none"], by_filter["cbf"]
    assert unfiltered[COLUMNS.index("seeds")] == 2  # the old row joined the unfiltered run
    assert filtered[COLUMNS.index("seeds")] == 1
    assert filtered[COLUMNS.index("state source")] == "true state"
    assert unfiltered[COLUMNS.index("state source")] == "none"
    assert filtered[COLUMNS.index("interventions [%]")] == pytest.approx(90.0)
    assert unfiltered[COLUMNS.index("interventions [%]")] is None
    header = leaderboard_markdown(rows).splitlines()[0]
    assert "| filter" in header and "| state source" in header and "interventions" in header
    labels = [row_label(row) for row in rows]
    assert labels[0].endswith("no filter") and labels[1] == labels[0].replace("seed 0", "seed 1")
    assert "filter: cbf; state source: true state" in labels[2]
    plot_trajectories(rows, tmp_path / "board.png")
    assert (tmp_path / "board.png").stat().st_size > 20_000


def test_runs_that_drove_the_same_path_are_drawn_once_under_all_their_labels(tmp_path: Path):
    """Two seeds of a deterministic driver from the same start drive one path: drawn twice,
    the second would hide the first and its legend entry would point at nothing."""
    rows = [fake_row(seed, None, lap_s=9.0) for seed in (0, 1, 2)]
    rows[2]["trajectory"] = {**rows[2]["trajectory"], "y_m": [0.0, -0.1, -0.2]}
    groups = same_paths(rows)
    assert [[row["seed"] for row in group] for group in groups] == [[0, 1], [2]]
    assert group_label(groups[0]) == f"{row_label(rows[0])} = {row_label(rows[1])} (the same path)"
    assert group_label(groups[1]) == row_label(rows[2])
    met_a_car = {**rows[1], "traffic": {"opponents": [], "collisions": [{"x_m": 1.0}]}}
    assert len(same_paths([rows[0], met_a_car])) == 2  # the same path, other traffic
    plot_trajectories(rows, tmp_path / "board.png")
    assert (tmp_path / "board.png").stat().st_size > 20_000


def test_filter_and_state_source_in_words():
    noisy = FilterConfig(kind="cbf", state_noise=(0.05, 0.05))
    learned = FilterConfig(kind="cbf", state_source="learned:runs/lab.pt", samples=10)
    assert filter_words(noisy) == "cbf, probabilistic"
    assert filter_words(FilterConfig(kind="cbf", state_noise=(0.05, 0.05), probabilistic=False)) \
        == "cbf, on the mean"  # fmt: skip
    assert state_source_words(noisy) == "noisy (sd 0.05 m, 0.05 rad)"
    assert state_source_words(learned) == "perceived (lab.pt, 10 samples)"
    assert state_source_words(FilterConfig(kind="cbf")) == "true state"
    assert filter_words(FilterConfig(kind="cbf", gains="paper")) == "cbf, paper gains"
    # two filters that differ only in their gains: two leaderboard lines, two labels
    rows = [fake_row(0, FilterConfig(kind="cbf", gains=g), lap_s=9.0) for g in ("paper", "grip")]
    assert len(leaderboard_rows(rows)) == 2 and row_label(rows[0]) != row_label(rows[1])


def test_eval_names_the_filter_and_the_leaderboard_plots_from_another_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The issue: a row named its track relative to where eval ran, so the leaderboard's
    plot failed from any other folder; and eval --filter cbf printed an unfiltered table."""
    runs, elsewhere = tmp_path / "runs", tmp_path / "elsewhere"
    runs.mkdir()
    elsewhere.mkdir()
    track = write_random_track(runs / "my_track.csv", 11)
    monkeypatch.chdir(runs)
    for extra in ((), ("--filter", "cbf")):
        result = run_cli(
            "eval", "--agent", "drift", "--track", "my_track.csv", "--max-seconds", "1",
            "--out", "rows.jsonl", *extra,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        table = [line for line in result.stdout.splitlines() if line.startswith("|")]
        assert "| filter" in table[0] and "| state source" in table[0]
        cells = [cell.strip() for cell in table[2].strip("|").split("|")]
        assert cells[3:5] == (["cbf", "true state"] if extra else ["none", "none"])
    monkeypatch.chdir(elsewhere)
    board = run_cli("leaderboard", str(runs / "rows.jsonl"), "--plot", "board.png")
    assert board.returncode == 0, board.stderr
    assert len([line for line in board.stdout.splitlines() if line.startswith("| ")]) == 1 + 2
    assert (elsewhere / "board.png").stat().st_size > 20_000
    track.write_text(track.read_text().replace("0.", "1.", 1))  # the file changed since
    refused = run_cli("leaderboard", str(runs / "rows.jsonl"), "--plot", "board.png")
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert str(track) in refused.stderr and "sha256" in refused.stderr


def test_a_row_finds_its_track_by_absolute_path_and_hash(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    track = write_random_track(tmp_path / "a" / "t.csv", 23)
    monkeypatch.chdir(tmp_path / "a")
    reference = track_reference("t.csv")
    assert reference["track"] == str(track) and reference["track_given"] == "t.csv"
    assert len(reference["track_sha256"]) == 64
    assert track_reference("lab") == {"track": "lab", "track_sha256": None, "track_given": "lab"}
    row = {"config": reference, "track": "t"}
    monkeypatch.chdir(tmp_path / "b")
    assert row_track(row).centerline.length_m == pytest.approx(
        Track.load(track).centerline.length_m
    )
    old_row = {"config": {"track": "t.csv"}, "track": "t"}  # written before: relative, no hash
    with pytest.raises(SafeRaceError, match="not found from"):
        row_track(old_row, "row 7")
    original = track.read_bytes()
    track.write_bytes(original.replace(b"0.", b"1.", 1))
    with pytest.raises(SafeRaceError, match=r"row 3.*has changed.*sha256") as refused:
        row_track(row, "row 3")
    assert str(track) in str(refused.value) and reference["track_sha256"] in str(refused.value)
    track.unlink()
    with pytest.raises(SafeRaceError, match=r"row 3.*is gone"):
        row_track(row, "row 3")
    track.write_bytes(original)  # put back: found again
    assert row_track(row).name == "t"


def test_legends_sit_outside_the_axes():
    figure, (ax_map, ax_speed) = plt.subplots(1, 2, layout="constrained")
    plot_track(ax_map, Track.load("lab"))
    ax_map.plot([0, 1], [0, 0], label="a driven path")
    ax_speed.plot([0, 1], [1, 2], label="speed")
    legend_outside(figure, (ax_map, ax_speed))
    figure.canvas.draw()
    (legend,) = figure.legends
    assert [t.get_text() for t in legend.get_texts()] == ["start/finish", "a driven path", "speed"]
    box = legend.get_window_extent()
    for ax in (ax_map, ax_speed):
        assert not box.overlaps(ax.get_window_extent())
    plt.close(figure)


def test_snapshot_views_are_captioned():
    from saferace.eval.drive import CAPTION_HEIGHT_PX, captioned_views

    chase = np.full((240, 320, 3), 90, np.uint8)
    for channels, panel_width in ((3, 240), (6, 120)):
        onboard = np.full((64, 64, channels), 90, np.uint8)
        frame = captioned_views(onboard, chase)
        assert frame.shape == (240 + CAPTION_HEIGHT_PX, panel_width + 320, 3)
        band = frame[:CAPTION_HEIGHT_PX]
        for columns in (band[:, :panel_width], band[:, panel_width:]):  # onboard, chase
            assert (columns.max(axis=2) < 128).sum() > 20  # dark text on the white band
        if channels == 6:  # "left" and "right" written on the stacked views
            top, bottom = (
                frame[CAPTION_HEIGHT_PX:][:120, :120],
                frame[CAPTION_HEIGHT_PX:][120:, :120],
            )
            for view in (top, bottom):
                assert (view.min(axis=2) > 200).sum() > 10  # white letters on grey


def test_gradcam_titles_name_the_outputs_with_units_and_the_sheet_has_a_colour_bar():
    from saferace.learning.gradcam import (
        COLOUR_BAR_WIDTH_PX,
        TITLE_HEIGHT_PX,
        column_titles,
        gradcam_sheet,
    )
    from saferace.learning.networks import DrivingNetwork, control_config, state_config

    networks = {
        "control": DrivingNetwork(control_config()),
        "state": DrivingNetwork(state_config()),
    }
    assert column_titles(networks) == [
        "camera", "control: steer [rad]", "control: target speed [m/s]", "state: e_y [m]",
        "state: e_psi [rad]", "state: kappa [1/m]", "GradCAM heat",
    ]  # fmt: skip
    image = np.random.default_rng(0).integers(0, 256, (64, 64, 3), np.uint8)
    sheet = gradcam_sheet(networks, image, np.zeros(3, np.float32), "layer2")
    assert sheet.shape == (TITLE_HEIGHT_PX + 192, 6 * 192 + COLOUR_BAR_WIDTH_PX, 3)
    bar = sheet[TITLE_HEIGHT_PX:, 6 * 192 :].astype(int)
    top, bottom = bar[12, 12], bar[-12, 12]
    assert top[0] > top[2] + 50 and bottom[2] > bottom[0] + 50  # red at 1, blue at 0


def test_reckless_paths_of_a_long_circuit_are_drawn_large(tmp_path: Path):
    import cv2

    from saferace.experiments.safety_table import PANEL_MAX_IN, panel_inches, plot_reckless_paths

    circuit = write_random_track(tmp_path / "circuit.csv", 11, radius_m=60.0)
    small, large = panel_inches(Track.load("lab")), panel_inches(Track.load(circuit))
    assert max(large) == pytest.approx(PANEL_MAX_IN) and max(large) > 2 * max(small)
    sizes = {}
    for track in ("lab", str(circuit)):
        rows = [
            {**fake_row(0, safety, track, lap_s=None), "agent": agent}
            for agent in ("drift", "weave", "speeding")
            for safety in (FilterConfig(), FilterConfig(kind="cbf"))
        ]
        path = tmp_path / f"{Path(track).stem}.png"
        plot_reckless_paths(rows, path)
        sizes[track] = cv2.imread(str(path)).shape[:2]
    assert max(sizes[str(circuit)]) > 1.8 * max(sizes["lab"])


def test_a_pipe_inside_a_cell_keeps_the_tables_columns():
    from saferace.eval.tables import markdown_table

    table = markdown_table(["max |u diff|", "n"], [["a|b", 1]])
    for line in table.splitlines():
        assert len(re.split(r"(?<!\\)\|", line)) == 4, line  # 2 cells between 3 pipes
