"""Progress of long work that reaches wherever its output goes.

On a terminal a tqdm bar redraws in place. In a log (standard error piped to a file or a
CI console, where a bar draws nothing useful) each finished unit of work gets one line
instead: what finished, how long it took, its key number, and the time left at the pace so
far. Finer detail (a stage within a unit, each training epoch's loss) goes to the
``saferace`` logger at INFO, which ``saferace -v`` shows.
"""

from __future__ import annotations

import logging
import sys
import time
from types import TracebackType
from typing import TextIO

from tqdm import tqdm

LOGGER = logging.getLogger("saferace")


def duration_words(seconds: float) -> str:
    """``seconds`` as a log line says it: ``42 s``, ``3 min 05 s``, ``1 h 02 min``."""
    seconds = max(0.0, seconds)
    if seconds < 60.0:
        return f"{seconds:.0f} s" if seconds >= 10.0 else f"{seconds:.1f} s"
    minutes, rest = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes} min {rest:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


def _plural(unit: str) -> str:
    return unit + ("es" if unit.endswith(("ch", "sh", "s", "x")) else "s")


class Progress:
    """Progress through ``total`` units (runs, rounds, batches) named ``unit``.

    ``enabled=False`` shows nothing (a caller's ``progress=False``); ``initial`` units were
    done before (a resumed run), and count neither towards the pace nor the lines.
    """

    def __init__(
        self,
        total: int,
        desc: str,
        unit: str,
        *,
        enabled: bool = True,
        initial: int = 0,
        stream: TextIO | None = None,
    ) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = enabled and self.stream.isatty()
        self.logging = enabled and not self.terminal
        self.total, self.desc, self.unit = total, desc, unit
        self.count = self._initial = initial
        self._started = self._last = time.monotonic()
        self._bar = tqdm(
            total=total,
            initial=initial,
            desc=desc,
            unit=unit,
            file=self.stream,
            disable=not self.terminal,
        )

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        self._bar.close()

    def update(self, count: int = 1) -> None:
        """``count`` more units done: the bar moves; a log gets no line (see :meth:`done`)."""
        self._bar.update(count)
        self.count += count

    def done(self, what: str, result: str = "") -> None:
        """One more unit done, ``what`` it was and its ``result`` (its key number): the bar
        moves, and a log gets a line."""
        self.update()
        self.report(what, result)

    def report(self, what: str, result: str = "", time_left: bool = True) -> None:
        """A log line for ``what`` just finished (no unit counted: an epoch within a bar of
        batches), with the time it took, ``result`` and (``time_left``) the time left."""
        now = time.monotonic()
        took, self._last = now - self._last, now
        if not self.logging:
            return
        line = f"{self.desc}: {what} done ({self.count}/{self.total} {_plural(self.unit)})"
        line += f" in {duration_words(took)}" + (f", {result}" if result else "")
        left = self.seconds_left(now) if time_left else None
        if left is not None:
            line += f"; about {duration_words(left)} left"
        print(line, file=self.stream, flush=True)

    def show(self, text: str) -> None:
        """A live reading beside the bar (a speed, a loss); nothing in a log."""
        if self.terminal:
            self._bar.set_postfix_str(text, refresh=False)

    def note(self, text: str) -> None:
        """What the current unit is doing: beside the bar, or at INFO in a log (``-v``)."""
        if self.terminal:
            self._bar.set_postfix_str(text)
        else:
            LOGGER.info("%s: %s", self.desc, text)

    def seconds_left(self, now: float | None = None) -> float | None:
        """The time the units left take at the pace of those done in this process (None
        before the first, and once none is left)."""
        done = self.count - self._initial
        if done <= 0 or self.count >= self.total:
            return None
        elapsed = (time.monotonic() if now is None else now) - self._started
        return elapsed / done * (self.total - self.count)
