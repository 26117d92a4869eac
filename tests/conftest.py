"""Shared fixtures: built-in tracks and a generator of tracks the repository has never seen."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from saferace.names import COMPILE_VARIABLE, DEVICE_VARIABLE
from saferace.track import Track, builtin_track_names
from saferace.track.random_track import write_random_track

# The tests' exact comparisons hold on the CPU; a GPU machine runs them there too.
os.environ[DEVICE_VARIABLE] = "cpu"
# A worker of a parallel run (pytest -n, as `make test` runs) gets a core: PyTorch and
# OpenMP on every core in each worker ran the suite slower than one worker.
if os.environ.get("PYTEST_XDIST_WORKER"):
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[variable] = "1"
# Eager networks: compiling one for the CPU takes 10-20 s (tests/test_cpu_compile.py does).
os.environ[COMPILE_VARIABLE] = "0"
#: The repository the tests run in: none of them may write into it.
REPOSITORY = Path(__file__).resolve().parents[1]
STATUS_BEFORE = pytest.StashKey[str | None]()
#: A file of the honest submission made beforehand, for runs of the tests many times over
#: code that does not make it (``scripts/mutation_run.py`` makes it once and sets this).
PREBUILT_SUBMISSION_VARIABLE = "SAFERACE_TEST_PREBUILT_SUBMISSION"


@pytest.fixture(params=builtin_track_names())
def builtin_track(request: pytest.FixtureRequest) -> Track:
    return Track.load(request.param)


@pytest.fixture(params=[11, 23])
def unseen_track_csv(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    """A CSV track the repository has never seen, clockwise for one seed."""
    return write_random_track(tmp_path / f"unseen_{request.param}.csv", request.param)


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory: pytest.TempPathFactory):
    """A checkpoint trained for one epoch on 3 s of expert driving on ``lab``, mono and stereo,
    conformally calibrated on the same frames (its monitor on the spread), so that the
    robust filter a learned state source gets by default takes it.

    ``tiny_checkpoint(stereo)`` gives ``(checkpoint path, data folder)``; nothing in it
    drives well, but every part of the learned driver runs on it.
    """
    from saferace.learning.collect import collect_round
    from saferace.learning.commands import train_and_report
    from saferace.learning.configs import CollectionConfig, EpisodeSettings, TrainConfig
    from saferace.learning.recalibrate import recalibrate

    made: dict[bool, tuple[Path, Path]] = {}

    def make(stereo: bool = False) -> tuple[Path, Path]:
        if stereo not in made:
            folder = tmp_path_factory.mktemp("stereo" if stereo else "mono")
            config = CollectionConfig(
                task="CenterLine",
                track="lab",
                episode=EpisodeSettings(laps=1, max_seconds=3.0, stereo=stereo),
            )
            collect_round(folder / "data", config, progress=False)
            checkpoint = folder / "tiny.pt"
            settings = TrainConfig(epochs=1, val_stretch=(0.05, 0.08))
            train_and_report([folder / "data"], checkpoint, settings, mc_samples=3, progress=False)
            recalibrate(checkpoint, [folder / "data"], checkpoint, mc_samples=3, monitor="spread")
            made[stereo] = checkpoint, folder / "data"
        return made[stereo]

    return make


@pytest.fixture(scope="session")
def quick_perception(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The generic perception model of the ``quick`` recipe (``--state-source
    generic:quick``), built once (about half a minute) into a cache folder of the session's
    own, never the user's; its model's path."""
    from saferace.cache import CACHE_VARIABLE
    from saferace.learning.perception import RECIPES, build_perception_model

    os.environ[CACHE_VARIABLE] = str(tmp_path_factory.mktemp("cache"))
    return build_perception_model(RECIPES["quick"], progress=False)


@pytest.fixture
def uncalibrated_checkpoint(tiny_checkpoint, tmp_path: Path) -> Path:
    """The mono tiny checkpoint without its conformal calibration."""
    import torch

    from saferace.learning.checkpoint import CONFORMAL_KEY

    payload = torch.load(tiny_checkpoint()[0], weights_only=False)
    del payload["metadata"][CONFORMAL_KEY]
    path = tmp_path / "uncalibrated.pt"
    torch.save(payload, path)
    return path


@pytest.fixture(scope="session")
def honest_submission(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Pure pursuit's submission of the whole benchmark suite, as ``saferace benchmark``
    writes it (about 30 s over two worker processes; its rows are the serial ones). Made
    once per test run: under ``pytest -n`` the workers share it (a worker's session fixture
    is its own, and two workers made it twice, 75-120 s each, in ``make test``)."""
    from filelock import FileLock

    from saferace.experiments.benchmark import run_benchmark

    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent  # this run's, one folder above each worker's own
    path = shared / "honest_benchmark" / "pure_pursuit.json"
    path.parent.mkdir(exist_ok=True)
    with FileLock(str(path.parent / "lock")):
        if not path.is_file():
            prebuilt = os.environ.get(PREBUILT_SUBMISSION_VARIABLE)
            if prebuilt:
                shutil.copyfile(prebuilt, path)
            else:
                run_benchmark("pure-pursuit", path, workers=2, progress=False)
    return path


def repository_status() -> str | None:
    """``git status`` of the repository, untracked files too (None outside a git checkout)."""
    try:
        return subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=all"],
            cwd=REPOSITORY, capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None


def pytest_sessionstart(session: pytest.Session) -> None:
    session.config.stash[STATUS_BEFORE] = repository_status()


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Fail the run where a test wrote into the repository (a stray file left behind)."""
    before, after = session.config.stash.get(STATUS_BEFORE, None), repository_status()
    if before is not None and after is not None and after != before:
        changed = sorted(set(after.splitlines()) - set(before.splitlines()))
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.write_line(
                "the tests wrote into the repository: " + ", ".join(changed), red=True
            )
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
