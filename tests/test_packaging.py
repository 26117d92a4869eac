"""The wheel installs and works outside the repository; optional parts name their extra.

The default test installs the built wheel with ``--no-deps`` into a fresh virtual
environment that sees this environment's packages through a filtered folder of links (all
but saferace's own editable install), so that it runs in seconds; the slow one installs the
wheel with its dependencies, as ``pip install saferace`` does.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import sysconfig
import time
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Drives the expert for a lap of a built-in track in whatever environment runs it, and
#: prints where saferace was imported from.
LAP = """
import gymnasium
import saferace
from saferace.eval.agents import make_agent

env = gymnasium.make("saferace/RacingLine-v0", track="oval")
agent = make_agent("expert", env)
observation, info = env.reset(seed=0)
for _ in range(400):
    observation, _, terminated, truncated, info = env.step(agent.act(observation, info))
    if terminated or truncated:
        break
env.close()
assert info["lap_completed"] and not terminated, info
print("saferace from", saferace.__file__)
"""


def clean_env() -> dict[str, str]:
    """This process's environment without anything that points Python at the repository."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("PYTHON")}
    env.pop("VIRTUAL_ENV", None)
    return env


def run(*command: str | Path, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    result = subprocess.run(
        [str(part) for part in command],
        cwd=cwd, env=clean_env(), capture_output=True, text=True, timeout=timeout, check=False,
    )  # fmt: skip
    assert result.returncode == 0, f"{command}:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel, built from an sdist of the repository (so the sdist is checked too)."""
    out = tmp_path_factory.mktemp("dist")
    result = run(sys.executable, "-m", "build", "--no-isolation", "--outdir", out, ROOT, cwd=out)
    log = result.stdout + result.stderr
    assert "deprecat" not in log.lower(), log
    (path,) = out.glob("saferace-*.whl")
    return path


def fresh_venv(folder: Path, with_pip: bool) -> tuple[Path, Path]:
    """A new virtual environment at ``folder``: its ``bin`` and its site-packages."""
    options = [] if with_pip else ["--without-pip"]
    run(sys.executable, "-m", "venv", *options, folder, cwd=folder.parent)
    python = folder / "bin" / "python"
    purelib = run(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])",
                  cwd=folder.parent).stdout.strip()  # fmt: skip
    return folder / "bin", Path(purelib)


def check_installed_saferace(bin_dir: Path, site_packages: Path, cwd: Path) -> None:
    """A lap of the expert on a built-in track and a command, from the installed wheel."""
    lap = run(bin_dir / "python", "-c", LAP, cwd=cwd)
    imported_from = Path(lap.stdout.split("saferace from", 1)[1].strip())
    assert imported_from.is_relative_to(site_packages), imported_from
    info = run(bin_dir / "saferace", "track-info", "lab", cwd=cwd)
    assert "lab" in info.stdout


def values(metadata: list[str], field: str) -> list[str]:
    return [line.split(":", 1)[1].strip() for line in metadata if line.startswith(f"{field}:")]


def test_wheel_metadata_keeps_heavy_parts_optional(wheel: Path):
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        (metadata,) = [name for name in names if name.endswith(".dist-info/METADATA")]
        lines = archive.read(metadata).decode().splitlines()
    requires = values(lines, "Requires-Dist")
    for package in ("ray", "minari", "stable-baselines3", "mkdocs"):
        mine = [req for req in requires if req.lower().startswith(package)]
        assert mine, f"{package} is in no extra"
        assert all("extra ==" in req for req in mine), mine
    assert {"ray", "minari", "sb3", "docs", "dev"} <= set(values(lines, "Provides-Extra"))
    assert "License-Expression: MIT" in lines
    assert any(name.startswith("saferace/assets/tracks/") for name in names)


def test_wheel_works_outside_the_repository(wheel: Path, tmp_path: Path):
    """Installed without dependencies into a fresh environment that sees this one's
    packages through links to all of them but saferace (whose editable install must not
    load: the test checks saferace comes from the fresh site-packages)."""
    bin_dir, site_packages = fresh_venv(tmp_path / "fresh", with_pip=False)
    shared = tmp_path / "shared"  # this environment's packages, less saferace's
    shared.mkdir()
    for entry in Path(sysconfig.get_paths()["purelib"]).iterdir():
        name = entry.name.lower()
        if not (name.startswith(("saferace", "__editable__")) or name.endswith(".pth")):
            (shared / entry.name).symlink_to(entry)
    (site_packages / "dev_packages.pth").write_text(f"{shared}\n")
    run(bin_dir / "python", "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", wheel,
        cwd=tmp_path)  # fmt: skip
    check_installed_saferace(bin_dir, site_packages, cwd=tmp_path)


@pytest.mark.slow
def test_wheel_installs_with_its_dependencies(wheel: Path, tmp_path: Path):
    """``pip install saferace`` as a user does it: the core works, Ray is not there."""
    bin_dir, site_packages = fresh_venv(tmp_path / "fresh", with_pip=True)
    started = time.perf_counter()
    run(bin_dir / "python", "-m", "pip", "install", "--quiet", wheel, cwd=tmp_path, timeout=1800)
    print(f"pip install of the wheel with its dependencies: {time.perf_counter() - started:.0f} s")
    check_installed_saferace(bin_dir, site_packages, cwd=tmp_path)
    missing = subprocess.run(
        [bin_dir / "python", "-c", "import ray"], env=clean_env(), capture_output=True, check=False
    )
    assert missing.returncode != 0, "ray came with the core install"
    result = subprocess.run(
        [bin_dir / "saferace", "benchmark", "--agent", "expert", "--ray", "--out",
         tmp_path / "bench.json"],
        cwd=tmp_path, env=clean_env(), capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert "pip install 'saferace[ray]'" in result.stderr
    assert "Traceback" not in result.stderr


def run_without(modules: tuple[str, ...], code: str, cwd: Path) -> subprocess.CompletedProcess:
    """``python -c code`` in this environment with ``modules`` blocked from importing."""
    block = "import sys\n" + "".join(f"sys.modules[{name!r}] = None\n" for name in modules)
    return subprocess.run(
        [sys.executable, "-c", block + code],
        cwd=cwd, env=clean_env(), capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip


@pytest.mark.slow  # 15 s (the extras' lazy loading: test_the_core_imports_none_of_the_extras)
def test_rerun_and_captum_load_only_to_record_and_to_draw_gradcam(tmp_path: Path):
    """Driving without a recording and training need neither (rerun-sdk is 170 MB, and a
    GPU machine's offline install leaves it behind)."""
    result = run_without(
        ("rerun", "captum"),
        "from saferace.cli import main\n"
        "import saferace.learning.commands\n"
        "sys.exit(main(['drive', '--agent', 'expert', '--track', 'lab']))",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    recording = run_without(
        ("rerun",),
        "from saferace.cli import main\n"
        "main(['drive', '--agent', 'expert', '--track', 'lab', "
        "'--rerun', 'x.rrd'])",
        cwd=tmp_path,
    )
    assert recording.returncode != 0 and "rerun" in recording.stderr


def test_a_command_needing_ray_names_the_extra(tmp_path: Path):
    out = tmp_path / "bench.json"
    result = run_without(
        ("ray",),
        "from saferace.cli import main\n"
        f"sys.exit(main(['benchmark', '--agent', 'expert', '--ray', '--out', {str(out)!r}]))",
        cwd=tmp_path,
    )
    assert result.returncode == 2, result.stderr
    assert "needs the optional package ray: pip install 'saferace[ray]'" in result.stderr
    assert "Traceback" not in result.stderr
    assert not out.exists()


def test_minari_export_without_minari_names_the_extra(tmp_path: Path):
    from saferace.errors import SafeRaceError
    from saferace.extras import MissingExtraError, require

    result = run_without(
        ("minari",),
        "from saferace.learning.minari_export import export_minari\n"
        "from saferace.errors import SafeRaceError\n"
        "try:\n    export_minari(['nowhere'], 'saferace/x-v0')\n"
        "except SafeRaceError as error:\n    print(error)",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "pip install 'saferace[minari]'" in result.stdout
    assert issubclass(MissingExtraError, SafeRaceError)
    assert require("json", "none", "reading JSON").loads("1") == 1


def test_the_core_imports_none_of_the_extras(tmp_path: Path):
    """The tasks, the expert, the filter and the learned driver load without them."""
    result = run_without(
        ("ray", "minari", "stable_baselines3", "mkdocs"),
        "import gymnasium, saferace\n"
        "from saferace.agents.mpc import MPCExpert\n"
        "from saferace.safety.cbf.filter import SafetyFilter\n"
        "from saferace.learning.agent import LearnedAgent\n"
        "from saferace.cli import build_parser\n"
        "build_parser()\n"
        "gymnasium.make('saferace/CenterLine-v0', track='oval').close()",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr


def test_getting_started_names_every_make_target_and_what_make_test_runs():
    root = Path(__file__).resolve().parents[1]
    makefile = (root / "Makefile").read_text()
    targets = re.search(r"^\.PHONY: (.+)$", makefile, re.MULTILINE)
    assert targets is not None
    table = (root / "docs" / "getting-started.md").read_text()
    rows = {line.split("|")[1].strip(): line for line in table.splitlines() if "| `make " in line}
    assert {f"`make {target}`" for target in targets.group(1).split()} <= set(rows)
    recipe = makefile.split("\ntest: setup\n")[1].split("\n\n")[0]
    for tool in ("ruff check", "ruff format --check", "mypy saferace", "mkdocs build", "pytest"):
        assert tool in recipe, tool
    for named in ("ruff check", "ruff format --check", "mypy saferace", "docs", "fast tests"):
        assert named in rows["`make test`"], named


def test_the_command_reference_is_rendered_in_place_of_the_note_for_raw_readers():
    spec = importlib.util.spec_from_file_location("hook", ROOT / "docs/hooks/commands.py")
    assert spec is not None and spec.loader is not None
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    raw = (ROOT / "docs" / "reference" / "commands.md").read_text()
    note = raw.split(hook.MARKER)[1].split(hook.END_MARKER)[0]
    assert "saferace --help" in note and "make docs" in note  # GitHub shows this
    built = hook.with_commands(raw, "REFERENCE")
    assert "REFERENCE" in built and "saferace --help" not in built and hook.MARKER not in built
    assert built.startswith(raw.split(hook.MARKER)[0])
    with pytest.raises(ValueError, match="lost its markers"):
        hook.with_commands(raw.replace(hook.END_MARKER, ""), "REFERENCE")


RESULTS = ROOT / "docs" / "results"
INCLUDE = re.compile(r'^--8<-- "(results/[^"]+)"$', re.M)
STAMP = re.compile(r"^\*\*Measured\*\* at commit `[0-9a-f]{7,}`[^;]*; [^;]+; by `[^`]+`\.$")


def test_every_results_file_the_pages_include_exists_and_carries_its_stamp():
    included = [name for page in RESULTS.glob("*.md") for name in INCLUDE.findall(page.read_text())]
    assert len(included) >= 6
    for name in included:
        path = ROOT / "docs" / name
        assert path.is_file(), f"{name} is included but missing: docs/results/sources.md says how"
        first = path.read_text().splitlines()[0]
        assert STAMP.match(first), f"{name} has no stamp: {first!r}"
        assert f"`{name.removeprefix('results/')}`" in (RESULTS / "sources.md").read_text()


def test_the_docs_link_only_results_pages_that_exist_and_date_no_numbers_outside_the_changelog():
    pages = [*(ROOT / "docs").glob("*.md"), ROOT / "README.md"]
    for page in pages:
        text = page.read_text()
        for target in re.findall(r"\]\(((?:docs/)?results/[^)#]+)", text):
            base = ROOT if target.startswith("docs/") else ROOT / "docs"
            assert (base / target).is_file(), f"{page.name} links {target}, which is missing"
        if page.name != "changelog.md":
            assert not re.search(r"`[0-9a-f]{7}`", text), f"{page.name} dates a number by commit"
        assert "written locally" not in text, page.name


def test_a_results_file_gets_one_stamp_and_its_tables_stand_apart_from_their_captions():
    spec = importlib.util.spec_from_file_location("docs_results", ROOT / "scripts/docs_results.py")
    assert spec is not None and spec.loader is not None
    docs_results = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(docs_results)
    output = "caption:\n| a | b |\n|---|---|\n| 1 | 2 |\ntarget met\nother target met\n"
    once = docs_results.stamped(output, "**Measured** at commit `abc1234`; m; by `x`.", csv=False)
    assert once.splitlines() == [
        "**Measured** at commit `abc1234`; m; by `x`.", "", "caption:", "",
        "| a | b |", "|---|---|", "| 1 | 2 |", "", "target met", "", "other target met",
    ]  # fmt: skip
    again = docs_results.stamped(once, "**Measured** at commit `def5678`; m; by `x`.", csv=False)
    assert again == once.replace("abc1234", "def5678")  # the old stamp replaced, no blank added
