"""Wall time of ``saferace benchmark``'s runs serial, over worker processes, and on Ray.

Runs are independent episodes, so they should scale with the cores until there are fewer
runs than cores; each worker pays its start-up (importing PyTorch and MuJoCo, about 2 s)
once, and a local Ray instance about 5 s to start. The runner gives each worker its share
of the cores for BLAS, OpenMP and PyTorch threads (``saferace.eval.parallel``), with no
environment variable set by hand. Targets on this 2-core machine: 2 workers at least 1.6x
faster than serial, Ray at least 1.3x. Rows must be identical in all three (the script
checks it).

    python benchmarks/benchmark_scaling.py [--agents expert pure-pursuit] [--tracks NAME ...]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from saferace.eval.parallel import available_cores
from saferace.eval.tables import markdown_table
from saferace.experiments.benchmark import load_suite, run_benchmark


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", nargs="+", default=["expert", "pure-pursuit"])
    parser.add_argument("--tracks", nargs="+", help="a subset of the suite's tracks (all)")
    args = parser.parse_args()
    runs = [spec for spec in load_suite().runs() if spec.track in (args.tracks or [spec.track])]
    cores = available_cores()
    ways = {
        "serial": {},
        f"{cores} workers": {"workers": cores},
        "Ray (local)": {"ray_address": "local"},
    }
    table = []
    with tempfile.TemporaryDirectory() as folder:
        for agent in args.agents:
            results, seconds = {}, {}
            for label, options in ways.items():
                started = time.perf_counter()
                out = Path(folder) / f"{agent}_{label.split()[0]}.json"
                results[label] = run_benchmark(agent, out, progress=False, runs=runs, **options)
                seconds[label] = time.perf_counter() - started
            same = all(result["rows"] == results["serial"]["rows"] for result in results.values())
            table += [
                [agent, label, len(runs), wall, f"{seconds['serial'] / wall:.2f}x", same]
                for label, wall in seconds.items()
            ]
    print(f"{cores} cores")
    print(
        markdown_table(
            ["agent", "how", "runs", "wall [s]", "speed-up", "rows identical to serial"], table
        )
    )


if __name__ == "__main__":
    main()
