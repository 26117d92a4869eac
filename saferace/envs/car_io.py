"""The car in a MuJoCo model: its named elements' addresses, and reading and writing its
state through them (placing it, its controls, a control step of physics, its pose)."""

from __future__ import annotations

import math
from collections.abc import Callable

import mujoco
import numpy as np

from saferace.envs.drivetrain import bicycle_angle

_SENSORS_OFF = int(mujoco.mjtDisableBit.mjDSBL_SENSOR)


class CarIO:
    """Addresses of the named model elements the env reads and writes every step, and the
    reads and writes themselves."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, prefix: str = "") -> None:
        """The car whose element names start with ``prefix`` (``""`` for the ego car)."""
        self.model, self.data, self.prefix = model, data, prefix
        self.chassis = model.body(prefix + "chassis").id
        root = model.joint(prefix + "root")
        self.root_qpos, self.root_qvel = int(root.qposadr[0]), int(root.dofadr[0])
        self.wheel_qvel = [
            int(model.joint(f"{prefix}{wheel}_spin").dofadr[0])
            for wheel in ("front_left", "front_right", "rear_left", "rear_right")
        ]
        self.steer_joints_qpos = [
            int(model.joint(f"{prefix}front_{side}_steer").qposadr[0]) for side in ("left", "right")
        ]
        self.steer_left = model.actuator(prefix + "front_left_steering_servo").id
        self.steer_right = model.actuator(prefix + "front_right_steering_servo").id
        self.motors = [
            model.actuator(prefix + "rear_left_motor").id,
            model.actuator(prefix + "rear_right_motor").id,
        ]
        self.brakes = [
            model.actuator(prefix + "front_left_brake").id,
            model.actuator(prefix + "front_right_brake").id,
        ]
        self.velocimeter = int(model.sensor(prefix + "imu_velocimeter").adr[0])
        self.gyro = int(model.sensor(prefix + "imu_gyro").adr[0])
        self.rear_wheel_speed = [
            int(model.sensor(prefix + "rear_left_wheel_speed").adr[0]),
            int(model.sensor(prefix + "rear_right_wheel_speed").adr[0]),
        ]

    def set_pose(
        self, pose: tuple[float, float, float], speed_mps: float, wheel_radius_m: float
    ) -> None:
        """Put the car at ``(x, y, yaw)`` rolling at ``speed_mps`` (positions and velocities
        only: the caller resets the physics before and runs ``mj_forward`` once every car is
        placed)."""
        data = self.data
        x, y, yaw = pose
        data.qpos[self.root_qpos : self.root_qpos + 7] = [
            x,
            y,
            wheel_radius_m,
            math.cos(yaw / 2),
            0.0,
            0.0,
            math.sin(yaw / 2),
        ]
        data.qvel[self.root_qvel : self.root_qvel + 3] = [
            speed_mps * math.cos(yaw),
            speed_mps * math.sin(yaw),
            0.0,
        ]
        for address in self.wheel_qvel:
            data.qvel[address] = speed_mps / wheel_radius_m

    def set_controls(
        self, steer_rad: tuple[float, float], rear_torque_nm: float, front_torque_nm: float
    ) -> None:
        """The servos' ``(left, right)`` angles, the rear motors' and front brakes' torques."""
        data = self.data
        data.ctrl[self.steer_left], data.ctrl[self.steer_right] = steer_rad
        for actuator in self.motors:
            data.ctrl[actuator] = rear_torque_nm
        for actuator in self.brakes:
            data.ctrl[actuator] = front_torque_nm

    def speeds(self) -> tuple[float, float]:
        """The forward speed and the rear wheels' mean rim speed (m/s)."""
        data = self.data
        rear = 0.5 * sum(float(data.sensordata[a]) for a in self.rear_wheel_speed)
        return float(data.sensordata[self.velocimeter]), rear

    def step(self, substeps: int, after_substep: Callable[[], None] | None = None) -> None:
        """One control step of physics, leaving positions, velocities and sensors current.

        ``mj_step`` computes positions and sensors *before* it integrates, so after it they
        lag the state by a substep. As dm_control does, each control step finishes the
        pending step (``mj_step2``, which applies the new controls), runs the other
        substeps, and ends with ``mj_step1`` for the new state. Sensors are only read
        then, so they are computed only then. ``after_substep`` (a scene with several cars:
        their contacts) runs after every substep, with the contacts of its positions.
        """
        model, data, opt = self.model, self.data, self.model.opt
        opt.disableflags |= _SENSORS_OFF
        mujoco.mj_step2(model, data)
        if after_substep is None:
            if substeps > 1:
                mujoco.mj_step(model, data, nstep=substeps - 1)
        else:
            for _ in range(substeps - 1):
                mujoco.mj_step(model, data)
                after_substep()
        opt.disableflags &= ~_SENSORS_OFF
        mujoco.mj_step1(model, data)
        if after_substep is not None:
            after_substep()

    def pose(self) -> tuple[float, float, float]:
        """``(x_m, y_m, yaw_rad)`` of the chassis."""
        data = self.data
        x, y = data.xpos[self.chassis, :2]
        rot = data.xmat[self.chassis]
        return float(x), float(y), math.atan2(rot[3], rot[0])

    def steer_angle(self) -> float:
        """The front wheels' bicycle angle now: the steering target after the servos' lag."""
        left, right = (float(self.data.qpos[a]) for a in self.steer_joints_qpos)
        return bicycle_angle(left, right)

    def flipped(self) -> bool:
        return bool(self.data.xmat[self.chassis, 8] < 0.3)

    def velocity(self) -> np.ndarray:
        """``[v_x, v_y, r]`` as the IMU measures them."""
        data = self.data
        v = data.sensordata[self.velocimeter : self.velocimeter + 2]
        return np.array([v[0], v[1], data.sensordata[self.gyro + 2]], dtype=np.float32)
