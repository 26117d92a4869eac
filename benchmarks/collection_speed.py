"""Collection's frames per second: N episodes one after another, beside N at once.

What ``saferace collect`` does for N seeds, timed whole (building the envs included):
serially (``--num-envs 1``), and with the N episodes driven together
(``--num-envs N``: each env and the expert that labels it in its own process, the drivers
asked in one batched forward pass where they are learned). The frames of the two must be
the same bit for bit (with a learned driver: to float rounding, the batched features
differ from one frame's in the last bits, so the frames are compared only for scripted
drivers). Targets: 8 envs on 2 cores at least 1.5x the serial frames per second; on a
GPU machine, 16 envs at least 1,500 frames per second.

    python benchmarks/collection_speed.py [--num-envs N] [--seconds S] [--track NAME]
        [--agent expert|drift|weave|speeding|learned:CKPT] [--device auto|cpu|cuda]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from saferace.eval.tables import markdown_table
from saferace.learning.collect import collect_episode, collect_episodes_together
from saferace.learning.configs import CollectionConfig, EpisodeSettings
from saferace.learning.device import use_device

TARGET_RATIO = 1.5
TARGET_GPU_FRAMES_PER_S = 1500.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated time per episode")
    parser.add_argument("--track", default="lab")
    parser.add_argument("--agent", default="expert")
    parser.add_argument("--device", default="auto", help="where a learned driver's network runs")
    args = parser.parse_args()
    device = use_device(args.device)
    config = CollectionConfig(
        agent=args.agent,
        task="CenterLine",
        track=args.track,
        seeds=tuple(range(args.num_envs)),
        episode=EpisodeSettings(max_seconds=args.seconds),
    )
    episodes = list(range(args.num_envs))
    started = time.perf_counter()
    serial = [collect_episode(config, episode, config.seeds[episode]) for episode in episodes]
    serial_s = time.perf_counter() - started
    started = time.perf_counter()
    together = collect_episodes_together(config, episodes)
    together_s = time.perf_counter() - started
    frames = sum(len(episode.frames["s_m"]) + len(episode.held_out["s_m"]) for episode in serial)
    same = all(
        np.array_equal(a.frames[name], b.frames[name]) and a.summary == b.summary
        for a, b in zip(serial, together, strict=True)
        for name in a.frames
    )
    rows = [
        ["one after another", serial_s, frames / serial_s, 1.0],
        [f"{args.num_envs} at once (--num-envs)", together_s, frames / together_s,
         serial_s / together_s],
    ]  # fmt: skip
    print(f"{os.cpu_count()} cores, networks on {device}; {args.num_envs} episodes of "
          f"{args.seconds:g} s on {args.track}, driver {args.agent}: {frames} frames")  # fmt: skip
    print(markdown_table(["collection", "wall [s]", "frames/s", "x serial"], rows))
    scripted = not args.agent.startswith("learned:")
    print(f"\nframes identical to the serial ones: {same}" + ("" if scripted else " (learned)"))
    ratio = serial_s / together_s
    print(f"{args.num_envs} envs: {ratio:.2f}x the serial frames/s "
          f"({'meets' if ratio >= TARGET_RATIO else 'misses'} {TARGET_RATIO}x)")  # fmt: skip
    if device.type == "cuda":
        rate = frames / together_s
        verdict = "meets" if rate >= TARGET_GPU_FRAMES_PER_S else "misses"
        print(f"{rate:.0f} frames/s, {verdict} {TARGET_GPU_FRAMES_PER_S:.0f} on a GPU machine")


if __name__ == "__main__":
    main()
