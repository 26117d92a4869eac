"""``saferace drive`` and ``saferace snapshots`` write what they promise."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_helpers import run_cli
from rerun.chunk import RrdReader

from saferace.eval.drive import CAPTION_HEIGHT_PX
from saferace.eval.leaderboard import COLUMNS


def test_drive_writes_video_and_rerun_recording(tmp_path: Path):
    video, recording = tmp_path / "lap.mp4", tmp_path / "lap.rrd"
    result = run_cli(
        "drive",
        "--task",
        "CenterLine",
        "--track",
        "lab",
        "--video",
        str(video),
        "--rerun",
        str(recording),
    )
    assert result.returncode == 0, result.stderr
    row = next(line for line in result.stdout.splitlines() if "CenterLine" in line)
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[:7] == [
        "pure-pursuit",
        "CenterLine",
        "lab",
        "none",
        "none",
        "1",
        "1",
    ]  # agent, task, track, filter, state source, seeds, laps
    assert float(cells[COLUMNS.index("outside lane [s]")]) == 0.0  # never outside the lane
    assert f"video written to {video}" in result.stdout
    capture = cv2.VideoCapture(str(video))
    frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, frame = capture.read()
    assert ok and frames > 100
    assert int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") == b"h264"  # browsers
    assert frame.shape == (
        240,
        240 + 320,
        3,
    )  # onboard scaled to the chase view's height, beside it
    entities = {str(path) for path in RrdReader(recording).store().schema().entity_paths()}
    for entity in (
        "/camera/onboard",
        "/map/lane_boundaries",
        "/map/racing_line",
        "/map/car",
        "/plots/speed_mps",
        "/plots/steer_rad",
        "/plots/e_y_m",
        "/map/driven_path",
    ):
        assert entity in entities


def test_snapshots_of_every_track(tmp_path: Path):
    result = run_cli("snapshots", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == [
        f"{t}_{k}.png" for t in ("lab", "oval", "technical", "varying") for k in ("mono", "stereo")
    ]
    image = cv2.imread(str(tmp_path / "lab_stereo.png"))
    assert image.shape == (CAPTION_HEIGHT_PX + 240, 120 + 320, 3)  # captions, then the views
    band, views = image[:CAPTION_HEIGHT_PX], image[CAPTION_HEIGHT_PX:]
    assert (band[:, :120].max(axis=2) < 128).sum() > 20  # "onboard" written over the pair
    assert (band[:, 120:].max(axis=2) < 128).sum() > 20  # "chase" over the chase view
    top, bottom = views[:120, :120], views[120:, :120]
    assert np.abs(top.astype(int) - bottom.astype(int)).mean() > 1.0  # two different cameras


def test_snapshots_of_a_randomisation_preset_make_a_contact_sheet(tmp_path: Path):
    result = run_cli(
        "snapshots", "--randomize", "strong", "--seeds", "0", "1", "--tracks", "lab",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    sheet = cv2.imread(str(tmp_path / "lab_strong_looks.png"))
    assert sheet.shape[0] == CAPTION_HEIGHT_PX + 2 * 240  # captions, a row per seed
    band = sheet[:CAPTION_HEIGHT_PX]
    assert (band.max(axis=2) < 128).sum() > 40  # the views' names on a white band
    rows = sheet[CAPTION_HEIGHT_PX:]
    first, second = rows[:240].astype(int), rows[240:].astype(int)
    assert np.abs(first - second).mean() > 5.0  # two different looks
    refused = run_cli("snapshots", "--randomize", "wild", "--out", str(tmp_path))
    assert refused.returncode != 0 and "unknown VisualRandomization preset 'wild'" in refused.stderr


@pytest.mark.slow  # 15-30 s: the default suite stays within 15 min on 2 cores
def test_drive_in_traffic_records_the_opponents_collisions_and_car_barriers(tmp_path: Path):
    recordings = {}
    for filtered in (False, True):
        recordings[filtered] = tmp_path / f"traffic_{filtered}.rrd"
        result = run_cli(
            "drive", "--track", "technical", "--agent", "pure-pursuit",
            "--opponents", "pure-pursuit:gap_m=6,speed_factor=0.3,lateral_offset_m=0",
            "--rerun", str(recordings[filtered]), *(["--filter", "cbf"] if filtered else []),
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
    unfiltered, filtered = (
        {str(path) for path in RrdReader(recordings[f]).store().schema().entity_paths()}
        for f in (False, True)
    )
    assert {"/map/opponents", "/events/collisions"} <= unfiltered  # ran into the slow car
    assert "/map/opponents" in filtered and "/filter/barriers/car1" in filtered
    assert "/events/collisions" not in filtered
