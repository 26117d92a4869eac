"""Videos are written in a format browsers play, and decode back to what was written: H.264
in MP4 with PyAV's encoder, VP8 in WebM where there is none."""

from __future__ import annotations

import logging
from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from saferace.errors import SafeRaceError
from saferace.eval import video as video_module
from saferace.eval.video import VideoWriter, h264_encoder, video_path

FRAMES = 30
HEIGHT, WIDTH = 65, 97  # odd sides: 4:2:0 chroma needs even ones


def frame(index: int) -> np.ndarray:
    """A flat colour per frame, its red rising: what survives lossy coding."""
    image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    image[..., 0] = 8 * index
    image[..., 2] = 200
    return image


def write(path: Path) -> VideoWriter:
    writer = VideoWriter(path, fps=20.0)
    for index in range(FRAMES):
        writer.write(frame(index))
    writer.close()
    return writer


def test_an_mp4_is_h264_in_yuv420_and_decodes_to_the_frames_written(tmp_path: Path):
    assert h264_encoder() is not None  # the video extra, which make setup installs
    writer = write(tmp_path / "lap.mp4")
    assert writer.path == tmp_path / "lap.mp4" and writer.frames == FRAMES
    with av.open(str(writer.path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    assert len(decoded) == FRAMES
    assert decoded[0].shape == (HEIGHT - 1, WIDTH - 1, 3)
    reds = [float(image[..., 0].mean()) for image in decoded]
    np.testing.assert_allclose(reds, [8 * index for index in range(FRAMES)], atol=4.0)
    assert all(abs(float(image[..., 2].mean()) - 200.0) < 4.0 for image in decoded)
    content = writer.path.read_bytes()  # the index before the frames: progressive playback
    assert 0 < content.find(b"moov") < content.find(b"mdat")


def test_without_an_h264_encoder_an_mp4_becomes_a_webm_that_decodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
):
    monkeypatch.setattr(video_module, "h264_encoder", lambda: None)
    with caplog.at_level(logging.WARNING):
        writer = write(tmp_path / "lap.mp4")
    assert writer.path == tmp_path / "lap.webm" and not (tmp_path / "lap.mp4").exists()
    assert "saferace[video]" in caplog.text and "lap.webm" in caplog.text
    capture = cv2.VideoCapture(str(writer.path))
    fourcc = int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode()
    decoded = []
    while (read := capture.read())[0]:
        decoded.append(cv2.cvtColor(read[1], cv2.COLOR_BGR2RGB))
    assert fourcc == "VP80" and len(decoded) == FRAMES
    reds = [float(image[..., 0].mean()) for image in decoded]
    np.testing.assert_allclose(reds, [8 * index for index in range(FRAMES)], atol=6.0)


def test_a_video_path_with_another_ending_is_refused_in_one_line(tmp_path: Path):
    assert video_path(tmp_path / "lap.webm") == tmp_path / "lap.webm"
    with pytest.raises(SafeRaceError, match=r"lap\.avi: a video is written as \.mp4 or \.webm"):
        video_path(tmp_path / "lap.avi")
