"""The examples run as a user would run them (slow: they train), and say which extra they
need when it is missing."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_sb3_example_without_sb3_names_the_extra(tmp_path: Path):
    blocked = (
        "import runpy, sys\n"
        "sys.modules['stable_baselines3'] = None\n"
        f"sys.argv = ['sb3_ppo_through_filter.py', '--out', {str(tmp_path)!r}]\n"
        f"runpy.run_path({str(EXAMPLES / 'sb3_ppo_through_filter.py')!r}, run_name='__main__')"
    )
    result = subprocess.run(
        [sys.executable, "-c", blocked], capture_output=True, text=True, timeout=300, check=False
    )
    assert result.returncode == 1
    assert "pip install 'saferace[sb3]'" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.slow
def test_sb3_ppo_trains_through_the_filter_and_drives(tmp_path: Path):
    pytest.importorskip("stable_baselines3", reason="needs saferace[sb3]")
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / "sb3_ppo_through_filter.py"), "--timesteps", "512",
         "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    trained = re.search(r"trained (\d+) steps .* intervened in ([\d.]+)%", result.stdout)
    assert trained and int(trained.group(1)) >= 512
    assert 0.0 < float(trained.group(2)) <= 100.0  # the filter was in the loop
    assert "evaluation:" in result.stdout
    assert (tmp_path / "ppo_saferace.zip").stat().st_size > 10_000


def test_my_agent_loads_from_the_current_folder_through_the_console_script(tmp_path: Path):
    """``saferace eval --agent my_agent:make`` beside ``my_agent.py``, as the docs show: the
    console script (unlike ``python -m``) does not put the current folder on the path."""
    shutil.copy(EXAMPLES / "my_agent.py", tmp_path)
    console_script = Path(sys.executable).parent / "saferace"
    result = subprocess.run(
        [str(console_script), "eval", "--agent", "my_agent:make", "--track", "lab",
         "--max-seconds", "2", "--out", "rows.jsonl"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    [row] = [json.loads(line) for line in (tmp_path / "rows.jsonl").read_text().splitlines()]
    assert row["agent"] == "my_agent:make" and row["summary"]["mean_abs_deviation_m"] < 0.1
