"""Driving commands: ``drive``, ``eval``, ``leaderboard``, ``benchmark`` and ``verify``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from saferace.cli import example, values
from saferace.cli.arguments import (
    AGENT_HELP,
    add_device_argument,
    add_episode_arguments,
    add_faults_argument,
    add_filter_arguments,
    add_num_envs_argument,
    add_parallel_arguments,
    add_seeds_argument,
    built_filter_config,
    check_drive_length,
    ensure_generic_model,
)
from saferace.errors import SafeRaceError
from saferace.names import (
    DEFAULT_EXPERT_MODEL,
    GAIN_NAMES,
    GENERIC_SOURCE,
    MC_SAMPLES,
    SLACK_PENALTIES,
    VEHICLE_MODELS,
    VERIFY_RUNS,
)

CIRCUITS_HELP = (
    "filter submissions with circuits: read their F1TENTH centre lines from this folder, "
    "not the one each submission names"
)
RECORDS_HELP = (
    "folder of this machine's verification records (default: $SAFERACE_VERIFIED, else "
    "~/.cache/saferace/verified)"
)


def register(commands: argparse._SubParsersAction) -> None:
    drive = commands.add_parser(
        "drive",
        help="a driver laps a track; video and Rerun recording",
        epilog=example(
            "saferace drive --agent expert --track technical --video lap.mp4 --rerun lap.rrd",
            "saferace drive --agent speeding --filter cbf --state-source noisy --track lab",
            "saferace drive --agent speeding --filter cbf --opponents braking blocker:gap_m=6",
        ),
    )
    add_episode_arguments(drive, default_agent="pure-pursuit")
    drive.add_argument(
        "--seed", type=values.seed, default=0, help="seeds the episode and its agent"
    )
    drive.add_argument(
        "--video",
        type=values.video_file,
        help="write the onboard and chase views here: .mp4 (H.264; WebM beside it where no "
        "H.264 encoder is installed) or .webm",
    )
    drive.add_argument("--rerun", type=Path, help="write a Rerun recording (.rrd) here")
    add_filter_arguments(drive)
    add_device_argument(drive)
    drive.set_defaults(command=_drive)

    evaluate = commands.add_parser(
        "eval",
        help="evaluate an agent; one JSON row per (agent, task, track, seed)",
        epilog=example(
            "saferace eval --agent expert --task RacingLine --track technical --out rows.jsonl",
            "saferace eval --agent weave --filter cbf --seeds 0 1 2 --out rows.jsonl",
            "saferace eval --agent expert --task Overtake --filter cbf --out rows.jsonl",
        ),
    )
    add_episode_arguments(evaluate, default_agent="expert")
    add_seeds_argument(evaluate, [0], "one episode per seed")
    evaluate.add_argument(
        "--model",
        default=DEFAULT_EXPERT_MODEL,
        choices=VEHICLE_MODELS,
        help="vehicle model of the expert MPC",
    )
    evaluate.add_argument(
        "--out", type=Path, required=True, help="JSONL file to append the rows to"
    )
    add_filter_arguments(evaluate)
    evaluate.add_argument(
        "--max-seconds", type=values.positive, help="end an episode after this much simulated time"
    )
    add_num_envs_argument(evaluate)
    add_device_argument(evaluate)
    evaluate.set_defaults(command=_eval)

    board = commands.add_parser(
        "leaderboard",
        help="markdown table (and plots) from eval results, or the benchmark's from submissions",
        epilog=example(
            "saferace leaderboard rows.jsonl --plot trajectories.png --csv table.csv",
            "saferace leaderboard submissions/*.json --html leaderboard.html",
        ),
    )
    board.add_argument(
        "results",
        type=values.existing,
        nargs="+",
        help="JSONL files written by saferace eval, or submission .json files of saferace "
        "benchmark",
    )
    board.add_argument("--csv", type=Path, help="also write the table as CSV")
    board.add_argument(
        "--plot",
        type=Path,
        help="driven trajectories and speeds to a PNG; for filter submissions, each entry's "
        "score and time outside per condition",
    )
    board.add_argument("--html", type=Path, help="submissions: one self-contained leaderboard page")
    board.add_argument(
        "--verified-only",
        action="store_true",
        help="submissions: list only those saferace verify has passed (in their current form)",
    )
    board.add_argument("--records", type=Path, help=RECORDS_HELP)
    board.add_argument("--circuits", type=values.existing, help=CIRCUITS_HELP)
    board.set_defaults(command=_leaderboard)

    bench = commands.add_parser(
        "benchmark",
        help="the fixed evaluation protocol for one agent, or for one safety filter (the "
        "filter protocol): a submission file",
        epilog=example(
            "saferace benchmark --agent pure-pursuit --out submissions/pure_pursuit.json",
            "saferace benchmark --agent learned:lab_mono.pt --workers 2 --out learned.json",
            "saferace benchmark --agent drift --faults steering:offset=0.04 --out drift_bent.json",
            "saferace benchmark --filter my_filter:make --workers 2 --out my_filter.json",
            "saferace benchmark --filter cbf --filter-gains paper --out cbf_paper.json",
            "saferace benchmark --filter cbf --state-source my_perception:make --out mine.json",
        ),
    )
    ranked = bench.add_mutually_exclusive_group(required=True)
    ranked.add_argument("--agent", help=AGENT_HELP)
    ranked.add_argument(
        "--filter",
        help="rank a safety filter instead, on the filter protocol: none, cbf, mpsf or "
        "MODULE:FACTORY (a filter of your own)",
    )
    filter_options = bench.add_argument_group("the filter protocol")
    filter_options.add_argument(
        "--state-source",
        default=GENERIC_SOURCE,
        help="what feeds the filter in the perceived conditions: generic[:RECIPE], "
        "learned:CKPT or MODULE:FACTORY (a perception method of your own)",
    )
    filter_options.add_argument(
        "--circuits",
        type=values.existing,
        help="also drive the protocol's F1TENTH circuits, their centre lines read from this "
        "folder (the racetracks' NAME_centerline.csv, as the protocol pins them)",
    )
    filter_options.add_argument("--filter-gains", choices=GAIN_NAMES, help="our cbf's gains")
    filter_options.add_argument(
        "--filter-slack", choices=SLACK_PENALTIES, help="our cbf's QP slack penalty"
    )
    bench.add_argument("--out", type=Path, required=True, help="the submission .json to write")
    add_parallel_arguments(bench)
    bench.add_argument(
        "--mc-samples",
        type=values.count,
        default=MC_SAMPLES,
        help="MC-dropout samples of a learned agent",
    )
    add_faults_argument(bench)
    add_device_argument(bench)
    bench.set_defaults(command=_benchmark)

    verify = commands.add_parser(
        "verify",
        help="drive a submission's runs again and compare every measurement",
        epilog=example(
            "saferace verify submissions/pure_pursuit.json",
            "saferace verify learned.json --all --workers 2",
        ),
    )
    verify.add_argument(
        "submission", type=values.existing, help="a submission .json of saferace benchmark"
    )
    how_many = verify.add_mutually_exclusive_group()
    how_many.add_argument(
        "--runs",
        type=values.count,
        default=VERIFY_RUNS,
        help="replay this many runs, drawn at random",
    )
    how_many.add_argument("--all", action="store_true", help="replay every run")
    verify.add_argument("--seed", type=values.seed, default=0, help="draws the runs to replay")
    verify.add_argument(
        "--workers", type=values.count, default=1, help="runs at once, in processes"
    )
    verify.add_argument("--records", type=Path, help=RECORDS_HELP)
    verify.add_argument("--circuits", type=values.existing, help=CIRCUITS_HELP)
    add_device_argument(verify)
    verify.set_defaults(command=_verify)


def _drive(args: argparse.Namespace) -> int:
    from saferace.eval.agents import check_agent_spec

    check_agent_spec(args.agent)
    check_drive_length(args)
    from saferace.eval.drive import drive
    from saferace.eval.leaderboard import leaderboard_markdown
    from saferace.eval.runner import result_row
    from saferace.eval.video import video_path

    video = video_path(args.video) if args.video else None  # where it goes: WebM without H.264
    safety = built_filter_config(args)
    result = drive(
        args.task,
        args.track,
        agent=args.agent,
        laps=args.laps,
        video=args.video,
        rerun=args.rerun,
        seed=args.seed,
        image_size=(args.image_size, args.image_size),
        stereo=args.stereo,
        mc_samples=args.mc_samples,
        safety=safety,
        opponents=args.opponents,
        faults=args.faults,
    )
    row = result_row(
        args.agent, args.task, Path(args.track).stem, args.track, args.seed, args.laps, "-",
        result, safety=safety,
    )  # fmt: skip
    environment = {"opponents": args.opponents, "faults": args.faults}
    if any(environment.values()):
        row["config"]["env"] = {key: value for key, value in environment.items() if value}
    print(leaderboard_markdown([row]))
    for label, path in (("video", video), ("rerun recording", args.rerun)):
        if path:
            print(f"{label} written to {path}")
    if result.summary["laps_completed"] < args.laps:  # a finished run, as eval's: exit 0
        print(f"saferace drive: not all {args.laps} laps driven; {result.ending}", file=sys.stderr)
    return 0


def _eval(args: argparse.Namespace) -> int:
    from saferace.eval.agents import check_agent_spec

    check_agent_spec(args.agent)
    check_drive_length(args)
    from saferace.eval.leaderboard import leaderboard_markdown
    from saferace.eval.runner import evaluate, max_steps_for

    rows = evaluate(
        args.agent,
        args.task,
        args.track,
        args.seeds,
        laps=args.laps,
        model=args.model,
        out=args.out,
        env_kwargs={
            "max_steps": max_steps_for(args.max_seconds),
            "image_size": (args.image_size, args.image_size),
            "stereo": args.stereo,
            **({} if args.opponents is None else {"opponents": args.opponents}),
            **({} if args.faults is None else {"faults": args.faults}),
        },
        safety=built_filter_config(args),
        mc_samples=args.mc_samples,
        num_envs=args.num_envs,
    )
    print(leaderboard_markdown(rows))
    print(f"{len(rows)} rows appended to {args.out}")
    return 0


def _leaderboard(args: argparse.Namespace) -> int:
    submissions = [path.suffix == ".json" for path in args.results]
    if any(submissions):
        if not all(submissions):
            raise SafeRaceError("give either eval results (.jsonl) or submissions (.json)")
        return _submission_leaderboard(args)
    if args.html or args.verified_only:
        raise SafeRaceError(
            "--html and --verified-only are for the benchmark: give submission .json files"
        )
    from saferace.eval.leaderboard import (
        leaderboard_markdown,
        plot_trajectories,
        write_leaderboard_csv,
    )
    from saferace.eval.runner import read_jsonl

    rows = []
    for path in args.results:
        if not path.exists():
            raise SafeRaceError(
                f"no results file at {path}; write one with saferace eval --out {path}"
            )
        rows += read_jsonl(path)
    if not rows:
        raise SafeRaceError("the results files hold no rows")
    print(leaderboard_markdown(rows))
    if args.csv:
        write_leaderboard_csv(rows, args.csv)
        print(f"table written to {args.csv}")
    if args.plot:
        plot_trajectories(rows, args.plot)
        print(f"plot written to {args.plot}")
    return 0


def _submission_leaderboard(args: argparse.Namespace) -> int:
    from saferace.eval.tables import markdown_table, write_csv
    from saferace.experiments.benchmark import load_suite
    from saferace.experiments.benchmark_page import COLUMNS, leaderboard_html, leaderboard_rows
    from saferace.experiments.filter_submission_checks import is_filter_submission_file
    from saferace.experiments.submission_checks import read_submission
    from saferace.experiments.verify import verification_record

    filters = [is_filter_submission_file(path) for path in args.results]
    if any(filters):
        if not all(filters):
            raise SafeRaceError(
                "give either drivers' submissions or filter submissions: they rank on "
                "boards of their own"
            )
        return _filter_board(args)
    if args.plot:
        raise SafeRaceError("--plot is for eval results; a submissions' page has --html")
    submissions = [
        {**read_submission(path), "verification": verification_record(path, args.records)}
        for path in args.results
    ]
    if args.verified_only:
        submissions = [entry for entry in submissions if entry["verification"]]
        if not submissions:
            raise SafeRaceError("no submission has passed saferace verify in its current form")
    rows = leaderboard_rows(submissions)
    print(markdown_table(COLUMNS, [["-" if v is None else v for v in row] for row in rows]))
    if args.csv:
        write_csv(args.csv, COLUMNS, rows)
        print(f"table written to {args.csv}")
    if args.html:
        args.html.parent.mkdir(parents=True, exist_ok=True)
        args.html.write_text(leaderboard_html(submissions, load_suite()))
        print(f"page written to {args.html}")
    return 0


def _filter_board(args: argparse.Namespace) -> int:
    """The filters' board of the filter submissions given (see :func:`_leaderboard`)."""
    from saferace.eval.tables import markdown_table, write_csv
    from saferace.experiments.filter_board import (
        COLUMNS,
        filter_board_html,
        filter_board_rows,
        plot_conditions,
    )
    from saferace.experiments.filter_submission_checks import read_filter_submission
    from saferace.experiments.filter_suite import load_filter_suite
    from saferace.experiments.verify import verification_record

    submissions = []
    for path in args.results:
        checked = read_filter_submission(str(path), circuits=args.circuits and str(args.circuits))
        submissions.append({**checked, "verification": verification_record(path, args.records)})
    if args.verified_only:
        submissions = [entry for entry in submissions if entry["verification"]]
        if not submissions:
            raise SafeRaceError("no submission has passed saferace verify in its current form")
    rows = filter_board_rows(submissions)
    print(markdown_table(COLUMNS, [["-" if v is None else v for v in row] for row in rows]))
    newest = max(entry["filter_suite_version"] for entry in submissions)
    suite = load_filter_suite(newest)
    pictured = [entry for entry in submissions if entry["filter_suite_version"] == newest]
    if args.csv:
        write_csv(args.csv, COLUMNS, rows)
        print(f"table written to {args.csv}")
    if args.plot:
        plot_conditions(pictured, suite, args.plot)
        print(f"plot written to {args.plot}")
    if args.html:
        args.html.parent.mkdir(parents=True, exist_ok=True)
        args.html.write_text(filter_board_html(submissions, suite))
        print(f"page written to {args.html}")
    return 0


def _benchmark(args: argparse.Namespace) -> int:
    if args.filter is not None:
        return _filter_benchmark(args)
    from saferace.experiments.benchmark import run_benchmark

    result = run_benchmark(
        args.agent,
        args.out,
        workers=args.workers,
        mc_samples=args.mc_samples,
        ray_address=args.ray,
        faults=args.faults or (),
    )
    score = "-" if result["score"] is None else f"{result['score']:.1f}"
    with_filter = result["score_with_filter"]
    print(
        f"{args.agent}: score {score}, with the filter "
        f"{'-' if with_filter is None else f'{with_filter:.1f}'}; submission written to {args.out}"
    )
    return 0


def _filter_benchmark(args: argparse.Namespace) -> int:
    from saferace.experiments.filter_benchmark import FilterEntry, run_filter_benchmark

    if args.faults:
        raise SafeRaceError("--faults: the filter protocol has no fault conditions yet")
    entry = FilterEntry(args.filter, args.state_source, args.filter_gains, args.filter_slack)
    if entry.filter != "none":
        ensure_generic_model(entry.perception, args.workers)
    result = run_filter_benchmark(
        entry, args.out, workers=args.workers, ray_address=args.ray, circuits=args.circuits
    )
    print(
        f"{entry.label}: score {result['score']:.1f}, {result['runs_outside']} runs outside "
        f"({result['time_outside_lane_s']:.2f} s), longest standstill "
        f"{result['longest_standstill_s']:.2f} s; submission written to {args.out}"
    )
    return 0


def _verify(args: argparse.Namespace) -> int:
    from saferace.experiments.verify import record_path, verify_submission

    result = verify_submission(
        args.submission,
        runs=None if args.all else args.runs,
        workers=args.workers,
        seed=args.seed,
        records=args.records,
        circuits=args.circuits and str(args.circuits),
    )
    for note in result.version_notes:
        print(f"note: {note}")
    replayed = f"{len(result.replayed)} of {result.total_runs} runs"
    if not result.passed:
        for mismatch in result.mismatches:
            print(f"mismatch: {mismatch}")
        raise SafeRaceError(
            f"{args.submission}: {len(result.mismatches)} of {len(result.replayed)} replayed "
            f"runs differ from the submission; first: {result.mismatches[0]}"
        )
    print(
        f"{args.submission}: {replayed} replayed, all as submitted; record in "
        f"{record_path(result.submission_sha256, args.records)}"
    )
    return 0
