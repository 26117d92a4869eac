"""Optional heavy packages, imported when a command needs them.

``pip install saferace`` gives the tasks, the expert, the safety filter and the learned
driver. Ray, Minari, Stable-Baselines3, PyAV (H.264 videos) and the documentation tools
are extras (``pip install 'saferace[ray]'`` and so on); :func:`require` imports one, or
says which extra to install.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from saferace.errors import SafeRaceError


class MissingExtraError(SafeRaceError, ImportError):
    """An optional package a command needs is not installed; the message names the extra."""


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """``module`` imported; if it is missing, a :class:`MissingExtraError` saying that
    ``purpose`` needs it and to ``pip install 'saferace[extra]'``."""
    package = module.partition(".")[0]
    try:
        return importlib.import_module(module)
    except ImportError as error:
        missing = (error.name or "").partition(".")[0]
        broken = "" if missing == package else f" (importing it failed: {error})"
        raise MissingExtraError(
            f"{purpose} needs the optional package {package}{broken}: "
            f"pip install 'saferace[{extra}]'"
        ) from None
