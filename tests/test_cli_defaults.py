"""The command line and the library agree on every default: a config built from a command
with no options is the config's own default, and every generated option's default is its
field's (a drift once made ``saferace dagger`` and ``DaggerRun(DaggerConfig())`` run
different filters)."""

from __future__ import annotations

import argparse
import json
import shlex
from pathlib import Path

import pytest

from saferace.cli import build_parser, values
from saferace.cli.arguments import filter_config
from saferace.cli.experiments import dagger_config
from saferace.cli.learning import collection_config, train_config
from saferace.cli.options import FLAGS_KEY
from saferace.cli.safety import robustness_config
from saferace.errors import ConfigError, SafeRaceError
from saferace.eval.filter_config import FilterConfig
from saferace.experiments.robustness_config import RobustnessConfig
from saferace.learning.configs import CollectionConfig, DaggerConfig, TrainConfig
from saferace.names import AUTO, DEFAULT_GAINS, GAIN_NAMES, ROBUST_GAINS

PARSER = build_parser()


def lenient_parser() -> argparse.ArgumentParser:
    """The parser with the input files and tracks its examples name taken as named (none of
    them is here)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(values, "existing", Path)
        patch.setattr(values, "track", str)
        patch.setattr(values, "labelled_folder", lambda text: tuple(text.partition("=")[::2]))
        return build_parser()


LENIENT = lenient_parser()
#: Each command built from a config: its shortest command line, its builder, the default.
BUILT = {
    "dagger": (["--out", "run"], dagger_config, DaggerConfig()),
    "collect": (["--out", "data"], collection_config, CollectionConfig()),
    "train": (["data", "--out", "m.pt"], train_config, TrainConfig()),
    "robustness": (["--out", "robust"], robustness_config, RobustnessConfig()),
    "eval": (["--out", "rows.jsonl"], filter_config, FilterConfig()),
    "drive": ([], filter_config, FilterConfig()),
}


def subparsers() -> dict[str, argparse.ArgumentParser]:
    (action,) = (a for a in PARSER._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


@pytest.mark.parametrize("command", sorted(BUILT))
def test_a_command_without_options_builds_the_default_config(command: str):
    argv, build, default = BUILT[command]
    assert build(LENIENT.parse_args([command, *argv])) == default


def library_default(config, dest: str):
    """The default of the field an option's ``dest`` names (``training.epochs``: the
    config's training's epochs; ``filter.*`` is the filter config wherever it nests)."""
    *path, name = dest.split(".")
    for part in path:
        config = getattr(config, part, None) or getattr(config, "safety", FilterConfig())
    value = getattr(config, name)
    return list(value) if isinstance(value, tuple) else value


@pytest.mark.parametrize("command", sorted(BUILT))
def test_every_generated_option_defaults_to_its_field(command: str):
    parser = subparsers()[command]
    _, _, default = BUILT[command]
    flags = parser.get_default(FLAGS_KEY)
    generated = [
        a for a in parser._actions if a.option_strings and a.option_strings[0] in flags.values()
    ]
    assert len(generated) == len(set(flags.values())) > 5
    settled = {"filter.uncertainty", "filter.gains", "filter.model"}  # auto: the config settles
    for action in generated:
        if action.dest in settled:
            assert action.default == AUTO, action.dest
        else:
            assert action.default == library_default(default, action.dest), action.dest


def test_one_default_gain_setting_everywhere():
    from saferace.safety.cbf.filter import GAIN_PRESETS

    assert tuple(GAIN_PRESETS) == GAIN_NAMES
    assert FilterConfig().gains == FilterConfig(state_noise=(0.05, 0.05)).gains == DEFAULT_GAINS
    for command in ("eval", "dagger", "collect", "robustness"):
        args = PARSER.parse_args([command, "--out", "x"])
        assert args.__dict__["filter.gains"] == AUTO, command
    table = PARSER.parse_args(["safety-table"])
    assert table.filter_gains == DEFAULT_GAINS


def built_filter(command: str, *options: str):
    """The filter config (and the whole config) a command line of ``command`` builds."""
    argv, build, _ = BUILT[command]
    config = build(PARSER.parse_args([command, "--filter", "cbf", *options, *argv]))
    if isinstance(config, FilterConfig):
        return config, config
    return getattr(config, "filter", None) or config.safety, config


@pytest.mark.parametrize("command", ["eval", "drive", "collect", "robustness", "dagger"])
def test_a_learned_state_source_gets_the_robust_filter_by_default(command: str):
    learned = ("--state-source", "learned" if command == "dagger" else "learned:m.pt")
    truth = ("--state-source", "oracle")
    safety, config = built_filter(command, *learned)
    assert (safety.uncertainty, safety.gains) == ("robust", ROBUST_GAINS)
    paper, _ = built_filter(command, *learned, "--filter-uncertainty", "chance")
    assert (paper.uncertainty, paper.gains) == ("chance", DEFAULT_GAINS)
    oracle, unperceived = built_filter(command, *truth)
    assert (oracle.uncertainty, oracle.gains) == ("chance", DEFAULT_GAINS)
    generic, generic_config = built_filter(command, "--state-source", "generic")
    assert (generic.uncertainty, generic.gains) == ("robust", ROBUST_GAINS)
    # A filter asked for without a source: the generic model where perception decides the
    # command's claim (dagger, robustness), the truth where a user drives or collects.
    perceived = command in ("dagger", "robustness")
    assert built_filter(command)[0] == (generic if perceived else oracle)
    if command == "robustness":  # a noisy oracle, or a monitor's own source, keeps the truth
        noisy, _ = built_filter(command, "--state-noise", "0.05", "0.05")
        assert noisy.state_source is None and noisy.state_noise == (0.05, 0.05)
        monitored, _ = built_filter(command, "--monitor-state", "learned:m.pt")
        assert monitored.state_source is None
    if command == "dagger":  # the state networks that the robust filter can trust
        assert config.training.state_uncertainty == "ensemble"
        assert unperceived.training.state_uncertainty == "mc-dropout"
        assert generic_config.training.state_uncertainty == "mc-dropout"  # feeds nothing


def test_a_config_error_names_the_option(capsys: pytest.CaptureFixture):
    from saferace.cli import main

    assert main(["dagger", "--min-train-steps", "9", "--max-train-steps", "5", "--out", "x"]) == 2
    assert "--min-train-steps 9 is above max_steps 5" in capsys.readouterr().err


@pytest.mark.parametrize("command", sorted(subparsers()))
def test_every_option_has_help_and_every_command_an_example(command: str):
    parser = subparsers()[command]
    undocumented = [
        action.dest
        for action in parser._actions
        if not isinstance(action, argparse._HelpAction) and not action.help
    ]
    assert not undocumented
    assert parser.epilog and parser.epilog.startswith("examples:")
    for line in parser.epilog.splitlines()[1:]:
        program, *argv = shlex.split(line)
        assert program == "saferace" and argv[0] == command
        LENIENT.parse_args(argv)  # the example is a valid command line


def test_options_of_the_chance_constraints_keep_auto_on_them(tmp_path):
    learned = ("--state-source", "learned:m.pt")
    for option in (("--deterministic",), ("--spread-scale", "2", "2", "1"), ("--fuse-odometry",)):
        safety, _ = built_filter("eval", *learned, *option)
        assert (safety.uncertainty, safety.gains) == ("chance", DEFAULT_GAINS), option
    own = ("--state-source", "learned")
    safety, config = built_filter("dagger", *own, "--calibrate-spread")
    assert safety.uncertainty == "chance" and config.training.state_uncertainty == "mc-dropout"
    with pytest.raises(ConfigError, match="calibrate_spread"):
        built_filter("dagger", *own, "--calibrate-spread", "--filter-uncertainty", "robust")
    with pytest.raises(ConfigError, match="run's own state network"):
        built_filter("dagger", "--state-source", "generic", "--calibrate-spread")


def test_a_fork_takes_the_state_networks_of_the_run_it_forks(tmp_path):
    base = tmp_path / "base"
    base.mkdir()
    for recorded, method in ((None, "mc-dropout"), ("ensemble", "ensemble")):
        fingerprint = {"task": "CenterLine"} | ({"state_uncertainty": recorded} if recorded else {})
        (base / "run.json").write_text(json.dumps({"fingerprint": fingerprint}))
        _, config = built_filter("dagger", "--fork-of", str(base))
        assert config.training.state_uncertainty == method
    (tmp_path / "nothing").mkdir()
    with pytest.raises(SafeRaceError, match="holds no DAgger run"):
        built_filter("dagger", "--fork-of", str(tmp_path / "nothing"))


def test_tracks_lists_every_built_in_track_with_its_numbers_and_how_to_bring_a_csv(capsys):
    from saferace.cli import main
    from saferace.track import Track, builtin_track_names

    assert main(["tracks"]) == 0
    printed = capsys.readouterr().out
    table = [line.split("|")[1:5] for line in printed.splitlines()[2:] if line.startswith("|")]
    rows = {name.strip(): values for name, *values in table}
    assert sorted(rows) == builtin_track_names()
    for name, (length, width, radius) in rows.items():
        track = Track.load(name)
        assert float(length) == pytest.approx(track.length_m, abs=0.05)
        assert float(radius) == pytest.approx(track.min_turn_radius_m(), abs=0.005)
        assert float(width.split("-")[0]) <= float(width.split("-")[-1])
    assert [rows[name][1].strip() for name in ("lab", "varying")] == ["0.80", "0.80-1.50"]
    assert "x_m,y_m,w_tr_right_m,w_tr_left_m" in printed
    with pytest.raises(SystemExit):
        main(["track-info", "--help"])
    usage = capsys.readouterr().out
    assert all(name in usage for name in builtin_track_names())
