"""Progress reaches a log as one line per finished unit, with its key number and the time
left; a terminal gets a bar instead; ``-v`` adds what a unit is doing."""

from __future__ import annotations

import io
import logging

import pytest

from saferace import progress
from saferace.progress import Progress, duration_words


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class Clock:
    """``time.monotonic`` that moves only when told."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    clock = Clock()
    monkeypatch.setattr(progress.time, "monotonic", clock)
    return clock


def test_a_log_gets_a_line_per_finished_unit_with_its_result_and_the_time_left(clock: Clock):
    log = io.StringIO()
    with Progress(4, "benchmark expert", "run", stream=log) as bar:
        clock.now += 2.0
        bar.done("lab/CenterLine/0/none", "score 98.1")
        clock.now += 4.0
        bar.update()  # counted, no line of its own
        clock.now += 1.5
        bar.done("lab/CenterLine/0/cbf")
        bar.done("lab/RacingLine/0/none")
    assert log.getvalue().splitlines() == [
        "benchmark expert: lab/CenterLine/0/none done (1/4 runs) in 2.0 s, score 98.1; "
        "about 6.0 s left",  # 2 s a run, 3 runs to go
        "benchmark expert: lab/CenterLine/0/cbf done (3/4 runs) in 5.5 s; about 2.5 s left",
        "benchmark expert: lab/RacingLine/0/none done (4/4 runs) in 0.0 s",  # none left
    ]


def test_a_resumed_job_counts_its_pace_from_the_units_it_did_itself(clock: Clock):
    log = io.StringIO()
    bar = Progress(10, "dagger", "iteration", stream=log, initial=8)
    assert bar.seconds_left() is None  # no pace yet: no guess
    clock.now += 30.0
    bar.done("iteration 8")
    bar.report("iteration 9 trained", "loss 0.1", time_left=False)
    assert log.getvalue().splitlines() == [
        "dagger: iteration 8 done (9/10 iterations) in 30 s; about 30 s left",
        "dagger: iteration 9 trained done (9/10 iterations) in 0.0 s, loss 0.1",
    ]


def test_a_terminal_gets_the_bar_and_no_log_lines_and_disabled_progress_nothing(clock: Clock):
    terminal, silent = Terminal(), io.StringIO()
    with Progress(2, "verify", "run", stream=terminal) as bar:
        bar.done("lab/CenterLine/0/none", "score 98.1")
        bar.show("v=2.0m/s")
    assert "verify:" in terminal.getvalue() and "done (" not in terminal.getvalue()
    assert "v=2.0m/s" in terminal.getvalue()
    with Progress(2, "verify", "run", stream=silent, enabled=False) as bar:
        bar.done("lab/CenterLine/0/none")
        bar.note("driving")
    assert silent.getvalue() == ""


def test_what_a_unit_is_doing_is_logged_at_info_for_verbose_runs(
    clock: Clock, caplog: pytest.LogCaptureFixture
):
    with caplog.at_level(logging.INFO, logger="saferace"):
        Progress(3, "dagger lab", "iteration", stream=io.StringIO()).note("iteration 1: training")
    assert caplog.messages == ["dagger lab: iteration 1: training"]


@pytest.mark.parametrize(
    ("seconds", "words"),
    [(0.25, "0.2 s"), (9.96, "10.0 s"), (42.4, "42 s"), (185.0, "3 min 05 s"),
     (3725.0, "1 h 02 min"), (-1.0, "0.0 s")],
)  # fmt: skip
def test_durations_in_words(seconds: float, words: str):
    assert duration_words(seconds) == words


def test_units_are_counted_in_their_plural():
    log = io.StringIO()
    Progress(12, "train state", "batch", stream=log).done("epoch 1/3")
    assert "(1/12 batches)" in log.getvalue()
