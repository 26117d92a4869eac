"""Videos of episodes, the onboard camera beside the chase view, in a format browsers play:
H.264 in MP4 where an encoder is at hand, else VP8 in WebM."""

from __future__ import annotations

import logging
from functools import cache
from pathlib import Path

import cv2
import numpy as np

from saferace.errors import SafeRaceError
from saferace.names import VIDEO_SUFFIXES

LOG = logging.getLogger(__name__)


def onboard_panel(image: np.ndarray, height: int) -> np.ndarray:
    """The onboard image (3 or 6 channels) scaled to ``height``; stereo pairs stacked."""
    views = [image[..., i : i + 3] for i in range(0, image.shape[-1], 3)]
    panel_height = height // len(views)
    scaled = [
        cv2.resize(
            v,
            (panel_height * v.shape[1] // v.shape[0], panel_height),
            interpolation=cv2.INTER_NEAREST,
        )
        for v in views
    ]
    panel = np.concatenate(scaled, axis=0)
    if panel.shape[0] < height:
        panel = np.pad(panel, ((0, height - panel.shape[0]), (0, 0), (0, 0)))
    return panel


def side_by_side(onboard: np.ndarray, chase: np.ndarray) -> np.ndarray:
    """One RGB frame: onboard camera (scaled up, pixels kept sharp) left, chase view right."""
    return np.concatenate([onboard_panel(onboard, chase.shape[0]), chase], axis=1)


#: The container and codec each video file ending gets: H.264 in MP4 needs PyAV (the
#: ``video`` extra, whose FFmpeg has libx264); VP8 in WebM is what OpenCV's own FFmpeg
#: writes that a browser plays too.
H264_SUFFIX, WEBM_SUFFIX = VIDEO_SUFFIXES


@cache
def h264_encoder() -> str | None:
    """The name of an H.264 encoder PyAV offers here, or None (no PyAV, or none built in)."""
    try:
        import av
    except ImportError:
        return None
    return next((name for name in ("libx264", "h264") if name in av.codecs_available), None)


def video_path(path: str | Path) -> Path:
    """Where a video asked for at ``path`` is written: ``path`` itself, except an MP4 where
    no H.264 encoder is at hand, which becomes the WebM beside it (browsers play both; the
    MPEG-4 Part 2 OpenCV writes in MP4 they do not)."""
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise SafeRaceError(
            f"{path}: a video is written as {' or '.join(VIDEO_SUFFIXES)} (H.264 or VP8), "
            f"not {path.suffix or 'a file without an ending'}"
        )
    if path.suffix.lower() == H264_SUFFIX and h264_encoder() is None:
        return path.with_suffix(WEBM_SUFFIX)
    return path


class VideoWriter:
    """Writes RGB frames to a video browsers play (see :func:`video_path`: ``path`` is
    where it was asked for, ``self.path`` where it goes); the size is set by the first
    frame."""

    def __init__(self, path: str | Path, fps: float) -> None:
        self.path = video_path(path)
        if self.path != Path(path):
            LOG.warning(
                "no H.264 encoder here (pip install 'saferace[video]' brings one): writing "
                "%s as WebM instead",
                self.path,
            )
        self.fps = fps
        self.frames = 0
        self._sink: _H264Sink | _WebmSink | None = None

    def write(self, frame_rgb: np.ndarray) -> None:
        if self._sink is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            sink = _H264Sink if self.path.suffix.lower() == H264_SUFFIX else _WebmSink
            self._sink = sink(self.path, self.fps, *frame_rgb.shape[:2])
        self._sink.write(frame_rgb)
        self.frames += 1

    def close(self) -> None:
        if self._sink is not None:
            self._sink.close()
            self._sink = None


class _H264Sink:
    """H.264 (yuv420p) in MP4 through PyAV."""

    def __init__(self, path: Path, fps: float, height: int, width: int) -> None:
        import av

        encoder = h264_encoder()
        assert encoder is not None  # video_path chose an MP4
        self._frame = av.VideoFrame.from_ndarray
        # the index (moov) before the frames: a browser plays it while it downloads
        self._container = av.open(str(path), "w", options={"movflags": "faststart"})
        stream = self._container.add_stream(encoder, rate=round(fps))
        assert isinstance(stream, av.VideoStream)
        stream.height, stream.width = height - height % 2, width - width % 2
        stream.pix_fmt = "yuv420p"  # what browsers decode
        self._stream = stream

    def write(self, frame_rgb: np.ndarray) -> None:
        for packet in self._stream.encode(self._frame(_even(frame_rgb), format="rgb24")):
            self._container.mux(packet)

    def close(self) -> None:
        for packet in self._stream.encode():  # what the encoder still holds
            self._container.mux(packet)
        self._container.close()


class _WebmSink:
    """VP8 in WebM through OpenCV's own FFmpeg."""

    def __init__(self, path: Path, fps: float, height: int, width: int) -> None:
        self._writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter.fourcc(*"VP80"), fps, (width, height)
        )
        if not self._writer.isOpened():
            raise OSError(f"OpenCV cannot write a WebM video to {path}")

    def write(self, frame_rgb: np.ndarray) -> None:
        self._writer.write(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        self._writer.release()


def _even(frame: np.ndarray) -> np.ndarray:
    """``frame`` cropped to even sides (4:2:0 chroma halves both)."""
    return frame[: frame.shape[0] - frame.shape[0] % 2, : frame.shape[1] - frame.shape[1] % 2]
