"""The runner's worker processes share the cores instead of oversubscribing them."""

from __future__ import annotations

import logging
import os

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
