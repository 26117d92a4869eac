"""Sensor and actuator faults named as strings: ``NAME[:KEY=VALUE,...]``.

Every fault acts from ``start`` seconds after the reset for ``duration`` seconds (``inf``:
to the episode's end) at a ``severity`` of 1, 2 or 3 (default 2), which sets its size;
a key given overrides the severity's value. ``blackout:start=3,duration=2`` is the
severity-2 blackout moved and lengthened. The faults and their sizes at severities 1, 2, 3:

========== ========================================================= ===================
fault      what it does                                              size by severity
========== ========================================================= ===================
blackout   black frames                                              ``duration`` 0.5, 1, 2 s
frozen     the last frame before ``start`` repeated                  ``duration`` 0.5, 1, 2 s
dropped    each frame lost with ``probability``, the last repeated   ``probability`` 0.1, 0.2, 0.4
latency    frames ``steps`` control steps late (``random=1``: a       ``steps`` 1, 2, 4
           fresh delay from 0 to ``steps`` each frame)
occlusion  a black square over ``fraction`` of the image, placed     ``fraction`` 0.1, 0.25, 0.5
           at random per episode
flicker    each frame's brightness scaled by ``1 +- amplitude``      ``amplitude`` 0.2, 0.4, 0.7
odometry   ``v_x`` and the yaw rate measured ``1 + bias`` times       ``bias`` 0.02, 0.05, 0.1;
           the truth, each of ``[v_x, v_y, r]`` with Gaussian noise  ``noise`` 0.01, 0.02, 0.05
           of std ``noise`` (m/s, rad/s)
steering   the servo's centre ``offset`` rad to the left             ``offset`` 0.02, 0.04, 0.07
delay      the command applied ``steps`` control steps late          ``steps`` 1, 2, 3
========== ========================================================= ===================

The time faults (blackout, frozen) last ``duration`` from ``start``; the others last to the
episode's end unless ``duration`` is given. Randomness (dropped frames, random latency,
the occlusion's place, flicker, odometry noise) comes from a generator seeded with the
episode's seed: the same seed gives the same faults.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from saferace.errors import SafeRaceError

#: The severities a fault takes, and the one it takes when none is given.
SEVERITIES = (1, 2, 3)
DEFAULT_SEVERITY = 2
#: The keys every fault takes, beside its own.
COMMON_KEYS = ("start", "duration", "severity")


class FaultError(SafeRaceError, ValueError):
    """A fault named or sized in a way it cannot take."""


@dataclass(frozen=True)
class FaultKind:
    """A fault's own keys: each with its values at severities 1, 2, 3 and its bounds
    (``integer`` keys take whole numbers); a ``duration`` among them is how long it lasts
    at each severity (else: to the episode's end)."""

    description: str
    sizes: dict[str, tuple[float, float, float]]
    bounds: dict[str, tuple[float, float]]
    integer: tuple[str, ...] = ()


FAULT_KINDS: dict[str, FaultKind] = {
    "blackout": FaultKind("black frames", {"duration": (0.5, 1.0, 2.0)}, {}),
    "frozen": FaultKind("the last frame repeated", {"duration": (0.5, 1.0, 2.0)}, {}),
    "dropped": FaultKind(
        "frames lost, the last repeated",
        {"probability": (0.1, 0.2, 0.4)},
        {"probability": (0.0, 1.0)},
    ),
    "latency": FaultKind(
        "frames late",
        {"steps": (1, 2, 4), "random": (0, 0, 0)},
        {"steps": (0, 100), "random": (0, 1)},
        integer=("steps", "random"),
    ),
    "occlusion": FaultKind(
        "a black square over part of the image",
        {"fraction": (0.1, 0.25, 0.5)},
        {"fraction": (0.0, 1.0)},
    ),
    "flicker": FaultKind(
        "the exposure flickering", {"amplitude": (0.2, 0.4, 0.7)}, {"amplitude": (0.0, 1.0)}
    ),
    "odometry": FaultKind(
        "odometry biased and noisy",
        {"bias": (0.02, 0.05, 0.1), "noise": (0.01, 0.02, 0.05)},
        {"bias": (-0.5, 0.5), "noise": (0.0, 1.0)},
    ),
    "steering": FaultKind(
        "the steering's centre off", {"offset": (0.02, 0.04, 0.07)}, {"offset": (-0.2, 0.2)}
    ),
    "delay": FaultKind(
        "the command applied late", {"steps": (1, 2, 3)}, {"steps": (0, 100)}, integer=("steps",)
    ),
}


@dataclass(frozen=True)
class Fault:
    """One fault: its ``name``, when it acts (``start_s`` for ``duration_s``), its
    ``severity`` and its sizes (``values``, every key of its kind)."""

    name: str
    start_s: float
    duration_s: float
    severity: int
    values: dict[str, float] = field(hash=False)

    def active(self, time_s: float) -> bool:
        """Whether the fault acts at ``time_s`` after the reset."""
        return self.start_s <= time_s < self.start_s + self.duration_s

    def __getitem__(self, key: str) -> float:
        return self.values[key]

    def spec(self) -> str:
        """The fault as the string that makes it again, every key written out."""
        items = {"start": self.start_s, "duration": self.duration_s, **self.values}
        return f"{self.name}:severity={self.severity}," + ",".join(
            f"{key}={_written(value)}" for key, value in items.items()
        )


def _written(value: float) -> str:
    return "inf" if math.isinf(value) else f"{value:g}"


def parse_fault(text: str | Fault) -> Fault:
    """The fault ``text`` names (``NAME[:KEY=VALUE,...]``, see the module)."""
    if isinstance(text, Fault):
        return text
    if not isinstance(text, str):
        raise FaultError(f"a fault is a string NAME[:KEY=VALUE,...], got {text!r}")
    name, _, assignments = text.strip().partition(":")
    kind = FAULT_KINDS.get(name)
    if kind is None:
        raise FaultError(f"unknown fault {name!r} in {text!r}: use {', '.join(FAULT_KINDS)}")
    entries = [entry.strip() for entry in assignments.split(",") if entry.strip()]
    given: dict[str, float] = {}
    for entry in entries:
        key, equals, value = entry.partition("=")
        key = key.strip()
        if not equals:
            raise FaultError(f"fault {text!r}: write {name}:KEY=VALUE,... (got {entry!r})")
        if key not in (*COMMON_KEYS, *kind.sizes):
            keys = ", ".join(dict.fromkeys((*COMMON_KEYS, *kind.sizes)))
            raise FaultError(f"fault {text!r}: {name} takes {keys}, not {key!r}")
        if key in given:
            raise FaultError(f"fault {text!r}: {key} given twice")
        try:
            given[key] = float(value)
        except ValueError:
            raise FaultError(f"fault {text!r}: {key} must be a number, got {value!r}") from None
    return _fault(name, kind, given, text)


def _fault(name: str, kind: FaultKind, given: dict[str, float], text: str) -> Fault:
    severity = given.pop("severity", DEFAULT_SEVERITY)
    if severity not in SEVERITIES:
        raise FaultError(f"fault {text!r}: severity is one of 1, 2, 3, got {severity:g}")
    level = int(severity) - 1
    values = {key: float(sizes[level]) for key, sizes in kind.sizes.items()}
    start_s = given.pop("start", 0.0)
    duration_s = given.pop("duration", values.pop("duration", math.inf))
    values.update(given)
    if not (math.isfinite(start_s) and start_s >= 0.0):
        raise FaultError(f"fault {text!r}: start is seconds after the reset, >= 0")
    if not duration_s > 0.0:
        raise FaultError(f"fault {text!r}: duration must be above 0 s (inf: to the end)")
    for key, (low, high) in kind.bounds.items():
        value = values[key]
        if not low <= value <= high:
            raise FaultError(f"fault {text!r}: {key} must lie in [{low:g}, {high:g}]")
        if key in kind.integer and value != int(value):
            raise FaultError(f"fault {text!r}: {key} is a whole number, got {value:g}")
    return Fault(name, start_s, duration_s, int(severity), values)


def parse_faults(texts: Iterable[str | Fault] | str | None) -> tuple[Fault, ...]:
    """The faults of a list of strings (or one string); at most one of each name."""
    if texts is None:
        return ()
    if isinstance(texts, str):
        texts = [texts]
    faults = tuple(parse_fault(text) for text in texts)
    names = [fault.name for fault in faults]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise FaultError(f"fault(s) {', '.join(twice)} named twice: give each once")
    return faults


def canonical_faults(texts: Iterable[str | Fault] | str | None) -> tuple[str, ...]:
    """The faults of ``texts`` written one way (every key, sorted by name): the same faults
    written otherwise are the same strings, what a resumed table matches its runs by."""
    return tuple(sorted(fault.spec() for fault in parse_faults(texts)))
