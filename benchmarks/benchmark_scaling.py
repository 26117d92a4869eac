"""Wall time of ``saferace benchmark``'s runs serial, over 2 worker processes, and on Ray.

Runs are independent episodes, so they should scale with the cores until there are fewer
runs than cores; each worker pays its start-up (importing PyTorch and MuJoCo, about 2 s)
once, and a local Ray instance about 5 s to start. Expected on this 2-core machine: close
to 2x for 2 workers (the parent only collects rows), somewhat less on Ray. Rows must be
identical in all three (the script checks it).

    python benchmarks/benchmark_scaling.py [--agent pure-pursuit] [--tracks NAME ...]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from saferace.eval.tables import markdown_table
from saferace.experiments.benchmark import load_suite, run_benchmark


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agent", default="pure-pursuit")
    parser.add_argument("--tracks", nargs="+", help="a subset of the suite's tracks (all)")
    args = parser.parse_args()
    runs = [spec for spec in load_suite().runs() if spec.track in (args.tracks or [spec.track])]
    ways = {"serial": {}, "2 workers": {"workers": 2}, "Ray (local)": {"ray_address": "local"}}
    rows, results = [], {}
    with tempfile.TemporaryDirectory() as folder:
        for label, options in ways.items():
            started = time.perf_counter()
            out = Path(folder) / f"{label.split()[0]}.json"
            results[label] = run_benchmark(args.agent, out, progress=False, runs=runs, **options)
            rows.append([label, len(runs), time.perf_counter() - started])
    serial = rows[0][2]
    table = [[*row, f"{serial / row[2]:.2f}x"] for row in rows]
    print(markdown_table(["how", "runs", "wall [s]", "speed-up"], table))
    same = all(result["rows"] == results["serial"]["rows"] for result in results.values())
    print(f"rows identical serial, 2 workers and Ray: {same}")


if __name__ == "__main__":
    main()
