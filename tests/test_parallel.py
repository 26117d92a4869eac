"""The runner's worker processes share the cores instead of oversubscribing them."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from saferace.eval.parallel import available_cores, run_jobs


def thread_counts() -> dict[str, int]:
    """The BLAS and PyTorch thread counts of the calling process, as threadpoolctl sees them."""
    import numpy  # noqa: F401  (loads BLAS)
    import torch
    from threadpoolctl import threadpool_info

    blas = [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]
    return {"blas": max(blas), "torch": torch.get_num_threads()}


def test_workers_on_every_core_see_one_thread_each_and_the_serial_path_keeps_its_own():
    cores = available_cores()
    seen: list[dict[str, int]] = []
    run_jobs(thread_counts, [()] * cores, lambda job, counts: seen.append(counts), workers=cores)
    assert seen == [{"blas": 1, "torch": 1}] * cores
    serial: list[dict[str, int]] = []
    run_jobs(thread_counts, [()], lambda job, counts: serial.append(counts))
    assert serial == [thread_counts()]  # the serial path keeps this process's threads


def test_more_workers_than_cores_are_capped_at_the_cores_in_one_line(
    caplog: pytest.LogCaptureFixture,
):
    cores = available_cores()
    pids: set[int] = set()
    with caplog.at_level(logging.WARNING):
        run_jobs(os.getpid, [()] * 4 * (cores + 1), lambda job, pid: pids.add(pid), cores + 2)
    assert len(pids) <= cores  # no more processes than cores
    assert caplog.messages == [f"{cores + 2} workers asked for on {cores} cores: running {cores}"]


def test_no_jobs_on_several_workers_is_nothing_to_do():
    kept: list = []
    for workers in (1, 2):
        run_jobs(abs, [], lambda job, value: kept.append(value), workers=workers)
    assert kept == []


PARENT = """
import os, signal, sys, time
from tqdm import tqdm
from saferace.eval.parallel import run_jobs

# a command run in the foreground, as a user's Ctrl-C meets it (a suite run in the
# background hands its children SIGINT ignored, and Python then never raises on it)
signal.signal(signal.SIGINT, signal.default_int_handler)

def wait(folder):
    tqdm(disable=True).close()  # a run's progress bar, as every worker's job makes
    open(os.path.join(folder, str(os.getpid())), "w").close()
    time.sleep(60)

if __name__ == "__main__":
    run_jobs(wait, [(sys.argv[1],)] * 6, lambda job, value: None, workers=2)
"""


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as stat:  # a zombie is gone, only not yet reaped
        return stat.read().split(")")[-1].split()[0] != "Z"


@pytest.mark.parametrize("signal_number", [signal.SIGINT, signal.SIGTERM], ids=["int", "term"])
def test_workers_end_with_their_parent_on_sigint_and_sigterm(tmp_path: Path, signal_number: int):
    """The issue's trace: ``benchmark --workers 3`` stopped by SIGINT to its main process
    left its idle workers and the resource tracker to PID 1, with leaked semaphores; and
    workers terminated holding their progress bars' locks left those ("2 leaked semaphore
    objects")."""
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    parent = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path)], stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 60.0
    while len(list(tmp_path.glob("[0-9]*"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    workers = [int(path.name) for path in tmp_path.glob("[0-9]*")]
    assert len(workers) == 2, "both workers started a job"
    parent.send_signal(signal_number)
    _, stderr = parent.communicate(timeout=30)
    assert parent.returncode != 0
    time.sleep(1.0)
    assert not [pid for pid in workers if alive(pid)]
    assert "leaked semaphore" not in stderr
