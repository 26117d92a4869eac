"""Independent runs, serial, over worker processes, or as Ray tasks; results as they end.

The benchmark's and the safety table's runs are independent episodes. :func:`run_jobs`
calls ``function(*job)`` for each job and hands ``keep(job, result)`` each result as it
arrives (in order when serial), so that the caller writes it down at once and a rerun
skips it. Worker processes are spawned (a forked child would share its parent's OpenGL
and PyTorch state). On Ray each job is one task (``ray_address="local"`` starts a Ray
instance on this machine), retried ``RAY_RETRIES`` times. A run that fails is reported
once all others have ended (their results kept), never dropped.

Every worker (process or Ray task) gets its share of the cores for BLAS, OpenMP and
PyTorch threads (:func:`limit_threads`): left alone, each of N workers starts a thread per
core, and their busy-waiting threads fight (2 workers ran the benchmark 6.6x slower than
one process). The serial path keeps its threads.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from multiprocessing import get_context
from typing import Any

from tqdm import tqdm

from saferace.cache import CACHE_VARIABLE
from saferace.errors import SafeRaceError
from saferace.extras import require
from saferace.names import COMPILE_VARIABLE, DEVICE_VARIABLE

LOG = logging.getLogger(__name__)
#: Linux's ``prctl`` option that has the kernel signal a process when its parent ends.
PR_SET_PDEATHSIG = 1

RAY_RETRIES = 2
#: Of a GPU, what each Ray task asks for when the networks run on CUDA: four tasks share one.
RAY_GPU_SHARE = 0.25
#: The command's choices that Ray tasks get as they are: the device, compiling, the cache.
FORWARDED = (DEVICE_VARIABLE, COMPILE_VARIABLE, CACHE_VARIABLE)
#: What BLAS, OpenMP and PyTorch builds read for their thread counts when they load.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

Job = tuple[Any, ...]


def run_jobs(
    function: Callable[..., Any],
    jobs: Sequence[Job],
    keep: Callable[[Job, Any], None],
    workers: int = 1,
    ray_address: str | None = None,
    advance: Callable[[Job], object] = lambda job: None,
    describe: Callable[[Job], str] = str,
) -> None:
    """``keep(job, function(*job))`` for every job; ``advance(job)`` after each, in the
    order they finish (a progress line); ``describe(job)`` names a job in the report of
    failures."""
    if not jobs:
        return
    if ray_address is not None:
        _run_on_ray(function, jobs, keep, ray_address, advance, describe)
    elif workers <= 1:
        for job in jobs:
            keep(job, function(*job))
            advance(job)
    else:
        cores, asked, workers = available_cores(), workers, min(workers, len(jobs))
        if workers > cores:  # more would share the cores and run slower than these
            LOG.warning("%d workers asked for on %d cores: running %d", asked, cores, cores)
            workers = cores
        failures = []
        pool = ProcessPoolExecutor(
            workers,
            mp_context=get_context("spawn"),
            initializer=start_worker,
            initargs=(max(1, cores // workers),),
        )
        try:
            with interrupted_by_sigterm():
                futures = {pool.submit(function, *job): job for job in jobs}
                for future in as_completed(futures):
                    job = futures[future]
                    try:
                        keep(job, future.result())
                    except Exception as error:  # keep the others' results, report it after
                        failures.append(f"{describe(job)}: {type(error).__name__}: {error}")
                    advance(job)
        except BaseException:  # Ctrl-C, SIGTERM: the workers end with the run, at once
            stop_workers(pool)
            raise
        pool.shutdown()
        _raise_failures(failures, "in worker processes")


@contextmanager
def interrupted_by_sigterm() -> Iterator[None]:
    """SIGTERM raises ``KeyboardInterrupt`` in the main thread while this lasts, as Ctrl-C
    does, so that the pool's workers are stopped before the process ends (left alone, it
    ended the run and left its workers to PID 1)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _raise_interrupt(signal_number: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signal_number}")


def stop_workers(pool: ProcessPoolExecutor) -> None:
    """End ``pool`` now: its queued jobs cancelled, its worker processes terminated."""
    processes = list(getattr(pool, "_processes", {}).values())  # the pool's own record
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(timeout=5.0)


def start_worker(threads: int) -> None:
    """A worker process's start: it ends with its parent however that ends (Linux: the
    kernel sends it SIGTERM, even where the parent was killed outright), and it takes
    ``threads`` threads (:func:`limit_threads`). Its progress bars share a thread lock, not
    tqdm's default one across processes: a worker terminated holding that semaphore left it
    to the resource tracker ("2 leaked semaphore objects" after ``benchmark --workers 2``
    was stopped)."""
    tqdm.set_lock(threading.RLock())  # see the docstring
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() == 1:  # the parent ended before the line above ran
            os._exit(1)
    limit_threads(threads)


def available_cores() -> int:
    """The cores this process may run on (its affinity, as in a container), else all."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def limit_threads(threads: int) -> None:
    """Give this worker process ``threads`` BLAS, OpenMP and PyTorch threads: the libraries
    loaded already through threadpoolctl and torch, those loaded later through the
    environment they read when they load."""
    from threadpoolctl import threadpool_limits

    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    threadpool_limits(threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


def _run_on_ray(
    function: Callable[..., Any],
    jobs: Sequence[Job],
    keep: Callable[[Job, Any], None],
    address: str,
    advance: Callable[[Job], object],
    describe: Callable[[Job], str],
) -> None:
    ray = require("ray", "ray", "running jobs as Ray tasks (--ray)")
    if not ray.is_initialized():
        ray.init(
            address=None if address == "local" else address,
            include_dashboard=False,
            log_to_driver=False,
            runtime_env={
                "env_vars": {
                    "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
                    **{name: "1" for name in THREAD_VARIABLES},  # a task has one CPU
                    **{name: os.environ[name] for name in FORWARDED if name in os.environ},
                }
            },
        )
    on_gpu = os.environ.get(DEVICE_VARIABLE, "").startswith("cuda")
    task = ray.remote(
        num_cpus=1,
        num_gpus=RAY_GPU_SHARE if on_gpu else 0,  # Ray hides GPUs from tasks that ask for none
        max_retries=RAY_RETRIES,
        retry_exceptions=True,
    )(function)
    pending = {task.remote(*job): job for job in jobs}
    failures = []
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for reference in ready:
            job = pending.pop(reference)
            try:
                keep(job, ray.get(reference))
            except ray.exceptions.RayError as error:
                failures.append(f"{describe(job)}: {str(error).strip().splitlines()[-1]}")
            advance(job)
    _raise_failures(failures, f"on Ray after {RAY_RETRIES} retries")


def _raise_failures(failures: list[str], where: str) -> None:
    if failures:
        raise SafeRaceError(
            f"{len(failures)} run(s) failed {where} (the rest are kept; run again to retry "
            "them): " + "; ".join(failures)
        )
