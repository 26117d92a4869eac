"""Mutation testing of chosen modules: one-line changes of the code, each run against the
fast tests that claim to check that module; a mutant that every test passes survives.

    .venv/bin/python scripts/mutation_run.py [--workers 2] [--only verify] [--out FILE]

Each mutant changes one site of the module's syntax tree: a comparison (``<`` and ``<=``,
``==`` and ``!=``, ``in`` and ``not in``), an arithmetic operator (``+`` and ``-``, ``*``
and ``/``), a boolean operator (``and`` and ``or``), a dropped ``not`` or unary minus, a
negated ``if``, a number (an integer plus one, a float doubled, a zero made one) or a
boolean flipped; and the semantic changes a real bug makes: an index into a vector one
lower (``x[1]`` for ``x[2]``), a field read by the name of another the module reads
(``info["s_m"]`` for ``info["e_y_m"]``), a tuple or list of two or more without its last
member, and a midpoint ``0.5 * (a + b)`` replaced by either end. Docstrings, annotations
and f-strings are left alone. The mutated module
is written as ``ast.unparse`` prints it (the unmutated module is run that way first, and
must pass), into a copy of the tree per worker, so that workers never share a file and the
checkout is never touched. The report lists every survivor with its line and change.

Each verdict is appended to a file beside the report (``--out`` with ``.jsonl``) as it is
reached, keyed by the module's and its tests' content: a run stopped part way (a module's
mutants can take hours) resumes where it was, and a change to the module or its tests
judges its mutants again.
"""

from __future__ import annotations

import argparse
import ast
import copy
import hashlib
import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import repeat
from pathlib import Path
from threading import Lock

ROOT = Path(__file__).resolve().parents[1]

#: Module -> the fast tests that claim to check it (a file, or ``file::-k expression``).
TARGETS: dict[str, list[str]] = {
    "saferace/safety/uncertainty/conformal.py": [
        "tests/test_conformal.py",
        "tests/test_intervals.py",
        "tests/test_recalibrate.py",
        "tests/test_adaptive.py",
        "tests/test_feature_monitor.py",
    ],
    "saferace/safety/uncertainty/intervals.py": [
        "tests/test_intervals.py",
        "tests/test_robust_filter.py",
        "tests/test_recalibrate.py",
        "tests/test_adaptive.py",
    ],
    "saferace/safety/uncertainty/fallback.py": [
        "tests/test_robust_filter.py",
        "tests/test_safety_filter.py",
        "tests/test_dead_reckoning.py",
    ],
    "saferace/safety/uncertainty/dead_reckoning.py": ["tests/test_dead_reckoning.py"],
    "saferace/safety/uncertainty/estimate.py": [
        "tests/test_state_estimate.py",
        "tests/test_robust_filter.py",
        "tests/test_dead_reckoning.py",
    ],
    "saferace/safety/uncertainty/last_trusted.py": [
        "tests/test_interval_votes.py",
        "tests/test_dead_reckoning.py",
        "tests/test_robust_filter.py",
    ],
    "saferace/safety/uncertainty/interval_votes.py": [
        "tests/test_interval_votes.py",
        "tests/test_dead_reckoning.py",
    ],
    "saferace/safety/predictive/condensed_qp.py": ["tests/test_condensed_qp.py"],
    "saferace/safety/predictive/plan.py": [
        "tests/test_predictive_filter.py",
        "tests/test_plan_linearisation.py",
        "tests/test_condensed_qp.py",
    ],
    "saferace/learning/cpu_compile.py": ["tests/test_cpu_compile.py"],
    "saferace/envs/dm_env_view.py": ["tests/test_dm_env_view.py"],
    # the model's build, resume, manifest and calibration by track; without the safety
    # table behind it (20 s a mutant, and the table's own module has its tests)
    "saferace/learning/perception.py": [
        "tests/test_perception.py::not safety_table",
        "tests/test_perception_training.py",
        "tests/test_track_calibration.py",
    ],
    "saferace/safety/model_code.py": ["tests/test_compiled_stages.py"],
    "saferace/numba_cache.py": ["tests/test_numba_cache.py"],
    "saferace/safety/predictive/filter.py": ["tests/test_predictive_filter.py"],
    "saferace/experiments/verify.py": ["tests/test_submission_checks.py"],
    "saferace/safety/traffic/car_barriers.py": [
        "tests/test_car_barrier_rows.py",
        "tests/test_traffic.py",
    ],
    # the checks of a submission's file, without verify's replays of its runs (which cost
    # a minute a mutant)
    "saferace/experiments/submission_checks.py": ["tests/test_submission_checks.py::not verify"],
}
#: Modules that do not make the honest submission the tests check: their runs share one.
SHARE_THE_SUBMISSION = (
    "saferace/experiments/verify.py",
    "saferace/experiments/submission_checks.py",
)
#: The tests' variable naming a prebuilt honest submission (see ``tests/conftest.py``).
PREBUILT_SUBMISSION_VARIABLE = "SAFERACE_TEST_PREBUILT_SUBMISSION"

COMPARE_SWAPS = {
    ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt,
    ast.Eq: ast.NotEq, ast.NotEq: ast.Eq, ast.In: ast.NotIn, ast.NotIn: ast.In,
    ast.Is: ast.IsNot, ast.IsNot: ast.Is,
}  # fmt: skip
ARITHMETIC_SWAPS = {
    ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult,
    ast.FloorDiv: ast.Mult, ast.Pow: ast.Mult, ast.Mod: ast.FloorDiv,
}  # fmt: skip


@dataclass(frozen=True)
class Mutant:
    """The ``index``-th mutation site of a module, described."""

    module: str
    index: int
    line: int
    change: str


def _skipped_nodes(tree: ast.Module) -> set[int]:
    """Ids of nodes no mutant touches: docstrings, annotations, f-strings, decorators."""
    skipped: set[int] = set()

    def skip(node: ast.AST | None) -> None:
        if node is not None:
            skipped.update(id(child) for child in ast.walk(node))

    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        first = body[0] if isinstance(body, list) and body else None
        if isinstance(first, ast.Expr) and _is_string(first.value):
            skip(first)
        if isinstance(node, ast.arg | ast.AnnAssign):
            skip(node.annotation)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            skip(node.returns)
            for decorator in node.decorator_list:
                skip(decorator)
        if isinstance(node, ast.JoinedStr):
            skip(node)
    return skipped


def _is_string(node: ast.AST) -> bool:
    return isinstance(node, ast.Constant) and isinstance(node.value, str)


def _changes(node: ast.AST) -> Iterator[tuple[str, ast.AST]]:
    """Each mutation of ``node`` alone: its description and the mutated copy."""
    if isinstance(node, ast.Compare):
        for position, operator in enumerate(node.ops):
            if type(operator) in COMPARE_SWAPS:
                mutated = copy.deepcopy(node)
                swapped = COMPARE_SWAPS[type(operator)]
                mutated.ops[position] = swapped()
                yield f"{type(operator).__name__} -> {swapped.__name__}", mutated
    elif isinstance(node, ast.BinOp | ast.AugAssign) and type(node.op) in ARITHMETIC_SWAPS:
        mutated = copy.deepcopy(node)
        mutated.op = ARITHMETIC_SWAPS[type(node.op)]()
        yield f"{type(node.op).__name__} -> {type(mutated.op).__name__}", mutated
    elif isinstance(node, ast.BoolOp):
        mutated = copy.deepcopy(node)
        mutated.op = ast.Or() if isinstance(node.op, ast.And) else ast.And()
        yield f"{type(node.op).__name__} -> {type(mutated.op).__name__}", mutated
    elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not | ast.USub):
        yield f"drop {type(node.op).__name__}", copy.deepcopy(node.operand)
    elif isinstance(node, ast.If):
        mutated = copy.deepcopy(node)
        mutated.test = ast.UnaryOp(ast.Not(), mutated.test)
        yield "negate if", mutated
    elif isinstance(node, ast.Tuple | ast.List) and len(node.elts) >= 2:
        if isinstance(node.ctx, ast.Load) and not any(
            isinstance(e, ast.Starred) for e in node.elts
        ):
            mutated = copy.deepcopy(node)
            mutated.elts = mutated.elts[:-1]
            yield f"drop the last of {len(node.elts)} members", mutated
    elif isinstance(node, ast.Constant) and type(node.value) in (int, float, bool):
        value = node.value
        if isinstance(value, bool):
            new: object = not value
        elif isinstance(value, int):
            new = value + 1
        else:
            new = 2.0 * value if value else 1.0
        yield f"{value!r} -> {new!r}", ast.Constant(new)


def _is_half(node: ast.AST) -> bool:
    return isinstance(node, ast.Constant) and node.value == 0.5


def _midpoint_changes(node: ast.AST) -> Iterator[tuple[str, ast.AST]]:
    """``0.5 * (a + b)`` (either way round) as ``a`` and as ``b``."""
    if not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult)):
        return
    pair = node.right if _is_half(node.left) else node.left if _is_half(node.right) else None
    if isinstance(pair, ast.BinOp) and isinstance(pair.op, ast.Add):
        yield "midpoint -> first end", copy.deepcopy(pair.left)
        yield "midpoint -> second end", copy.deepcopy(pair.right)


def _subscript_changes(node: ast.Subscript, keys: list[str]) -> Iterator[tuple[str, ast.AST]]:
    """An index one lower (a positive integer index), or a field read by the name of the
    next of the module's ``keys`` (a string key)."""
    index = node.slice
    if not isinstance(index, ast.Constant) or not isinstance(node.ctx, ast.Load):
        return
    value = index.value
    if type(value) is int and value > 0:
        mutated = copy.deepcopy(node)
        mutated.slice = ast.Constant(value - 1)
        yield f"index {value} -> {value - 1}", mutated
    elif isinstance(value, str) and len(keys) > 1:
        other = keys[(keys.index(value) + 1) % len(keys)]
        mutated = copy.deepcopy(node)
        mutated.slice = ast.Constant(other)
        yield f"field {value!r} -> {other!r}", mutated


def _sites(tree: ast.Module) -> list[tuple[ast.AST, str, ast.AST]]:
    skipped = _skipped_nodes(tree)
    keys = sorted(
        {
            node.slice.value
            for node in ast.walk(tree)
            if isinstance(node, ast.Subscript)
            and isinstance(node.slice, ast.Constant)
            and isinstance(node.slice.value, str)
            and id(node) not in skipped
        }
    )
    sites = []
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        changes = list(_changes(node)) + list(_midpoint_changes(node))
        if isinstance(node, ast.Subscript):
            changes += list(_subscript_changes(node, keys))
        sites += [(node, change, mutated) for change, mutated in changes]
    return sites


class _Replace(ast.NodeTransformer):
    def __init__(self, target: ast.AST, replacement: ast.AST) -> None:
        self.target, self.replacement = target, replacement

    def visit(self, node: ast.AST) -> ast.AST:
        if node is self.target:
            return ast.copy_location(self.replacement, node)
        return super().visit(node)


def mutants(module: str) -> list[Mutant]:
    tree = ast.parse((ROOT / module).read_text())
    return [
        Mutant(module, index, getattr(node, "lineno", 0), change)
        for index, (node, change, _) in enumerate(_sites(tree))
    ]


def mutated_source(mutant: Mutant | None, module: str) -> str:
    """The module as ``ast.unparse`` prints it, with ``mutant`` applied (None: unmutated)."""
    tree = ast.parse((ROOT / module).read_text())
    if mutant is not None:
        node, _, replacement = _sites(tree)[mutant.index]
        tree = _Replace(node, replacement).visit(tree)
        ast.fix_missing_locations(tree)
    return ast.unparse(tree) + "\n"


def _pytest_args(tests: list[str]) -> list[str]:
    files = [test.partition("::")[0] for test in tests]
    expressions = [test.partition("::")[2] for test in tests if "::" in test]
    return [*files, *(["-k", " or ".join(expressions)] if expressions else [])]


def run_tests(
    tree: Path, tests: list[str], timeout_s: float, submission: Path | None = None
) -> tuple[bool, float]:
    """Whether every test passed in ``tree`` (within ``timeout_s``; with the honest
    ``submission`` made beforehand, if given), and the seconds taken."""
    started = time.perf_counter()
    command = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
               *_pytest_args(tests)]  # fmt: skip
    environment = {**os.environ, "PYTHONPATH": str(tree), "MUJOCO_GL": "egl"}
    if submission is not None:
        environment[PREBUILT_SUBMISSION_VARIABLE] = str(submission)
    try:
        result = subprocess.run(
            command, cwd=tree, env=environment, capture_output=True, timeout=timeout_s,
            check=False,
        )  # fmt: skip
        passed = result.returncode == 0
    except subprocess.TimeoutExpired:
        passed = False
    return passed, time.perf_counter() - started


def honest_submission(tree: Path) -> Path:
    """Pure pursuit's submission of the benchmark suite, made once in ``tree``."""
    path = tree.parent / "pure_pursuit.json"
    script = (
        "from saferace.experiments.benchmark import run_benchmark\n"
        f"run_benchmark('pure-pursuit', {str(path)!r}, workers=2, progress=False)\n"
    )
    environment = {**os.environ, "PYTHONPATH": str(tree), "MUJOCO_GL": "egl"}
    subprocess.run([sys.executable, "-c", script], cwd=tree, env=environment, check=True)
    return path


def copy_tree(destination: Path) -> Path:
    """A copy of the checkout, its git history too: what records the commit (a perception
    model's manifest, an eval row) reads it from there."""
    shutil.copytree(
        ROOT, destination,
        ignore=shutil.ignore_patterns(".venv", "results", "site", "__pycache__"),
    )  # fmt: skip
    return destination


@dataclass(frozen=True)
class Target:
    """A module and how its mutants are judged."""

    module: str
    tests: list[str]
    timeout_s: float
    submission: Path | None


def judge(target: Target, mutant: Mutant, trees: queue.Queue[Path]) -> bool:
    """Whether ``mutant`` survives ``target``'s tests, run in a free tree of ``trees``."""
    tree = trees.get()
    try:
        (tree / target.module).write_text(mutated_source(mutant, target.module))
        return run_tests(tree, target.tests, target.timeout_s, target.submission)[0]
    finally:
        (tree / target.module).write_text((ROOT / target.module).read_text())
        trees.put(tree)


def content_key(module: str, tests: list[str]) -> str:
    """A hash of the module and of the tests that judge its mutants, and how they are run."""
    digest = hashlib.sha256(module.encode() + (ROOT / module).read_bytes())
    for test in tests:
        digest.update(test.encode() + (ROOT / test.partition("::")[0]).read_bytes())
    return digest.hexdigest()[:16]


class Verdicts:
    """The verdicts reached so far (``path``, JSON lines): whether each mutant survived,
    by module, content key and mutant index; each new one appended as it is reached."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = Lock()
        lines = path.read_text().splitlines() if path.exists() else []
        self._known = {
            (row["module"], row["key"], row["index"]): row["survived"]
            for row in map(json.loads, lines)
        }

    def get(self, module: str, key: str, index: int) -> bool | None:
        return self._known.get((module, key, index))

    def add(self, module: str, key: str, mutant: Mutant, survived: bool) -> None:
        row = {"module": module, "key": key, "index": mutant.index, "line": mutant.line,
               "change": mutant.change, "survived": survived}  # fmt: skip
        with self._lock:
            self._known[(module, key, mutant.index)] = survived
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with self.path.open("a") as handle:
                handle.write(json.dumps(row) + "\n")


def judge_and_keep(
    target: Target, key: str, verdicts: Verdicts, mutant: Mutant, trees: queue.Queue[Path]
) -> bool:
    """:func:`judge`, or the verdict kept from an earlier run of the same content."""
    known = verdicts.get(target.module, key, mutant.index)
    if known is not None:
        return known
    survived = judge(target, mutant, trees)
    verdicts.add(target.module, key, mutant, survived)
    verdict = "survived" if survived else "killed"
    print(f"  line {mutant.line} `{mutant.change}` (site {mutant.index}): {verdict}", flush=True)
    return survived


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--only", nargs="*", default=(), help="modules whose path has a word")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "mutations.md")
    args = parser.parse_args()
    if args.workers < 1:
        parser.error(f"--workers must be at least 1, got {args.workers}")
    modules = [m for m in TARGETS if not args.only or any(word in m for word in args.only)]
    if not modules:
        parser.error(f"--only {' '.join(args.only)} names none of {', '.join(TARGETS)}")
    scratch = Path(tempfile.mkdtemp(prefix="saferace-mutants-"))
    trees: queue.Queue[Path] = queue.Queue()
    for worker in range(args.workers):
        trees.put(copy_tree(scratch / f"tree{worker}"))
    first_tree = scratch / "tree0"
    verdicts = Verdicts(args.out.with_suffix(".jsonl"))
    lines = ["# Mutation run", "", "| module | mutants | killed | survived |", "|---|---|---|---|"]
    survivors: list[str] = []
    submission = None
    try:
        for module in modules:
            if module in SHARE_THE_SUBMISSION and submission is None:
                submission = honest_submission(first_tree)
            shared = submission if module in SHARE_THE_SUBMISSION else None
            (first_tree / module).write_text(mutated_source(None, module))
            passed, baseline_s = run_tests(first_tree, TARGETS[module], 1800.0, shared)
            (first_tree / module).write_text((ROOT / module).read_text())
            if not passed:
                raise SystemExit(f"{module}: its tests fail on the unmutated, unparsed module")
            target = Target(module, TARGETS[module], 3.0 * baseline_s + 30.0, shared)
            found = mutants(module)
            key = content_key(module, TARGETS[module])
            kept = sum(verdicts.get(module, key, mutant.index) is not None for mutant in found)
            print(
                f"{module}: {len(found)} mutants ({kept} judged before), tests "
                f"{baseline_s:.0f} s", flush=True,
            )  # fmt: skip
            with ThreadPoolExecutor(args.workers) as pool:
                survived = list(
                    pool.map(judge_and_keep, repeat(target), repeat(key), repeat(verdicts), found,
                             repeat(trees))
                )  # fmt: skip
            alive = [mutant for mutant, lives in zip(found, survived, strict=True) if lives]
            lines.append(f"| {module} | {len(found)} | {len(found) - len(alive)} | {len(alive)} |")
            survivors += [f"- {m.module}:{m.line} `{m.change}` (site {m.index})" for m in alive]
            print(f"  killed {len(found) - len(alive)} of {len(found)}", flush=True)
            write_report(args.out, lines, survivors)  # after each module: nothing lost
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    print(args.out.read_text())
    return 0


def write_report(path: Path, table: list[str], survivors: list[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join([*table, "", "## Survivors", "", *survivors]) + "\n")


if __name__ == "__main__":
    sys.exit(main())
