"""Every command refuses a bad value of any of its checked options where it parses it (a
number out of its range or no number, an input file that is not there, an unknown track):
exit status 2 and one line that names the option, before any work starts."""

from __future__ import annotations

import argparse
import math
import time

import gymnasium as gym
import pytest

from saferace.cli import build_parser, main, values
from saferace.cli.arguments import FAST_MEAN_SPEED_MPS, check_drive_length
from saferace.cli.maxima import MAXIMA, UNCAPPED, uncapped, upper_end
from saferace.cli.values import CheckedNumber
from saferace.track import Track

PARSER = build_parser()
COMMANDS = next(a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction)).choices
#: A value each kind of checked option refuses, besides a negative number for numbers.
BAD_VALUES = {
    "number": "abc",
    "existing": "/no/such/file.json",
    "track": "no_such_track",
    "labelled folder": "ensemble=/no/such/folder",
    "video file": "lap.avi",
}


#: Values that parse for each kind (anything else: this file, which exists).
GOOD_VALUES = {"track": "lab", "labelled folder": "here=.", "video file": "lap.mp4"}


def kind(action: argparse.Action) -> str | None:
    """Which kind of checked value ``action`` takes (None: unchecked or a switch)."""
    if isinstance(action.type, CheckedNumber) or action.type in (int, float):
        return "number"
    if action.type is values.existing:
        return "existing"
    if action.type is values.track:
        return "track"
    if action.type is values.labelled_folder:
        return "labelled folder"
    if action.type is values.video_file:
        return "video file"
    return None


def count(action: argparse.Action) -> int:
    return action.nargs if isinstance(action.nargs, int) else 1


def name(action: argparse.Action) -> str:
    """How argparse names ``action`` in its errors."""
    if action.option_strings:
        return action.option_strings[-1]
    return action.metavar if isinstance(action.metavar, str) else action.dest


def arguments(command: str, tested: argparse.Action, bad: str) -> list[str]:
    """The command's line with ``bad`` for ``tested`` and values that parse for its other
    positionals and required options (no work starts: the bad value is refused first)."""
    given = [bad] * count(tested)
    argv = [command, *tested.option_strings[-1:], *given] if tested.option_strings else [command]
    for action in COMMANDS[command]._actions:
        good = [GOOD_VALUES.get(kind(action), __file__)] * count(action)
        if action is tested and not action.option_strings:
            argv += given
        elif action is not tested and not action.option_strings and action.dest != "help":
            argv += good
        elif action is not tested and action.required:
            argv += [action.option_strings[-1], *good]
    return argv


def too_large(action: argparse.Action) -> tuple[str, ...]:
    """Just past the largest value ``action`` takes (none where it has no largest)."""
    if not isinstance(action.type, CheckedNumber):
        return ()
    end, bounds = upper_end(action.type), action.type.bounds
    if math.isinf(end):
        return ()
    if bounds.below is not None and bounds.below == end:
        return (f"{end:g}",)  # the open end itself
    return (str(int(end) + 1) if action.type.number_type is int else f"{end * 1.5:g}",)


def bad_values(action: argparse.Action, checked: str) -> tuple[str, ...]:
    if checked == "number":
        return ("-1", BAD_VALUES["number"], *too_large(action))
    return (BAD_VALUES[checked],)


CASES = [
    (command, action, bad)
    for command in COMMANDS
    for action in COMMANDS[command]._actions
    if (checked := kind(action)) is not None
    for bad in bad_values(action, checked)
]
NUMBERS = [
    (command, action)
    for command in COMMANDS
    for action in COMMANDS[command]._actions
    if isinstance(action.type, CheckedNumber) and action.option_strings
]


def case_id(case: object) -> str:
    return name(case) if isinstance(case, argparse.Action) else str(case)


def test_the_walk_covers_every_command_and_kind_of_value():
    covered = {(command, kind(action)) for command, action, _ in CASES}
    assert len(CASES) >= 150
    large = [bad for _, _, bad in CASES if bad not in ("-1", BAD_VALUES["number"])]
    assert len([value for value in large if value.replace(".", "").isdigit()]) >= 60
    assert {("eval", "number"), ("train", "existing"), ("raceline", "track")} <= covered
    assert ("drive", "video file") in covered
    assert {command for command, _ in covered} >= set(COMMANDS) - {"tracks", "sysid"}


@pytest.mark.parametrize(("command", "action"), NUMBERS, ids=case_id)
def test_every_numeric_option_has_a_largest_value_or_says_why_not(
    command: str, action: argparse.Action
):
    """``benchmark --workers 100000`` started 72 processes on 2 cores; ``eval --laps
    1000000`` ran for minutes in silence. A new option without an entry in
    ``saferace.cli.maxima`` fails here."""
    flag = action.option_strings[-1]
    assert math.isfinite(upper_end(action.type)) or uncapped(command, flag), (command, flag)
    assert flag in MAXIMA or flag in UNCAPPED or math.isfinite(upper_end(action.type))


@pytest.mark.parametrize(("command", "action", "bad"), CASES, ids=case_id)
def test_a_bad_value_is_refused_in_one_line_naming_its_option(
    command: str, action: argparse.Action, bad: str, capsys: pytest.CaptureFixture
):
    started = time.perf_counter()
    try:
        code = main(arguments(command, action, bad))
    except SystemExit as exit:
        code = exit.code
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2, lines
    assert len(lines) == 1 and name(action).replace("_", "-") in lines[0].replace("_", "-"), lines
    assert time.perf_counter() - started < 1.0  # refused before any work


SEEDS = [
    (command, action)
    for command in COMMANDS
    for action in COMMANDS[command]._actions
    if action.dest == "seeds"
]


@pytest.mark.parametrize(("command", "action"), SEEDS, ids=case_id)
def test_a_seed_given_twice_is_refused_in_one_line(
    command: str, action: argparse.Action, capsys: pytest.CaptureFixture
):
    argv = arguments(command, action, "1")
    at = argv.index(action.option_strings[-1]) + 1
    argv[at + 1 : at + 1] = ["2", "1"]  # --seeds 1 2 1
    try:
        code = main(argv)
    except SystemExit as exit:
        code = exit.code
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and lines == [f"saferace {command}: error: argument --seeds: 1 is given "
                                   "twice; give each once"]  # fmt: skip
    assert isinstance(action, values.Distinct) and len(SEEDS) >= 3


def test_laps_beyond_an_hour_of_driving_ask_for_yes_in_one_line_with_the_estimate(
    capsys: pytest.CaptureFixture,
):
    """``eval --laps 1000000`` printed nothing for minutes and kept every step in memory."""
    code = main(["eval", "--agent", "expert", "--track", "lab", "--laps", "1000000",
                 "--seeds", "0", "1", "--out", "rows.jsonl"])  # fmt: skip
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert "1,000,000 laps of lab" in lines[0] and "x 2 episode(s)" in lines[0]
    assert "pass --yes" in lines[0] and "--laps" in lines[0]
    hours = 1_000_000 * 2 * Track.load("lab").length_m / FAST_MEAN_SPEED_MPS / 3600.0
    assert f"at least {hours:,.1f} h" in lines[0]
    fine = argparse.Namespace(track="lab", laps=100, seeds=[0], yes=False)
    check_drive_length(fine)  # 100 laps of lab: 7 min
    check_drive_length(argparse.Namespace(track="lab", laps=10**6, seeds=[0], yes=True))


@pytest.mark.parametrize("command", ["eval", "drive"])
@pytest.mark.parametrize(
    ("agent", "problem"),
    [
        ("no_such_module:make", "cannot load 'no_such_module:make': No module named"),
        ("learned:/no/such.pt", "agent 'learned:/no/such.pt': no checkpoint at /no/such.pt"),
        ("reckles", "unknown agent 'reckles'"),
    ],
)
def test_an_agent_that_cannot_be_made_is_refused_before_any_setup(
    command: str,
    agent: str,
    problem: str,
    capsys: pytest.CaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
):
    def built(*args, **kwargs):
        raise AssertionError("a task was built before the agent was checked")

    monkeypatch.setattr(gym, "make", built)
    monkeypatch.setattr(gym, "make_vec", built)
    out = ["--out", "rows.jsonl"] if command == "eval" else []
    code = main([command, "--agent", agent, "--track", "lab", *out])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"saferace {command}: error: {problem}")


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_argument_no_option_takes_is_refused_by_its_command(
    command: str, capsys: pytest.CaptureFixture
):
    """``drive --out run`` said ``saferace: error: unrecognized arguments: --out run``,
    naming no command."""
    argv = [command]
    chosen = [  # one option of each group it requires one of (benchmark: --agent or --filter)
        group._group_actions[0] for group in COMMANDS[command]._mutually_exclusive_groups
        if group.required
    ]  # fmt: skip
    for action in COMMANDS[command]._actions:  # what the command requires, so it parses
        if (action.required or action in chosen) and action.option_strings:
            argv += [action.option_strings[-1], *[__file__] * count(action)]
        elif not action.option_strings and action.dest != "help":
            argv += [GOOD_VALUES.get(kind(action), __file__)] * count(action)
    with pytest.raises(SystemExit) as exit:
        main([*argv, "--no-such-option"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert exit.value.code == 2
    assert lines == [f"saferace {command}: error: unrecognized arguments: --no-such-option"]


def test_a_command_stopped_by_ctrl_c_says_so_in_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
):
    """A stopped benchmark printed a Python traceback and exited 1."""
    import saferace.cli

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    def stopped(args: argparse.Namespace) -> int:
        raise KeyboardInterrupt

    commands.choices["tracks"].set_defaults(command=stopped)
    monkeypatch.setattr(saferace.cli, "build_parser", lambda: parser)
    assert main(["tracks"]) == 130
    assert capsys.readouterr().err == "saferace tracks: interrupted\n"
