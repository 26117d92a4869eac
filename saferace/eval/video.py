"""MP4 videos of episodes: the onboard camera beside the chase view."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


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


class VideoWriter:
    """Writes RGB frames to an MP4 file (OpenCV, ``mp4v``); the size is set by the first frame."""

    def __init__(self, path: str | Path, fps: float) -> None:
        self.path = Path(path)
        self.fps = fps
        self._writer: cv2.VideoWriter | None = None
        self.frames = 0

    def write(self, frame_rgb: np.ndarray) -> None:
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            height, width = frame_rgb.shape[:2]
            self._writer = cv2.VideoWriter(
                str(self.path), cv2.VideoWriter.fourcc(*"mp4v"), self.fps, (width, height)
            )
            if not self._writer.isOpened():
                raise OSError(f"OpenCV cannot write an MP4 video to {self.path}")
        self._writer.write(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
