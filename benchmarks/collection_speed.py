"""Collection's frames per second: N episodes one after another, beside N at once.

What ``saferace collect`` does for N seeds, timed whole (building the envs included): with
the N episodes driven together (``--num-envs N``: a learned driver's in lockstep, the envs
and the experts that label them in as many workers as cores, the drivers asked in one
batched forward pass; the expert's and scripted drivers' each driven through in a worker),
then serially (``--num-envs 1``; second, since a process that has rendered cannot fork
its workers and they would start from a server). The frames of the two must be the same
bit for bit (with a learned driver: to float rounding, the batched features differ from
one frame's in the last bits). Targets: 8 envs on 2 cores at least 1.5x the serial frames
per second; on a GPU machine, 16 envs at least 1,500 frames per second.

    python benchmarks/collection_speed.py [--num-envs N] [--seconds S] [--laps L]
        [--track NAME] [--agent expert|drift|weave|speeding|learned:CKPT] [--device D]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace

import numpy as np

from saferace.eval.tables import markdown_table
from saferace.learning.collect import collect_episode, collect_episodes_together
from saferace.learning.configs import CollectionConfig, EpisodeSettings

TARGET_RATIO = 1.5
TARGET_GPU_FRAMES_PER_S = 1500.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=30.0, help="simulated time per episode")
    parser.add_argument("--laps", type=int, default=5, help="laps per episode, at most")
    parser.add_argument("--track", default="lab")
    parser.add_argument("--agent", default="expert")
    parser.add_argument("--device", default="auto", help="where a learned driver's network runs")
    args = parser.parse_args()
    learned = args.agent.startswith("learned:")
    if learned:  # PyTorch only where a network drives (its workers then fork from a server)
        from saferace.learning.device import use_device

        print(f"networks on {use_device(args.device)}")
    config = CollectionConfig(
        agent=args.agent,
        task="CenterLine",
        track=args.track,
        seeds=tuple(range(args.num_envs)),
        episode=EpisodeSettings(laps=args.laps, max_seconds=args.seconds),
    )
    episodes = list(range(args.num_envs))
    if learned:  # its network compiles for this CPU at its first frame (once): not timed
        collect_episode(replace(config, episode=replace(config.episode, max_seconds=0.1)), 0, 0)
    started = time.perf_counter()
    together = collect_episodes_together(config, episodes)
    together_s = time.perf_counter() - started
    started = time.perf_counter()
    serial = [collect_episode(config, episode, config.seeds[episode]) for episode in episodes]
    serial_s = time.perf_counter() - started
    frames = sum(len(episode.frames["s_m"]) + len(episode.held_out["s_m"]) for episode in serial)
    same = all(
        np.array_equal(a.frames[name], b.frames[name]) and a.summary == b.summary
        for a, b in zip(serial, together, strict=True)
        for name in a.frames
    )
    ratio = serial_s / together_s
    rows = [
        ["one after another", serial_s, frames / serial_s, 1.0],
        [f"{args.num_envs} at once (--num-envs)", together_s, frames / together_s, ratio],
    ]
    print(f"{os.cpu_count()} cores; {args.num_envs} episodes of at most {args.seconds:g} s on "
          f"{args.track}, driver {args.agent}: {frames} frames")  # fmt: skip
    print(markdown_table(["collection", "wall [s]", "frames/s", "x serial"], rows))
    print(f"\nframes identical to the serial ones: {same}" + (" (learned)" if learned else ""))
    print(f"{args.num_envs} envs: {ratio:.2f}x the serial frames/s "
          f"({'meets' if ratio >= TARGET_RATIO else 'misses'} {TARGET_RATIO}x)")  # fmt: skip
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        rate = frames / together_s
        verdict = "meets" if rate >= TARGET_GPU_FRAMES_PER_S else "misses"
        print(f"{rate:.0f} frames/s, {verdict} {TARGET_GPU_FRAMES_PER_S:.0f} on a GPU machine")


if __name__ == "__main__":
    main()
