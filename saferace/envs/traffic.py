"""Opponent cars in a racing task: where they start, who drives them, what they do.

An env with opponents has one more rc10 per opponent in its scene (``car1/``, ``car2/``...).
Each opponent is driven by a seeded policy from ground truth (:mod:`saferace.agents.opponents`,
loaded by entry point on first use, as gymnasium loads envs), or from outside
(``"external"``: the PettingZoo env's other learners). The ego car's agent sees the
opponents through its camera; ``info`` has their states and the collisions.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from saferace.envs.car_io import CarIO
from saferace.envs.collisions import Collision, CollisionMonitor
from saferace.envs.drivetrain import ackermann_angles, rate_limited, wheel_torques
from saferace.envs.scene import car_prefix
from saferace.errors import SafeRaceError
from saferace.track.frenet import wrap_arc

#: Policies that drive an opponent (``saferace.agents.opponents``), and ``external``: the
#: caller gives its actions (:meth:`Traffic.set_external_actions`).
OPPONENT_POLICIES = (
    "expert",
    "racer",
    "pure-pursuit",
    "lane-changer",
    "blocker",
    "braking",
    "external",
)
EXTERNAL = "external"
#: The ego car's name in collisions and in the other cars' view (opponents are car1, car2...).
EGO = "car0"
_OPPONENT_FACTORY = "saferace.agents.opponents:make_opponent"
#: Where opponents start if not told: this far apart, the first this far ahead of the ego (m).
DEFAULT_GAP_M = 3.0


@dataclass(frozen=True)
class OpponentSpec:
    """One opponent: its policy, where it starts, and how it drives.

    ``gap_m``: its start's arc length ahead of the ego car's (negative: behind; default
    ``DEFAULT_GAP_M`` times its number). ``start_offset_m``: its lateral offset there
    (positive left). ``speed_factor``: the fraction of its line's speed profile it drives.
    ``lateral_offset_m``: the pure pursuit's offset from the centre line, the lane changer's
    lanes and the blocker's cover (positive left, clipped to the lane).
    """

    policy: str = "expert"
    gap_m: float | None = None
    start_offset_m: float = 0.0
    speed_factor: float = 0.8
    lateral_offset_m: float = 0.25

    def __post_init__(self) -> None:
        if self.policy not in OPPONENT_POLICIES:
            raise SafeRaceError(
                f"unknown opponent policy {self.policy!r}: use {', '.join(OPPONENT_POLICIES)}"
            )
        if not 0.0 < self.speed_factor <= 2.0:
            raise SafeRaceError(f"speed_factor must be in (0, 2], got {self.speed_factor}")
        for name in ("start_offset_m", "lateral_offset_m"):
            if abs(getattr(self, name)) > 2.0:
                raise SafeRaceError(f"{name} must be within +-2 m, got {getattr(self, name)}")


def opponent_specs(values: Sequence[Any] | None) -> tuple[OpponentSpec, ...]:
    """Opponents from specs, dicts of their fields, or strings ``POLICY[:FIELD=VALUE,...]``
    (``"blocker"``, ``"expert:speed_factor=0.8,gap_m=2"``); gaps default to 3 m apart."""
    specs = []
    for index, value in enumerate(values or (), start=1):
        spec = _opponent_spec(value)
        if spec.gap_m is None:
            spec = dataclasses.replace(spec, gap_m=DEFAULT_GAP_M * index)
        specs.append(spec)
    return tuple(specs)


def _opponent_spec(value: Any) -> OpponentSpec:
    if isinstance(value, OpponentSpec):
        return value
    if isinstance(value, str):
        policy, _, assignments = value.partition(":")
        entries = [entry for entry in assignments.split(",") if entry]
        if any("=" not in entry for entry in entries):
            raise SafeRaceError(f"opponent {value!r}: write POLICY[:FIELD=VALUE,...]")
        value = {"policy": policy, **dict(entry.split("=", 1) for entry in entries)}
    if not isinstance(value, Mapping):
        raise SafeRaceError(f"an opponent is an OpponentSpec, a dict or a string, got {value!r}")
    known = {field.name for field in dataclasses.fields(OpponentSpec)}
    unknown = set(value) - known
    if unknown:
        raise SafeRaceError(
            f"unknown opponent field(s) {sorted(unknown)}: use {', '.join(sorted(known))}"
        )
    try:
        numbers: dict[str, Any] = {
            name: None if entry is None else float(entry)
            for name, entry in value.items()
            if name != "policy"
        }
    except (TypeError, ValueError):
        raise SafeRaceError(
            f"opponent {dict(value)!r}: fields other than policy are numbers"
        ) from None
    return OpponentSpec(str(value.get("policy", OpponentSpec.policy)), **numbers)


class OpponentCar:
    """One opponent's car in the scene, its driver and its state after the last step."""

    def __init__(self, env, index: int, spec: OpponentSpec) -> None:
        self.name = f"car{index}"
        self.spec = spec
        self.gap_m = DEFAULT_GAP_M * index if spec.gap_m is None else spec.gap_m
        self.io = CarIO(env.model, env.data, car_prefix(index))
        self.projector = env.track.projector()
        self.policy = None if spec.policy == EXTERNAL else _load_factory()(spec, env)
        self.steer_target = 0.0
        self.state: dict[str, Any] = {}
        self.progress_m = 0.0


class Traffic:
    """The opponents of an env: placing them, driving them a step, their states, collisions."""

    def __init__(self, env, specs: Sequence[OpponentSpec]) -> None:
        self.env = env
        self.cars = [OpponentCar(env, index, spec) for index, spec in enumerate(specs, start=1)]
        self.monitor = CollisionMonitor(
            env.data, [env._car_io, *(car.io for car in self.cars)], [EGO, *self.names]
        )
        self._external: dict[str, np.ndarray] = {}
        self._driven = any(car.policy is not None for car in self.cars)

    @property
    def names(self) -> list[str]:
        return [car.name for car in self.cars]

    def place(self, ego_start_s_m: float, rng: np.random.Generator) -> None:
        """Put every opponent at its start, rolling at its line's speed there (after the
        physics reset, before ``mj_forward``), and reseed the policies from ``rng``."""
        env = self.env
        length = env.track.length_m
        for car in self.cars:
            s = (ego_start_s_m + car.gap_m) % length
            pose = car.projector.from_frenet(s, car.spec.start_offset_m)
            speed = car.spec.speed_factor * float(env.reference.speed_at(s))
            car.io.set_pose(pose, speed, env.params.wheel_radius_m)
            car.projector.reset(s)
            car.steer_target = 0.0
            car.progress_m = 0.0
            reset = getattr(car.policy, "reset", None)
            if reset is not None:
                reset(np.random.default_rng(rng.integers(2**32)))
        self.monitor.reset()
        self._external = {}

    def get_state(self) -> dict[str, Any]:
        """What changes while racing (pickling an env saves it), drivers included."""
        return {
            "cars": [
                {
                    "steer_target": car.steer_target,
                    "state": dict(car.state),
                    "progress_m": car.progress_m,
                    "projector": car.projector.get_state(),
                    "policy": None if car.policy is None else car.policy.get_state(),
                }
                for car in self.cars
            ],
            "monitor": self.monitor.get_state(),
            "external": dict(self._external),
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`get_state` returned, in an env built with the same opponents."""
        for car, saved in zip(self.cars, state["cars"], strict=True):
            car.steer_target = saved["steer_target"]
            car.state, car.progress_m = dict(saved["state"]), saved["progress_m"]
            car.projector.set_state(saved["projector"])
            if car.policy is not None:
                car.policy.set_state(saved["policy"])
        self.monitor.set_state(state["monitor"])
        self._external = dict(state["external"])

    def set_external_actions(self, actions: Mapping[str, np.ndarray]) -> None:
        """The actions of the ``external`` opponents for the next step, by car name."""
        self._external = {name: np.asarray(action, float) for name, action in actions.items()}

    def drive(self) -> None:
        """Set every opponent's controls for the next step from its policy's action (its
        braking no harder than stops the car within the step)."""
        env = self.env
        params = env.params
        for car in self.cars:
            if car.policy is None:
                action = self._external.get(car.name, (0.0, -params.max_brake_mps2))
            else:
                action = car.policy.act(None, car.state)
            steer = min(max(float(action[0]), -params.max_steer_rad), params.max_steer_rad)
            speeds = car.io.speeds()  # braking stops the car, never backs it up
            brake = min(params.max_brake_mps2, max(speeds[0], 0.0) / env.control_dt_s)
            accel = min(max(float(action[1]), -brake), params.max_accel_mps2)
            car.steer_target = rate_limited(
                steer, car.steer_target, params.max_steer_rate_radps, env.control_dt_s
            )
            torques = wheel_torques(accel, *speeds, params)
            car.io.set_controls(
                ackermann_angles(car.steer_target, params), torques.rear_nm, torques.front_nm
            )

    def observe(self, ego: Mapping[str, Any], first: bool = False) -> list[Collision]:
        """Update every opponent's state after a step (or a reset, ``first``), given the
        ego's info, and return the collisions that started during the step."""
        env = self.env
        for car in self.cars:
            pose = car.io.pose()
            s, e_y, e_psi = car.projector.to_frenet(*pose)
            if not first:
                car.progress_m += wrap_arc(s - car.state["s_m"], env.track.length_m)
            car.state = self._state(car, pose, (s, e_y, e_psi))
        if self._driven:  # what a driver knows of the other cars
            everyone = [_summary(EGO, ego), *(_summary(car.name, car.state) for car in self.cars)]
            for car in self.cars:
                car.state["cars"] = [other for other in everyone if other["name"] != car.name]
        if first or not self.monitor.pending():
            return []
        centre = env.track.centerline
        tangents = [
            centre.tangent(ego["s_m"]),
            *(centre.tangent(car.state["s_m"]) for car in self.cars),
        ]
        return self.monitor.collect(tangents)

    def ego_info(
        self, info: dict[str, Any], collisions: list[Collision], collision_penalty: float
    ) -> dict[str, Any]:
        """The ego's ``info`` with the opponents' states, the collisions that started this
        step, and the reward term for those the ego caused."""
        at_fault = sum(collision.at_fault == EGO for collision in collisions)
        return {
            **info,
            "opponents": self.opponents_info(info["s_m"], info["progress_m"]),
            "collisions": [collision.as_dict() for collision in collisions],
            "at_fault_collisions": at_fault,
            "reward_collision": -collision_penalty * at_fault,
        }

    def opponents_info(self, ego_s_m: float, ego_progress_m: float) -> list[dict[str, Any]]:
        """Each opponent's pose, Frenet state, speed, whether its driver leaves room to a car
        alongside (``leaves_room``), gap ahead of the ego (m, along the centre line, within
        half a lap) and ``ego_lead_m``: how far the ego has driven past it since the start,
        laps counted (negative while it has not)."""
        length = self.env.track.length_m
        return [
            {
                key: car.state[key]
                for key in (
                    "name",
                    "policy",
                    "x_m",
                    "y_m",
                    "yaw_rad",
                    "s_m",
                    "e_y_m",
                    "e_psi_rad",
                    "v_x_mps",
                    "v_y_mps",
                    "speed_mps",
                    "progress_m",
                    "outside_lane",
                    "leaves_room",
                )
            }
            | {
                "gap_m": wrap_arc(car.state["s_m"] - ego_s_m, length),
                "ego_lead_m": ego_progress_m - car.progress_m - car.gap_m,
            }
            for car in self.cars
        ]

    def _state(self, car: OpponentCar, pose, frenet) -> dict[str, Any]:
        env = self.env
        s, e_y, e_psi = (float(value) for value in frenet)
        v_x, v_y, r = car.io.velocity().tolist()
        w_right, w_left = (float(w) for w in env.track.widths(s))
        half = env.car_half_width_m
        return {
            "name": car.name,
            "policy": car.spec.policy,
            "x_m": pose[0],
            "y_m": pose[1],
            "yaw_rad": pose[2],
            "s_m": s,
            "e_y_m": e_y,
            "e_psi_rad": e_psi,
            "v_x_mps": v_x,
            "v_y_mps": v_y,
            "yaw_rate_radps": r,
            "speed_mps": math.hypot(v_x, v_y),
            "steer_rad": car.steer_target,
            "steer_angle_rad": car.io.steer_angle(),
            "w_left_m": w_left,
            "w_right_m": w_right,
            "time_s": float(env.data.time),
            "progress_m": car.progress_m,
            "outside_lane": bool(e_y + half > w_left or e_y - half < -w_right),
            "fully_outside_lane": bool(e_y - half > w_left or e_y + half < -w_right),
            "leaves_room": bool(getattr(car.policy, "leaves_room", False)),
        }


def _summary(name: str, state: Mapping[str, Any]) -> dict[str, Any]:
    """What a car's driver knows of another car: where it is, how fast it goes, and whether
    it leaves room to a car alongside."""
    speed = state.get("speed_mps", math.hypot(state["v_x_mps"], state["v_y_mps"]))
    return {
        "name": name,
        "s_m": state["s_m"],
        "e_y_m": state["e_y_m"],
        "e_psi_rad": state["e_psi_rad"],
        "speed_mps": speed,
        "leaves_room": state.get("leaves_room", False),
    }


def _load_factory():
    module_name, _, name = _OPPONENT_FACTORY.partition(":")
    return getattr(importlib.import_module(module_name), name)
