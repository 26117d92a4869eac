"""Run the ``saferace`` command as a user would, in a fresh Python process; read a child
process's first line without hanging on a child that never prints it."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout

#: How long a child process may take to print its first line before it is killed.
FIRST_LINE_TIMEOUT_S = 300.0


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "saferace", *args], capture_output=True, text=True, check=False
    )


def first_line(process: subprocess.Popen, timeout_s: float = FIRST_LINE_TIMEOUT_S) -> str:
    """The first line ``process`` prints on its piped stdout, stripped; a process that
    prints none within ``timeout_s`` is killed, and its line is what it had printed."""
    assert process.stdout is not None, "start the process with stdout=subprocess.PIPE"
    with ThreadPoolExecutor(max_workers=1) as pool:
        line = pool.submit(process.stdout.readline)
        try:
            return line.result(timeout=timeout_s).strip()
        except FutureTimeout:
            process.kill()  # ends the read: the pipe closes
            return line.result().strip()
