"""Run the ``saferace`` command as a user would, in a fresh Python process."""

from __future__ import annotations

import subprocess
import sys


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "saferace", *args], capture_output=True, text=True, check=False
    )
