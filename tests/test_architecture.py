"""The package's shape: one-way dependencies between its floors, no import cycles, small
files, and a command line that only parses, calls and prints."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "saferace"
#: The floors, bottom up: a module may import its own floor and those below, never above.
FLOORS = {
    "names": 0, "config": 0, "errors": 0, "version": 0, "registry": 0, "extras": 0, "progress": 0,
    "assets": 0, "cache": 0, "numba_cache": 0,
    "track": 1,
    "envs": 2, "faults": 2,
    "safety": 3, "agents": 3,
    "eval": 4, "sysid": 4, "multi": 4,
    "learning": 5,
    "experiments": 6,
    "cli": 7, "__main__": 7, "__init__": 7,
}  # fmt: skip
#: Packages on one floor and one they must not import: the filter never depends on an
#: agent (both depend on the vehicle models in ``safety``).
NOT_IMPORTING = {"safety": "agents"}
MAX_LINES = 500


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def part(module: str) -> str:
    """The floor key of ``saferace.X...``: ``X`` (``__init__`` for the package itself)."""
    pieces = module.split(".")
    return pieces[1] if len(pieces) > 1 else "__init__"


def imported_from(path: Path, node: ast.ImportFrom) -> str:
    """The absolute module of ``from [.]* module import ...`` in ``path``."""
    if node.level == 0:
        return node.module or ""
    package = module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def imports(path: Path, top_level_only: bool = False) -> set[str]:
    """The saferace modules ``path`` imports, relative imports resolved (only at module
    level if asked)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else ast.walk(tree)
    found = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = imported_from(path, node)
            found.add(module)
            found |= {f"{module}.{alias.name}" for alias in node.names}
    return {name for name in found if name.split(".")[0] == "saferace"}


#: A string naming a module of the package, as ``importlib`` or an entry point loads it
#: (``"saferace.agents.opponents:make_opponent"``, or the start of an f-string).
MODULE_STRING = re.compile(r"(saferace(?:\.\w+)+)(?::\w*)?")
#: The modules that load a higher floor by name at run time, and what they load: plug-in
#: points kept visible here (an entry missing from the source fails as well as a new one).
DYNAMIC_IMPORTS_ALLOWED = {
    "saferace.registry": {"saferace.envs.tasks"},
    "saferace.envs.traffic": {"saferace.agents.opponents"},
    "saferace.eval.agents": {"saferace.learning.agent"},
    "saferace.eval.filter_config": {"saferace.learning.agent", "saferace.learning.perception"},
}


def modules_named_in_strings(path: Path) -> set[str]:
    """The saferace modules that string constants in ``path`` name (see
    :data:`MODULE_STRING`)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        is_string = isinstance(node, ast.Constant) and isinstance(node.value, str)
        if is_string and (match := MODULE_STRING.fullmatch(node.value)):
            found.add(match.group(1))
    return found


SOURCES = sorted(PACKAGE.rglob("*.py"))
MODULES = {module_name(path) for path in SOURCES}


def known(name: str) -> str | None:
    """``name`` if it is a module of the package, else its parent if that is (an imported
    attribute), else None."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_imports_a_higher_floor(path: Path):
    own = part(module_name(path))
    for imported in imports(path):
        target = part(imported)
        assert FLOORS[target] <= FLOORS[own], f"{own} imports {imported}, a higher floor"
        assert NOT_IMPORTING.get(own) != target, f"{own} imports {imported}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_modules_loaded_by_name_from_a_higher_floor_are_the_allowed_ones(path: Path):
    own = module_name(path)
    upward = {
        module
        for name in modules_named_in_strings(path)
        if (module := known(name)) and FLOORS[part(module)] > FLOORS[part(own)]
    }
    assert upward == DYNAMIC_IMPORTS_ALLOWED.get(own, set()), f"{own} loads {upward} by name"


def test_the_safety_package_shows_its_four_concerns_at_a_glance():
    safety = PACKAGE / "safety"
    packages = sorted(p.name for p in safety.iterdir() if (p / "__init__.py").exists())
    assert packages == ["cbf", "predictive", "traffic", "uncertainty"]
    shared = sorted(p.stem for p in safety.glob("*.py") if p.name != "__init__.py")
    assert shared == [
        "decision", "filter_protocol", "frenet_stages", "ltv_mpc", "matrix_exponential",
        "model_code", "models", "stage_qp", "vehicle_params",
    ]  # fmt: skip
    docstring = ast.get_docstring(ast.parse((safety / "__init__.py").read_text())) or ""
    assert all(f"saferace.safety.{name}" in docstring for name in packages)


def test_relative_imports_are_resolved():
    path = PACKAGE / "safety" / "models.py"
    node = ast.parse("from ..agents import mpc").body[0]
    assert isinstance(node, ast.ImportFrom)
    assert imported_from(path, node) == "saferace.agents"
    package = ast.parse("from . import filter").body[0]
    assert isinstance(package, ast.ImportFrom)
    assert imported_from(PACKAGE / "safety" / "__init__.py", package) == "saferace.safety"
    assert set(DYNAMIC_IMPORTS_ALLOWED) <= MODULES  # no entry outlives its module


def test_no_import_cycles():
    graph = {
        module_name(path): {m for name in imports(path, True) if (m := known(name))}
        for path in SOURCES
    }
    state: dict[str, int] = {}

    def visit(module: str, trail: list[str]) -> None:
        state[module] = 1
        for child in graph.get(module, ()):
            # a package's __init__ importing its own submodules is not a cycle of two modules
            if child == module or (module.startswith(child + ".") and child != "saferace"):
                continue
            if state.get(child) == 1:
                raise AssertionError(" -> ".join([*trail, module, child]))
            if not state.get(child):
                visit(child, [*trail, module])
        state[module] = 2

    for module in sorted(graph):
        if not state.get(module):
            visit(module, [])


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_file_over_the_limit(path: Path):
    lines = len(path.read_text().splitlines())
    assert lines <= MAX_LINES, f"{path.name} has {lines} lines"


CLI_SOURCES = sorted((PACKAGE / "cli").glob("*.py"))


@pytest.mark.parametrize("path", CLI_SOURCES, ids=lambda p: p.name)
def test_the_command_line_only_parses_calls_and_prints(path: Path):
    """No numerical, plotting or learning library in ``cli/``, and short handlers: the work
    is in the library, where other code and the tests can call it."""
    tree = ast.parse(path.read_text())
    libraries = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            libraries |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            libraries.add(node.module.split(".")[0])
    assert not libraries & {"numpy", "torch", "matplotlib", "mujoco", "scipy", "cv2"}
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef) and node.name != "register":
            length = node.end_lineno - node.lineno + 1
            assert length <= 45, f"{node.name} is {length} lines: move its work to the library"
