"""numba's on-disk cache, dropped when a function's callees in other modules change.

numba keys a cached function on its own source file alone, yet compiles the ``njit``
functions it calls from other modules into it: edit one of those and the caller's cached
machine code runs the old callee, silently (``tests/test_numba_cache.py`` shows it).
:func:`recompiled_when_changed` stamps a function's cache with a digest of its callees'
source files and empties the cache where the stamp differs, so numba compiles afresh.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

Compiled = TypeVar("Compiled")
LOG = logging.getLogger(__name__)

#: The stamp beside a function's cache index: ``NAME.callees`` in numba's cache folder.
STAMP_SUFFIX = ".callees"


def callees_digest(callees: tuple[Any, ...]) -> str:
    """SHA-256 of the source files of the ``njit`` functions ``callees``, in order."""
    digest = hashlib.sha256()
    for callee in callees:
        digest.update(Path(inspect.getfile(callee.py_func)).read_bytes())
    return digest.hexdigest()


def recompiled_when_changed(*callees: Any) -> Callable[[Compiled], Compiled]:
    """Decorate an ``@njit(cache=True)`` function (above the ``njit``) that calls the ``njit``
    functions ``callees`` of other modules: its cache is emptied where their source files
    changed since it was stamped. A cache that cannot be read or written is left to numba
    (which then compiles in memory)."""

    def decorate(dispatcher: Compiled) -> Compiled:
        cache: Any = getattr(dispatcher, "_cache", None)
        if getattr(cache, "cache_path", None) is None:  # not njit, or without cache=True
            raise TypeError(f"{dispatcher!r} is not an njit function with cache=True")
        name = getattr(dispatcher, "__qualname__", type(dispatcher).__name__)
        stamp = Path(cache.cache_path) / f"{name}{STAMP_SUFFIX}"
        digest = callees_digest(callees)
        try:
            if stamp.is_file() and stamp.read_text() == digest:
                return dispatcher
            cache.flush()  # numba's own: an empty index, so the next call compiles
            stamp.parent.mkdir(parents=True, exist_ok=True)
            stamp.write_text(digest)
        except OSError:
            pass
        return dispatcher

    return decorate


def compiled_here(dispatcher: Any) -> bool:
    """Whether numba's disk cache holds an index of ``dispatcher``'s machine code (False
    where it does not, or where it cannot tell): its first call then compiles."""
    cache_file = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    index = getattr(cache_file, "_index_path", None)
    return index is not None and Path(index).is_file()


def announce_compiling(what: str, *dispatchers: Any) -> None:
    """Say, once, that ``what`` is compiled for this machine where a ``dispatcher`` has no
    machine code cached yet: its first run waited 5-14 s without a word before."""
    if not all(compiled_here(dispatcher) for dispatcher in dispatchers):
        LOG.warning("compiling %s for this machine, once: a few seconds", what)
