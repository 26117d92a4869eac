"""A protocol's runs journaled as they end: an interrupted benchmark goes on where it
stopped, over worker processes or Ray, and computes nothing twice."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from saferace.eval.parallel import run_jobs
from saferace.eval.runner import append_jsonl
from saferace.progress import Progress


def journaled_runs(
    journal: Path,
    done: list[dict],
    wanted: list,
    drive: Callable[..., dict],
    job_of: Callable[[Any], tuple],
    keyed: Callable[[dict, Any], dict],
    words: Callable[[dict], str],
    title: str,
    how: tuple[int, str | None, bool],
) -> list[dict]:
    """The rows of the runs ``wanted`` (specs with a ``key``), in their order: those the
    journal's rows ``done`` lack driven as ``drive(*job_of(spec))`` (the spec its job's
    second item), each row ``keyed(row, spec)`` appended to ``journal`` as it arrives; ``how``:
    the workers, the Ray address and whether a progress line shows."""
    workers, ray_address, progress = how
    finished = {row["key"] for row in done}
    missing = [spec for spec in wanted if spec.key not in finished]

    def keep(job: tuple, row: dict) -> None:
        row = keyed(row, job[1])
        append_jsonl(journal, row)
        done.append(row)

    def finished_words(key: str) -> str:
        row = next((row for row in reversed(done) if row["key"] == key), None)
        return "failed" if row is None else words(row)

    with Progress(len(missing), title, "run", enabled=progress) as bar:
        run_jobs(
            drive,
            [job_of(spec) for spec in missing],
            keep,
            workers=workers,
            ray_address=ray_address,
            advance=lambda job: bar.done(job[1].key, finished_words(job[1].key)),
            describe=lambda job: job[1].key,
        )
    by_key = {row["key"]: row for row in done}
    return [by_key[spec.key] for spec in wanted]
