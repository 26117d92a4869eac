"""Where SafeRace keeps what it builds once and reuses: ``~/.cache/saferace``, or the
folder :data:`CACHE_VARIABLE` names (the generic perception model, compiled networks)."""

from __future__ import annotations

import os
from pathlib import Path

#: Where caches live: this variable, or ``~/.cache/saferace``.
CACHE_VARIABLE = "SAFERACE_CACHE"


def cache_root() -> Path:
    return Path(os.environ.get(CACHE_VARIABLE) or "~/.cache/saferace").expanduser()
