"""What ``make demo`` wrote under its results folder (files newer than its start, a
dataset's round folders or a folder of many files as one line) and its seconds per stage.

Usage: python scripts/demo_summary.py RESULTS (reads RESULTS/demo_timings.txt).
"""

import os
import sys
from pathlib import Path

results = Path(sys.argv[1])
timings = results / "demo_timings.txt"
lines = [line.split() for line in timings.read_text().splitlines() if line.strip()]
started = float(lines[0][1])  # the first line: "started EPOCH_SECONDS"
stages = lines[1:]


def size(n):
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000


print(f"\nwritten under {results}/:")
for folder, dirs, files in os.walk(results):
    dirs.sort()
    here = Path(folder)
    new = [here / name for name in sorted(files) if (here / name).stat().st_mtime >= started]
    rounds = [name for name in dirs if name.startswith("round_")]
    if here != results and (rounds or len(new) > 8):  # a dataset, or many files: one line
        dirs.clear()
        inside = [Path(f, name) for f, _, names in os.walk(here) for name in names]
        inside = [path for path in inside if path.stat().st_mtime >= started]
        what = f"{len(rounds)} rounds, " if rounds else ""
        total = sum(path.stat().st_size for path in inside)
        print(f"  {here.relative_to(results)}/  {what}{len(inside)} files, {size(total)}")
        continue
    for path in new:
        if path != timings:
            print(f"  {path.relative_to(results)}  {size(path.stat().st_size)}")
print("\nseconds per stage:")
for name, seconds in stages:
    print(f"  {name:<14} {int(seconds):>6}")
print(f"  {'total':<14} {sum(int(seconds) for _, seconds in stages):>6}")
