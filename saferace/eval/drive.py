"""Drive laps with a built-in driver, writing a video and a Rerun recording."""

from __future__ import annotations

from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np

from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig
from saferace.eval.recording import EpisodeRecording
from saferace.eval.runner import EpisodeResult, make_task_env, run_episode, task_id
from saferace.eval.video import VideoWriter, side_by_side
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
    base = env.unwrapped
    writer = VideoWriter(video, fps=base.metadata["render_fps"]) if video else None
    recording = None
    if rerun:
        recording = EpisodeRecording(
            rerun,
            base.track,
            [center_line(base.track), racing_line(base.track)],
            stereo=base.stereo,
        )

    def on_step(observation, info, action) -> None:
        if writer:
            writer.write(side_by_side(observation["image"], env.render()))
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


def snapshots(out_dir: str | Path, tracks: list[str], image_size: int = 64) -> list[Path]:
    """Onboard (mono and stereo) and chase-view PNGs at the start of each track."""
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
            frame = side_by_side(observation["image"], env.render())
            path = out_dir / f"{Path(name).stem}_{'stereo' if stereo else 'mono'}.png"
            cv2.imwrite(str(path), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            written.append(path)
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
    the onboard view (scaled up) beside the chase view, the seed written on each row."""
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
        rows = []
        for seed in seeds:
            observation, _ = env.reset(seed=seed)
            row = side_by_side(observation["image"], env.render())
            cv2.putText(row, f"seed {seed}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 0))
            rows.append(row)
        env.close()
        path = out_dir / f"{Path(name).stem}_{randomize}_looks.png"
        cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
        written.append(path)
    return written
