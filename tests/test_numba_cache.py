"""numba's on-disk cache of a function that calls another module's ``njit`` function: stale
after an edit of the callee as numba keeps it, compiled afresh behind
:func:`~saferace.numba_cache.recompiled_when_changed`, and loaded while nothing changed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from numba import njit

from saferace.numba_cache import callees_digest, recompiled_when_changed
from saferace.safety import frenet_stages, models
from saferace.safety.matrix_exponential import expm_stacked
from saferace.track.path import piece_values

CALLEE = "from numba import njit\n\n\n@njit(cache=True)\ndef f():\n    return 1\n"
CALLER = """from numba import njit

from toy.callee import f
{import_line}

{decorator}
@njit(cache=True)
def g():
    return f() + 10
"""
RUN = "from toy.caller import g; g(); print(g(), sum(g.stats.cache_hits.values()))"


def run_caller(folder: Path) -> tuple[int, int]:
    """``g()`` in a fresh process, and whether it was loaded from the cache (1) or compiled."""
    path = os.pathsep.join(filter(None, [str(folder), os.environ.get("PYTHONPATH")]))
    environment = {**os.environ, "PYTHONPATH": path}
    environment.pop("NUMBA_CACHE_DIR", None)
    output = subprocess.run(
        [sys.executable, "-c", RUN], env=environment, capture_output=True, text=True, check=True
    ).stdout.split()
    return int(output[0]), int(output[1])


def toy_package(folder: Path, stamped: bool) -> Path:
    package = folder / "toy"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "callee.py").write_text(CALLEE)
    import_line = "from saferace.numba_cache import recompiled_when_changed" if stamped else ""
    decorator = "@recompiled_when_changed(f)" if stamped else ""
    (package / "caller.py").write_text(CALLER.format(import_line=import_line, decorator=decorator))
    return package


@pytest.mark.parametrize("stamped", [False, True], ids=["numba alone", "stamped"])
def test_an_edited_callee_is_compiled_into_its_caller_only_when_stamped(
    tmp_path: Path, stamped: bool
):
    package = toy_package(tmp_path, stamped)
    assert run_caller(tmp_path) == (11, 0)  # compiled
    assert run_caller(tmp_path) == (11, 1)  # loaded
    (package / "callee.py").write_text(CALLEE.replace("return 1", "return 2"))
    if stamped:
        assert run_caller(tmp_path) == (12, 0)  # the new callee, compiled
        assert run_caller(tmp_path) == (12, 1)  # and loaded from then on
    else:
        assert run_caller(tmp_path) == (11, 1)  # numba's cache: the old callee's code


def test_saferaces_cross_module_callers_are_stamped():
    """Each cached function that compiles another module's callee into itself carries the
    stamp of that callee's file (written when it was decorated)."""
    for caller, callee in (
        (frenet_stages.stages_along_map, piece_values),
        (frenet_stages._heading_and_curvature, piece_values),
        (models._lagged_zero_order_hold, expm_stacked),
    ):
        stamp = Path(caller._cache.cache_path) / f"{caller.__qualname__}.callees"
        assert stamp.read_text() == callees_digest((callee,))


def test_only_a_cached_njit_function_can_be_stamped():
    def plain() -> int:
        return 1

    with pytest.raises(TypeError, match="not an njit function with cache=True"):
        recompiled_when_changed(piece_values)(plain)
    with pytest.raises(TypeError, match="not an njit function with cache=True"):
        recompiled_when_changed(piece_values)(njit(plain))  # compiled, not cached
