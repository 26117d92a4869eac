"""The safety filters' protocol: a fixed, versioned suite that ranks filters, not drivers.

Filter protocol v1 (``saferace/assets/benchmark/filters/v1/suite.json``): fixed drivers
(``drift``, ``weave``, ``speeding`` and the expert MPC) each drive one lap of the racing
line, at most 30 s, on the six tracks of the drivers' benchmark (the four built-in ones
and its two evaluation tracks) behind the filter, under each perception condition: the
true state, a noisy one (the noisy oracle), and the entry's perception (by default the
generic model) at look severities 0, 2 and 4, and at severity 0 with its frames two steps
(100 ms) late from 3 s on, or with the camera blacked out for 1 s at 3 s. Then the traffic
set: the ``Overtake`` task behind a car at 80% of the line's speed that brakes hard every
few seconds, under the true state and the perception at severity 0. 216 runs per entry.
With ``--circuits DIR``, a folder of the F1TENTH racetracks' centre lines (not shipped:
their licence is not ours; the suite pins each file's sha256), 30 s of three circuits as
given (2.2 m lanes) under the true state and the perception, 24 runs more: such an entry
ranks among those with circuits.

An **entry** is a filter (``none``, ours with its settings, or ``MODULE:FACTORY``) and a
perception (``generic[:RECIPE]``, ``learned:CKPT`` or ``MODULE:FACTORY``) that it is fed in
the perceived conditions.

A run's score, from 0 to 1, puts safety first: a run in which the car was outside its lane
for any time, or caused a collision, scores below 0.5,

    0.5 * exp(-time_outside_lane_s / 1 s) * collision_factor ** at_fault_collisions,

every run without either at least 0.5,

    0.5 + 0.5 * (0.8 * liveness + 0.2 * fidelity),

with ``liveness`` the run's mean speed over the expert's lap alone on the track (at most
1: a standstill costs here) and ``fidelity`` one less the filter's mean corrections, each
over its actuator's scale (``correction_scales``: how little it changed the driver). A run
whose filter raised scores 0. The entry's **score** is 100 times the mean over its runs.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from saferace.errors import SafeRaceError
from saferace.eval.runner import file_sha256

FILTER_SUITE_VERSION = 1
OUTSIDE_SCALE_S = 1.0  # below the floor, the score falls by 1/e per second outside
SAFE_FLOOR = 0.5  # every safe run scores at least this, every unsafe one less
LIVENESS_WEIGHT = 0.8  # of the safe runs' share above the floor; the rest is fidelity
STATES = ("true", "noisy", "perceived")


@dataclass(frozen=True)
class Condition:
    """What the filter's state source is in a run: the ``state`` (``true``, ``noisy``
    with standard deviations ``noise`` ``(e_y_m, e_psi_rad)``, or ``perceived`` by the
    entry's perception), the scene's ``look`` severity (None: the plain scene) and the
    sensor ``faults`` (:mod:`saferace.faults`) of the run."""

    state: str
    noise: tuple[float, float] | None = None
    look: int | None = None
    faults: tuple[str, ...] = ()

    @property
    def randomize(self) -> str | None:
        """The env's ``randomize`` of the look."""
        return None if self.look is None else f"severity-{self.look}"


@dataclass(frozen=True)
class FilterRunSpec:
    """One run of the filter protocol: ``driver`` on ``track`` under ``condition``, among
    the traffic set's ``opponents`` where named."""

    driver: str
    track: str
    condition: str
    opponents: str | None = None

    @property
    def key(self) -> str:
        """``DRIVER/TRACK/CONDITION[/OPPONENTS]``: the run's name in rows and messages."""
        key = f"{self.driver}/{self.track}/{self.condition}"
        return key if self.opponents is None else f"{key}/{self.opponents}"

    @classmethod
    def of_row(cls, row: dict) -> FilterRunSpec:
        """The run a row was driven for."""
        opponents = row.get("opponents")
        return cls(
            str(row["driver"]),
            str(row["track"]),
            str(row["condition"]),
            None if opponents is None else str(opponents),
        )


@dataclass(frozen=True)
class FilterSuite:
    """A version of the filter protocol (see the module docstring)."""

    version: int
    drivers: tuple[str, ...]
    tracks: tuple[str, ...]
    task: str
    seed: int
    laps: int
    max_seconds: float
    conditions: dict[str, Condition]
    traffic_task: str
    opponents: dict[str, tuple[str, ...]]
    traffic_conditions: tuple[str, ...]
    collision_factor: float
    correction_scales: tuple[float, float]
    expert_lap_time_s: dict[str, float]
    folder: Path
    circuits: dict[str, str]
    circuit_conditions: tuple[str, ...]
    circuits_folder: Path | None = None

    def with_circuits(self, folder: str | Path) -> FilterSuite:
        """The suite with its circuits' runs, their centre lines read from ``folder`` (the
        F1TENTH racetracks' ``NAME.csv``, there or in the racetracks' own subfolder, each
        with the sha256 the suite pins)."""
        suite = dataclasses.replace(self, circuits_folder=Path(folder).expanduser().resolve())
        for name, digest in self.circuits.items():
            path = Path(suite.track_argument(name))
            if not path.is_file():
                raise SafeRaceError(
                    f"circuit {name}: no {path} (give the folder of the F1TENTH racetracks' "
                    "centre lines)"
                )
            if file_sha256(path) != digest:
                raise SafeRaceError(
                    f"circuit {name}: {path} is not the protocol's (its sha256 is "
                    f"{file_sha256(path)[:12]}, the protocol's {digest[:12]})"
                )
        return suite

    def track_argument(self, track: str) -> str:
        """A built-in track's name, or the path of one of the suite's own tracks or of its
        circuits (``NAME.csv`` in the circuits' folder, or in its subfolder named before the
        first ``_``, as the racetracks' repository keeps them)."""
        if track in self.circuits:
            if self.circuits_folder is None:
                raise SafeRaceError(f"circuit {track}: no folder of circuits given (--circuits)")
            flat = self.circuits_folder / f"{track}.csv"
            nested = self.circuits_folder / track.split("_")[0] / f"{track}.csv"
            return str(nested if not flat.is_file() and nested.is_file() else flat)
        path = self.folder / f"{track}.csv"
        return str(path) if path.exists() else track

    def runs(self) -> list[FilterRunSpec]:
        """Every run of the protocol: the lane set's, the traffic set's, then, with a
        folder of circuits, the circuits'."""
        lane = [
            FilterRunSpec(driver, track, condition)
            for track in self.tracks
            for condition in self.conditions
            for driver in self.drivers
        ]
        traffic = [
            FilterRunSpec(driver, track, condition, opponents)
            for track in self.tracks
            for opponents in self.opponents
            for condition in self.traffic_conditions
            for driver in self.drivers
        ]
        if self.circuits_folder is None:
            return lane + traffic
        return (
            lane
            + traffic
            + [
                FilterRunSpec(driver, circuit, condition)
                for circuit in self.circuits
                for condition in self.circuit_conditions
                for driver in self.drivers
            ]
        )

    def task_of(self, spec: FilterRunSpec) -> str:
        """The task a run drives: the lane's, or among opponents the traffic set's."""
        return self.task if spec.opponents is None else self.traffic_task


def filter_suite_folder(version: int = FILTER_SUITE_VERSION) -> Path:
    """Where the filter protocol of ``version`` ships (its suite.json and tracks)."""
    return Path(str(resources.files("saferace.assets").joinpath(f"benchmark/filters/v{version}")))


def load_filter_suite(version: int = FILTER_SUITE_VERSION) -> FilterSuite:
    """The filter protocol of ``version`` as shipped in the package."""
    folder = filter_suite_folder(version)
    path = folder / "suite.json"
    if not path.exists():
        raise SafeRaceError(f"no filter protocol version {version} in this SafeRace ({path})")
    data = json.loads(path.read_text())
    traffic = data["traffic"]
    return FilterSuite(
        version=data["version"],
        drivers=tuple(data["drivers"]),
        tracks=tuple(data["tracks"]),
        task=data["task"],
        seed=data["seed"],
        laps=data["laps"],
        max_seconds=data["max_seconds"],
        conditions={
            name: Condition(
                entry["state"],
                None if "noise" not in entry else tuple(entry["noise"]),
                entry.get("look"),
                tuple(entry.get("faults", ())),
            )
            for name, entry in data["conditions"].items()
        },
        traffic_task=traffic["task"],
        opponents={name: tuple(specs) for name, specs in traffic["opponents"].items()},
        traffic_conditions=tuple(traffic["conditions"]),
        collision_factor=data["collision_factor"],
        correction_scales=tuple(data["correction_scales"]),
        expert_lap_time_s=data["expert_lap_time_s"],
        folder=folder,
        circuits=data["circuits"]["sha256"],
        circuit_conditions=tuple(data["circuits"]["conditions"]),
    )


def scored_filter_run(measurements: dict, spec: FilterRunSpec, suite: FilterSuite) -> dict:
    """A run's derived fields from its measurements and the suite's expert reference (never
    from a score carried in a row): its liveness, fidelity, whether it was safe, and its
    score (see the module docstring)."""
    expert_lap_s = suite.expert_lap_time_s[spec.track]
    completion, driven_s = measurements["completion"], measurements["driven_s"]
    speed_ratio = completion * suite.laps * expert_lap_s / driven_s if driven_s else 0.0
    liveness = min(1.0, speed_ratio)
    steer_scale, accel_scale = suite.correction_scales
    steer = measurements["mean_steer_correction_rad"] or 0.0
    accel = measurements["mean_accel_correction_mps2"] or 0.0
    fidelity = min(1.0, max(0.0, 1.0 - 0.5 * (steer / steer_scale + accel / accel_scale)))
    outside_s = measurements["time_outside_lane_s"]
    collisions = measurements.get("at_fault_collisions") or 0
    safe = outside_s == 0.0 and collisions == 0
    if measurements.get("filter_error") is not None:
        score = 0.0
    elif safe:
        share = LIVENESS_WEIGHT * liveness + (1.0 - LIVENESS_WEIGHT) * fidelity
        score = SAFE_FLOOR + (1.0 - SAFE_FLOOR) * share
    else:
        score = (
            SAFE_FLOOR * math.exp(-outside_s / OUTSIDE_SCALE_S) * suite.collision_factor**collisions
        )
    lap_time_s = measurements["lap_time_s"]
    return {
        "expert_lap_time_s": expert_lap_s,
        "lap_time_ratio": None if lap_time_s is None else lap_time_s / expert_lap_s,
        "liveness": liveness,
        "fidelity": fidelity,
        "safe": safe,
        "score": score,
    }


def filter_totals(rows: list[dict], suite: FilterSuite) -> dict:
    """The entry's score and totals from its rows' scores and measurements: the score over
    all runs and per state (true, noisy, perceived), the runs that left the lane, the time
    outside and at-fault collisions, the longest standstill, the mean intervention rate and
    the clipped answers and raising runs of the filter."""

    def score(selected: list[dict]) -> float | None:
        return 100.0 * sum(row["score"] for row in selected) / len(selected) if selected else None

    def of_state(state: str) -> list[dict]:
        return [row for row in rows if suite.conditions[row["condition"]].state == state]

    rates = [row["intervention_rate"] for row in rows if row["intervention_rate"] is not None]
    return {
        "score": score(rows),
        **{f"score_{state}": score(of_state(state)) for state in STATES},
        "runs_outside": sum(row["time_outside_lane_s"] > 0.0 for row in rows),
        "time_outside_lane_s": float(sum(row["time_outside_lane_s"] for row in rows)),
        "time_outside_true_state_s": float(
            sum(row["time_outside_lane_s"] for row in of_state("true"))
        ),
        "at_fault_collisions": sum(row.get("at_fault_collisions") or 0 for row in rows),
        "longest_standstill_s": max(row["longest_standstill_s"] for row in rows),
        "intervention_rate": sum(rates) / len(rates) if rates else None,
        "clipped_steps": sum(row["clipped_steps"] or 0 for row in rows),
        "filter_errors": sum(row["filter_error"] is not None for row in rows),
    }
