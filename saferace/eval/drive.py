"""Drive laps with a built-in driver, writing a video and a Rerun recording."""

from __future__ import annotations

from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np

from saferace.envs.unwrap import racing_env
from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig
from saferace.eval.runner import EpisodeResult, make_task_env, run_episode, task_id
from saferace.eval.video import VideoWriter, onboard_panel, side_by_side
from saferace.track.raceline import center_line, racing_line


def drive(
    task: str,
    track: str,
    agent: str = "pure-pursuit",
    laps: int = 1,
    video: str | Path | None = None,
    rerun: str | Path | None = None,
    seed: int = 0,
    mc_samples: int = 10,
    safety: FilterConfig | None = None,
    progress: bool = True,
    **env_kwargs,
) -> EpisodeResult:
    """Let ``agent`` drive ``laps`` laps; optionally record an MP4 and a Rerun ``.rrd``.

    ``mc_samples``: MC-dropout samples per step of a learned agent; ``safety``: the filter
    between the agent and the car (none by default).
    """
    env = make_task_env(
        task,
        track,
        laps,
        safety or FilterConfig(),
        seed,
        render_mode="rgb_array" if video else None,
        **env_kwargs,
    )
    base = racing_env(env)
    writer = VideoWriter(video, fps=base.metadata["render_fps"]) if video else None
    recording = None
    if rerun:
        from saferace.eval.recording import EpisodeRecording  # rerun-sdk only when recording

        recording = EpisodeRecording(
            rerun,
            base.track,
            [center_line(base.track), racing_line(base.track)],
            stereo=base.stereo,
        )

    def on_step(observation, info, action) -> None:
        if writer:
            writer.write(side_by_side(observation["image"], chase_view(env)))
        if recording:
            recording.log_step(observation, info, action)

    try:
        driver = make_agent(agent, env, mc_samples=mc_samples, seed=seed)
        return run_episode(env, driver, seed=seed, progress=progress, on_step=on_step)
    finally:
        if writer:
            writer.close()
        if recording:
            recording.close()
        env.close()


#: Height of the white band above a snapshot that names its views, in pixels.
CAPTION_HEIGHT_PX = 26
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def chase_view(env: gym.Env) -> np.ndarray:
    """The chase view of an env made with ``render_mode="rgb_array"``."""
    frame = env.render()
    assert isinstance(frame, np.ndarray), "make the env with render_mode='rgb_array'"
    return frame


def captioned_views(onboard: np.ndarray, chase: np.ndarray) -> np.ndarray:
    """The onboard image (scaled up; a stereo pair stacked, each view labelled ``left`` or
    ``right``) beside the chase view, under a band that names them: ``onboard`` and
    ``chase``."""
    panel = onboard_panel(onboard, chase.shape[0]).copy()
    views = onboard.shape[-1] // 3
    if views == 2:
        for number, name in enumerate(("left", "right")):
            _boxed_text(panel, name, (4, number * panel.shape[0] // 2 + 4))
    frame = np.concatenate([panel, chase], axis=1)
    band = np.full((CAPTION_HEIGHT_PX, frame.shape[1], 3), 255, np.uint8)
    size = onboard.shape[0]
    onboard_name = f"onboard {size}x{size}" + (", stereo" if views == 2 else "")
    _centred_text(band, onboard_name, 0, panel.shape[1])
    _centred_text(band, "chase", panel.shape[1], frame.shape[1])
    return np.concatenate([band, frame], axis=0)


def _centred_text(band: np.ndarray, text: str, left: int, right: int) -> None:
    """``text`` in black, centred between columns ``left`` and ``right`` of ``band`` (smaller
    if it would not fit)."""
    scale = 0.55
    (width, _), _ = cv2.getTextSize(text, _FONT, scale, 1)
    scale = min(scale, scale * (right - left - 6) / width)  # shrunk to fit its column
    (width, height), _ = cv2.getTextSize(text, _FONT, scale, 1)
    origin = (left + max((right - left - width) // 2, 2), (band.shape[0] + height) // 2)
    cv2.putText(band, text, origin, _FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


def _boxed_text(image: np.ndarray, text: str, corner: tuple[int, int]) -> None:
    """White ``text`` on a black box whose top left is ``corner``: readable on any image."""
    (width, height), baseline = cv2.getTextSize(text, _FONT, 0.45, 1)
    x, y = corner
    cv2.rectangle(image, (x, y), (x + width + 4, y + height + baseline + 2), (0, 0, 0), -1)
    cv2.putText(image, text, (x + 2, y + height + 1), _FONT, 0.45, (255, 255, 255), 1, cv2.LINE_AA)


def write_rgb(path: Path, image: np.ndarray) -> Path:
    cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    return path


def snapshots(out_dir: str | Path, tracks: list[str], image_size: int = 64) -> list[Path]:
    """Onboard (mono and stereo) and chase-view PNGs at the start of each track, under a
    caption band that names the views (:func:`captioned_views`)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in tracks:
        for stereo in (False, True):
            env = gym.make(
                task_id("RacingLine"),
                track=name,
                stereo=stereo,
                image_size=(image_size, image_size),
                render_mode="rgb_array",
            )
            observation, _ = env.reset(seed=0)
            frame = captioned_views(observation["image"], chase_view(env))
            path = out_dir / f"{Path(name).stem}_{'stereo' if stereo else 'mono'}.png"
            written.append(write_rgb(path, frame))
            env.close()
    return written


def contact_sheets(
    out_dir: str | Path,
    tracks: list[str],
    randomize: str,
    seeds: list[int],
    image_size: int = 64,
) -> list[Path]:
    """One PNG per track of the looks that ``randomize`` draws for ``seeds``: a row per seed,
    the onboard view (scaled up) beside the chase view, the seed written on each row, under
    a caption band that names the views."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in tracks:
        env = gym.make(
            task_id("RacingLine"),
            track=name,
            image_size=(image_size, image_size),
            render_mode="rgb_array",
            randomize=randomize,
        )
        rows: list[np.ndarray] = []
        for seed in seeds:
            observation, _ = env.reset(seed=seed)
            row = captioned_views(observation["image"], chase_view(env))
            if rows:  # one caption band, above the first row
                row = row[CAPTION_HEIGHT_PX:]
            _boxed_text(row, f"seed {seed}", (4, row.shape[0] - 24))
            rows.append(row)
        env.close()
        path = out_dir / f"{Path(name).stem}_{randomize}_looks.png"
        written.append(write_rgb(path, np.concatenate(rows, axis=0)))
    return written
