"""Drive the MuJoCo car through prepared manoeuvres and log what identification needs.

The car runs on a wide "proving ground" circle (radius 40 m, lane 24 m), at 100 Hz
control so that derivatives are well resolved, through the same drivetrain as the
tasks: steering steps, chirp sweeps and steady circles at several speeds, and
acceleration and braking steps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from saferace.envs.drivetrain import DrivetrainParams
from saferace.envs.racing_env import CenterLineEnv
from saferace.track import Track

CONTROL_HZ = 100.0
SPEED_GAIN_PER_S = 3.0
SIGNALS = (
    "t_s",
    "v_x",
    "v_y",
    "r",
    "steer_target",
    "steer_actual",
    "accel_cmd",
    "e_y",
    "e_psi",
    "kappa",
)

#: steer(t) and accel(t, v_x) of a manoeuvre.
Steering = Callable[[float], float]


@dataclass(frozen=True)
class Manoeuvre:
    """A named open-loop steering programme at a held (or commanded) speed."""

    name: str
    speed_mps: float
    duration_s: float
    steer: Steering
    accel: Callable[[float, float], float] | None = None  # default: hold speed_mps


def linear_steer_amplitude(speed_mps: float) -> float:
    """Steering that asks for about 3 m/s^2 of lateral acceleration (the tyres' linear range)."""
    return float(min(0.3, 3.0 * DrivetrainParams().wheelbase_m / speed_mps**2))


def doublet(amplitude: float) -> Steering:
    """``amplitude`` from 0.5 to 1.5 s, ``-amplitude`` from 1.5 to 2.5 s, else straight."""

    def steer(t: float) -> float:
        return amplitude if 0.5 <= t < 1.5 else (-amplitude if 1.5 <= t < 2.5 else 0.0)

    return steer


def constant(angle: float) -> Steering:
    """``angle`` throughout."""

    def steer(t: float) -> float:
        return angle

    return steer


def chirp(amplitude: float, f0_hz: float, f1_hz: float, duration_s: float) -> Steering:
    def steer(t: float) -> float:
        phase = 2 * np.pi * (f0_hz * t + 0.5 * (f1_hz - f0_hz) / duration_s * t * t)
        return amplitude * np.sin(phase)

    return steer


def standard_manoeuvres(speeds_mps: tuple[float, ...] = (1.5, 3.0, 4.5)) -> list[Manoeuvre]:
    """Steps, sweeps and circles at each speed, then acceleration and braking steps."""
    manoeuvres: list[Manoeuvre] = []
    for v in speeds_mps:
        amp = linear_steer_amplitude(v)
        manoeuvres += [
            Manoeuvre(f"step_{v:g}", v, 3.0, doublet(amp)),
            Manoeuvre(f"sweep_{v:g}", v, 6.0, chirp(amp, 0.2, 3.0, 6.0)),
            Manoeuvre(f"circle_{v:g}", v, 3.0, constant(0.7 * amp)),
        ]
    manoeuvres.append(
        Manoeuvre(
            "accel_brake",
            1.0,
            5.0,
            lambda t: 0.0,
            accel=lambda t, v: 3.0 if t < 1.5 else (-3.0 if t < 2.5 else 1.0),
        )
    )
    return manoeuvres


def proving_ground() -> Track:
    """A circle of radius 40 m with a 24 m wide lane: room for every manoeuvre."""
    theta = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    return Track.from_arrays(
        40.0 * np.cos(theta), 40.0 * np.sin(theta), 12.0, 12.0, name="proving_ground"
    )


def run_manoeuvre(env: CenterLineEnv, manoeuvre: Manoeuvre) -> dict[str, np.ndarray]:
    """Drive one manoeuvre from a fresh start; one row of SIGNALS per control step."""
    _, info = env.reset(seed=0, options={"start_s_m": 0.0, "start_speed_mps": manoeuvre.speed_mps})
    model, data = env.model, env.data
    steer_joints = [model.joint(f"front_{side}_steer").qposadr[0] for side in ("left", "right")]
    rows = []
    t = 0.0
    for _ in range(round(manoeuvre.duration_s * CONTROL_HZ)):
        if manoeuvre.accel is None:
            accel = SPEED_GAIN_PER_S * (manoeuvre.speed_mps - info["v_x_mps"])
        else:
            accel = manoeuvre.accel(t, info["v_x_mps"])
        _, _, terminated, _, info = env.step(np.array([manoeuvre.steer(t), accel]))
        if terminated:
            break
        t = info["time_s"]
        steer_actual = float(np.mean([data.qpos[j] for j in steer_joints]))
        rows.append(
            [
                t,
                info["v_x_mps"],
                info["v_y_mps"],
                info["yaw_rate_radps"],
                info["steer_rad"],
                steer_actual,
                info["accel_mps2"],
                info["e_y_m"],
                info["e_psi_rad"],
                info["kappa_radpm"],
            ]
        )
    table = np.asarray(rows)
    return {name: table[:, i] for i, name in enumerate(SIGNALS)}


def collect(
    manoeuvres: list[Manoeuvre] | None = None,
) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, float]]:
    """Logs of every manoeuvre, and the car's mass and axle distances from its model."""
    env = CenterLineEnv(
        track=proving_ground(), control_hz=CONTROL_HZ, image_size=(8, 8), max_laps=100
    )
    try:
        logs = {m.name: run_manoeuvre(env, m) for m in manoeuvres or standard_manoeuvres()}
        geometry = car_geometry(env)
    finally:
        env.close()
    return logs, geometry


def car_geometry(env: CenterLineEnv) -> dict[str, float]:
    """Mass and the distances from the centre of mass to the axles, from the MuJoCo model."""
    model, data = env.model, env.data
    chassis = model.body("chassis").id
    com_world = data.subtree_com[chassis]
    rotation = data.xmat[chassis].reshape(3, 3)
    com_x = float((rotation.T @ (com_world - data.xpos[chassis]))[0])
    front_x = float(model.body("front_left_knuckle").pos[0])
    rear_x = float(model.body("rear_left_wheel").pos[0])
    return {
        "mass_kg": float(model.body_subtreemass[chassis]),
        "lf_m": front_x - com_x,
        "lr_m": com_x - rear_x,
    }
