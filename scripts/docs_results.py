"""Put a command's measured table into the docs, stamped with the commit and the machine.

    python scripts/docs_results.py results/paper/table2.md docs/results/paper/table2.md \\
        --command "saferace paper-tables --preset full"
    python benchmarks/env_speed.py | python scripts/docs_results.py - docs/results/speed/env.md \\
        --command "python benchmarks/env_speed.py"

The results pages include the files under ``docs/results/`` (``--8<--``), so their numbers
come from what the commands wrote, never from prose. The first line of a markdown file is
its stamp (``# `` before it in a CSV file); a stamp already there is replaced.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

STAMP_PREFIX = "**Measured**"
ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    """The short commit of the working tree, marked when it has uncommitted changes (outside
    ``docs/results/``)."""
    try:
        head = _git("rev-parse", "--short", "HEAD")
    except (OSError, subprocess.CalledProcessError):
        return "an unknown commit"
    # results files written a moment ago are no change to what measured them
    dirty = _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":!docs/results")
    return f"commit `{head}`" + (" with uncommitted changes" if dirty else "")


def machine() -> str:
    """Cores and GPU, as the stamps say them: ``2-core CPU, no GPU``."""
    gpus = ""
    if shutil.which("nvidia-smi"):
        try:
            gpus = subprocess.run(
                ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                capture_output=True,
                text=True,
                check=True,
                timeout=30,
            ).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            gpus = ""
    names = gpus.splitlines()
    gpu = ", ".join(f"{names.count(n)}x {n}" for n in sorted(set(names))) or "no GPU"
    return f"{os.cpu_count()}-core CPU, {gpu}"


def stamp(command: str, machine_text: str | None = None) -> str:
    return f"{STAMP_PREFIX} at {commit()}; {machine_text or machine()}; by `{command}`."


def stamped(text: str, line: str, csv: bool) -> str:
    lines = text.splitlines()
    head = f"# {line}" if csv else line
    if lines and lines[0].lstrip("# ").startswith(STAMP_PREFIX):
        lines = lines[1:]
    while lines and not lines[0].strip():
        lines = lines[1:]
    if not csv:
        lines = _tables_apart(lines)
    body = "\n".join(lines)
    return f"{head}\n{body}\n" if csv else f"{head}\n\n{body}\n"


def _tables_apart(lines: list[str]) -> list[str]:
    """``lines`` with a blank line between a markdown table and the text right before or
    after it (a benchmark prints its caption on the line above), so that it renders, and
    between two lines of text, so that each stays a line of its own."""
    out: list[str] = []
    for line in lines:
        in_table, after_table = line.startswith("|"), bool(out) and out[-1].startswith("|")
        if line.strip() and out and out[-1].strip() and not (in_table and after_table):
            out.append("")
        out.append(line)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", help="the file a command wrote, or - for standard input")
    parser.add_argument("dest", type=Path, help="where under docs/results/ it goes")
    parser.add_argument("--command", required=True, help="the command that measured it")
    parser.add_argument("--machine", help="the machine, if not this one ('2-core CPU, no GPU')")
    args = parser.parse_args(argv)

    text = sys.stdin.read() if args.source == "-" else Path(args.source).read_text()
    dest = args.dest if args.dest.is_absolute() else Path.cwd() / args.dest
    if ROOT / "docs" / "results" not in dest.resolve().parents:
        parser.error(f"{args.dest} is not under docs/results/")
    dest.parent.mkdir(parents=True, exist_ok=True)
    line = stamp(args.command, args.machine)
    dest.write_text(stamped(text, line, csv=dest.suffix == ".csv"))
    print(f"{dest}: {line}")
    return 0


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()


if __name__ == "__main__":
    raise SystemExit(main())
