"""Drive a lap with the pure-pursuit driver, writing a video and a Rerun recording."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
from tqdm import tqdm

from saferace.agents.pure_pursuit import PurePursuit
from saferace.eval.recording import EpisodeRecording
from saferace.eval.video import VideoWriter, side_by_side
from saferace.track.raceline import center_line, racing_line

TASKS = {"CenterLine": "saferace/CenterLine-v0", "RacingLine": "saferace/RacingLine-v0"}


@dataclass(frozen=True)
class DriveSummary:
    """What happened in one driven episode."""

    task: str
    track: str
    steps: int
    sim_time_s: float
    laps: int
    lap_times_s: list[float]
    time_outside_lane_s: float
    max_abs_deviation_m: float
    terminated: bool


def task_id(task: str) -> str:
    """Gymnasium id of a task given as ``CenterLine``/``RacingLine`` or a full id."""
    if task in TASKS.values():
        return task
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}: use one of {', '.join(TASKS)}")
    return TASKS[task]


def drive(
    task: str,
    track: str,
    laps: int = 1,
    video: str | Path | None = None,
    rerun: str | Path | None = None,
    seed: int = 0,
    **env_kwargs,
) -> DriveSummary:
    """Let pure pursuit drive ``laps`` laps; optionally record an MP4 and a Rerun ``.rrd``."""
    render_mode = "rgb_array" if video else None
    env = gym.make(task_id(task), track=track, max_laps=laps, render_mode=render_mode, **env_kwargs)
    base = env.unwrapped
    agent = PurePursuit.for_env(env)
    writer = VideoWriter(video, fps=base.metadata["render_fps"]) if video else None
    recording = None
    if rerun:
        lines = [center_line(base.track), racing_line(base.track)]
        recording = EpisodeRecording(rerun, base.track, lines, stereo=base.stereo)
    observation, info = env.reset(seed=seed)
    outside_steps, max_deviation, steps = 0, 0.0, 0
    terminated = truncated = False
    try:
        with tqdm(
            total=base.max_steps, desc=f"{task} on {base.track.name}", unit="step", disable=None
        ) as bar:
            while not (terminated or truncated):
                action = agent.act(observation, info)
                observation, _, terminated, truncated, info = env.step(action)
                steps += 1
                outside_steps += info["cost"] > 0
                max_deviation = max(max_deviation, abs(info["deviation_m"]))
                if writer:
                    writer.write(side_by_side(observation["image"], env.render()))
                if recording:
                    recording.log_step(observation, info, action)
                bar.update()
                bar.set_postfix(lap=info["lap"], v=f"{info['v_x_mps']:.1f}m/s")
    finally:
        if writer:
            writer.close()
        if recording:
            recording.close()
        env.close()
    return DriveSummary(
        task=task,
        track=base.track.name,
        steps=steps,
        sim_time_s=info["time_s"],
        laps=info["lap"],
        lap_times_s=list(info["lap_times_s"]),
        time_outside_lane_s=outside_steps * base.control_dt_s,
        max_abs_deviation_m=max_deviation,
        terminated=terminated,
    )


def snapshots(out_dir: str | Path, tracks: list[str], image_size: int = 64) -> list[Path]:
    """Onboard (mono and stereo) and chase-view PNGs at the start of each track."""
    import cv2

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in tracks:
        for stereo in (False, True):
            env = gym.make(
                TASKS["RacingLine"],
                track=name,
                stereo=stereo,
                image_size=(image_size, image_size),
                render_mode="rgb_array",
            )
            observation, _ = env.reset(seed=0)
            frame = side_by_side(observation["image"], env.render())
            path = out_dir / f"{name}_{'stereo' if stereo else 'mono'}.png"
            cv2.imwrite(str(path), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            written.append(path)
            env.close()
    return written


def format_lap_times(lap_times_s: list[float]) -> str:
    """Lap times for a table cell."""
    return ", ".join(f"{t:.2f}" for t in lap_times_s) if lap_times_s else "-"
