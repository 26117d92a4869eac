"""The tasks' reference lines, computed once per track geometry and process."""

from __future__ import annotations

from collections.abc import Callable

from saferace.errors import SafeRaceError
from saferace.track import Track
from saferace.track.raceline import ReferenceLine, center_line, racing_line


def reference_line(track: Track, kind: str) -> ReferenceLine:
    """The task's reference line: ``"center"`` or ``"racing"``.

    Computed once per track geometry and process (a racing line of a 450 m circuit takes
    a minute or two, and evaluations make one env per run); lines are never modified.
    """
    if kind not in _REFERENCE_LINES:
        raise SafeRaceError(f"unknown reference line {kind!r}: use 'center' or 'racing'")
    key = (track.fingerprint, kind)
    if key not in _COMPUTED_LINES:
        if len(_COMPUTED_LINES) >= _MAX_COMPUTED_LINES:
            _COMPUTED_LINES.pop(next(iter(_COMPUTED_LINES)))
        _COMPUTED_LINES[key] = _REFERENCE_LINES[kind](track)
    return _COMPUTED_LINES[key]


_REFERENCE_LINES: dict[str, Callable[[Track], ReferenceLine]] = {
    "center": center_line,
    "racing": racing_line,
}
_MAX_COMPUTED_LINES = 16
_COMPUTED_LINES: dict[tuple[str, str], ReferenceLine] = {}  # oldest first
