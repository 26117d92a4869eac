"""The SafeRace racing tasks: drive the rc10 around a track from its onboard camera."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from saferace.envs.arguments import check_task_arguments
from saferace.envs.car_io import CarIO
from saferace.envs.car_variation import CarVariation
from saferace.envs.drivetrain import (
    DrivetrainParams,
    ackermann_angles,
    rate_limited,
    wheel_torques,
)
from saferace.envs.randomization import (
    PhysicsRandomization,
    VisualRandomization,
    physics_randomization,
    visual_randomization,
)
from saferace.envs.reference_lines import reference_line
from saferace.envs.scene import SceneOptions, build_model
from saferace.envs.scene_look import SceneLook
from saferace.envs.traffic import OpponentSpec, Traffic, opponent_specs
from saferace.envs.views import Views
from saferace.errors import SafeRaceError
from saferace.track import Track, VehicleEnvelope
from saferace.track.frenet import wrap_arc

#: Bounds of ``[v_x, v_y, r]`` (m/s, m/s, rad/s): far beyond the car's 7 m/s, but finite.
VELOCITY_BOUND = np.array([30.0, 30.0, 100.0], np.float32)
DEFAULT_CONTROL_HZ = 20.0
_STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION


class RacingEnv(gym.Env):
    """Drive the rc10 1/10 car around a track along a reference line, from camera images.

    ## Description
    A MuJoCo scene of a track (asphalt, white boundary lines, roadside objects) and the
    rc10 car (3.5 kg, wheelbase 0.33 m, Ackermann steering, rear-wheel drive). The
    reference line is the track's center line (``CenterLine-v0``) or its
    minimum-curvature racing line (``RacingLine-v0``), each with a speed profile.

    ## Action space
    ``Box(2,)`` float32 in physical units: ``[steer_rad, accel_mps2]``, the front-wheel
    (bicycle) angle in ``[-0.36, 0.36]`` rad, positive left, rate-limited to 6 rad/s,
    and the longitudinal acceleration command in ``[-4, 4]`` m/s^2, which the motor turns
    into rear-wheel torque (saturating with wheel speed, top speed about 7 m/s).

    ## Observation space (``Dict``)
    - ``image``: uint8 ``(H, W, 3)`` from ``front_camera``, or ``(H, W, 6)`` with
      ``stereo=True`` (``stereo_left`` then ``stereo_right``, 0.12 m apart).
    - ``velocity``: float32 ``[v_x, v_y, r]``: body-frame forward and leftward speed
      (m/s) and yaw rate (rad/s), as an IMU and wheel encoders would measure them.
    Ground truth never enters the observation; it is in ``info`` (below).

    ## Rewards
    ``reward = progress_m - deviation_weight * deviation_m ** 2`` per step:
    ``progress_m`` is the centerline distance gained this step (m), ``deviation_m`` the
    lateral distance from the reference line (m). Both terms are in ``info`` as
    ``reward_progress`` and ``reward_deviation``.

    ## Cost
    ``info["cost"]`` is 1.0 while any part of the car (0.30 m wide) is outside the lane.

    ## Traffic
    ``opponents``: other rc10s, each an :class:`~saferace.envs.traffic.OpponentSpec`, a dict
    of its fields or ``"POLICY[:FIELD=VALUE,...]"`` (``expert``, ``racer``, ``pure-pursuit``,
    ``lane-changer``, ``blocker``, ``braking``; seeded, driven from ground truth), seen by the
    onboard camera. ``info`` then has ``opponents`` (pose, Frenet state, speed, ``gap_m``,
    ``leaves_room``), ``collisions`` (started this step: cars, time, relative speed, the car
    at fault; the ego is ``car0``) and ``at_fault_collisions``; one the ego causes costs
    ``collision_penalty`` (``reward_collision``) and ends the episode (``terminate_on_collision``).

    ## Starting state
    On the reference line at centerline arc length ``start_s_m`` (default 0, the
    start/finish line; uniformly random with ``random_start=True``, or
    ``reset(options={"start_s_m": s})``), with the reference heading and the reference
    speed (or ``reset(options={"start_speed_mps": v})``).

    ## Episode end
    Terminated when the whole car is outside the lane or it flips. Truncated after
    ``max_laps`` laps (``info["lap_completed"]`` is True on the step a lap ends) or after
    ``max_steps`` steps (default: time for ``max_laps`` laps at 0.5 m/s).

    ## Info
    ``s_m, e_y_m, e_psi_rad, kappa_radpm`` (Frenet state on the centerline), ``ref_offset_m,
    ref_speed_mps, deviation_m`` (the reference at ``s``), ``w_left_m, w_right_m`` (lane half
    widths at ``s``), ``x_m, y_m, yaw_rad`` (pose), ``v_x_mps, v_y_mps, yaw_rate_radps``,
    ``steer_rad`` (applied steering target), ``steer_angle_rad`` (the wheels' bicycle angle,
    which follows the target with the servos' lag), ``accel_mps2`` (command), ``time_s``,
    ``progress_m`` (since reset), ``lap`` (laps completed), ``lap_time_s`` (last completed lap,
    None before), ``lap_times_s``, ``lap_completed``, ``outside_lane``, ``cost``,
    ``reward_progress``, ``reward_deviation``.

    ## Arguments
    ``track``: built-in name, CSV path or :class:`~saferace.track.Track` (``"technical"``);
    ``image_size=(64, 64)`` (H, W); ``stereo=False``; ``control_hz=20``;
    ``physics_dt_s=0.005``; ``max_laps=1``; ``max_steps=None``; ``render_mode=None`` or
    ``"rgb_array"`` (chase view of ``render_size=(240, 320)``); ``start_s_m=0.0``;
    ``random_start=False``; ``deviation_weight=1.0``; ``scene_options``; ``randomize``: visual
    domain randomisation, a preset (``"none"``, ``"mild"``, ``"strong"``) or a
    :class:`~saferace.envs.randomization.VisualRandomization` of ranges (light, colours,
    textures, lane markings, roadside objects, onboard camera mounting, image noise and blur);
    ``physics_randomize``: the same for the car (mass, tyre friction, motor strength;
    :class:`~saferace.envs.randomization.PhysicsRandomization`). Both are drawn at each reset
    from the env's seeded generator (same seed, same look and car) and written into the model in
    place; the values drawn are in the reset info as ``look`` and ``car``.

    ## Version history
    - v0: first release (``gym.make`` takes ``faults``: :mod:`saferace.faults`).
    """

    # gym.Env declares metadata an instance attribute: __init__ sets each env's render_fps.
    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 20}  # noqa: RUF012
    action_space: spaces.Box
    observation_space: spaces.Dict
    reference_kind = "center"
    default_opponents: tuple[OpponentSpec, ...] = ()
    default_collision_penalty = 0.0
    default_terminate_on_collision = False

    def __init__(
        self,
        track: str | Track = "technical",
        image_size: tuple[int, int] = (64, 64),
        stereo: bool = False,
        control_hz: float = DEFAULT_CONTROL_HZ,
        physics_dt_s: float = 0.005,
        max_laps: int = 1,
        max_steps: int | None = None,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (240, 320),
        start_s_m: float = 0.0,
        random_start: bool = False,
        deviation_weight: float = 1.0,
        scene_options: SceneOptions | None = None,
        randomize: str | VisualRandomization | None = None,
        physics_randomize: str | PhysicsRandomization | None = None,
        opponents: Sequence[OpponentSpec | dict | str] | None = None,
        collision_penalty: float | None = None,
        terminate_on_collision: bool | None = None,
    ) -> None:
        check_task_arguments(
            image_size, control_hz, physics_dt_s, max_laps, render_mode, self.metadata
        )
        self._init_kwargs = dict(
            track=track,
            image_size=tuple(image_size),
            stereo=stereo,
            control_hz=control_hz,
            physics_dt_s=physics_dt_s,
            max_laps=max_laps,
            max_steps=max_steps,
            render_mode=render_mode,
            render_size=tuple(render_size),
            start_s_m=start_s_m,
            random_start=random_start,
            deviation_weight=deviation_weight,
            scene_options=scene_options,
            randomize=randomize,
            physics_randomize=physics_randomize,
            opponents=opponents,
            collision_penalty=collision_penalty,
            terminate_on_collision=terminate_on_collision,
        )
        self.randomize = visual_randomization(randomize)
        self.physics_randomize = physics_randomization(physics_randomize)
        self.track = track if isinstance(track, Track) else Track.load(track)
        self.reference = reference_line(self.track, self.reference_kind)
        self.params = DrivetrainParams()  # nominal: what controllers may know of the car
        self._drivetrain = self.params  # the car driven: varied by physics_randomize
        self.car_half_width_m = 0.5 * VehicleEnvelope().width_m
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.stereo = stereo
        self.control_dt_s = 1.0 / control_hz
        self.substeps = max(1, round(self.control_dt_s / physics_dt_s))
        self.max_laps = max_laps
        self.max_steps = max_steps or math.ceil(max_laps * self.track.length_m / 0.5 * control_hz)
        self.render_mode = render_mode
        self.render_size = (int(render_size[0]), int(render_size[1]))
        self.start_s_m = start_s_m
        self.random_start = random_start
        self.deviation_weight = deviation_weight
        self.metadata = {**self.metadata, "render_fps": control_hz}

        options = scene_options or SceneOptions()
        if not self.randomize.is_identity:
            options = dataclasses.replace(options, randomizable=True)
        self.opponents = opponent_specs(self.default_opponents if opponents is None else opponents)
        self.collision_penalty = float(
            self.default_collision_penalty if collision_penalty is None else collision_penalty
        )
        self.terminate_on_collision = bool(
            self.default_terminate_on_collision
            if terminate_on_collision is None
            else terminate_on_collision
        )
        self.model = build_model(self.track, options, len(self.opponents))
        self.model.opt.timestep = physics_dt_s
        self.data = mujoco.MjData(self.model)
        self._look = (
            None
            if self.randomize.is_identity
            else SceneLook(self.model, self.randomize, self.image_size)
        )
        self._car = (
            None
            if self.physics_randomize.is_identity
            else CarVariation(self.model, self.params, self.physics_randomize)
        )
        self._car_io = CarIO(self.model, self.data)
        self._projector = self.track.projector()
        self._traffic = Traffic(self, self.opponents) if self.opponents else None
        cameras = ("stereo_left", "stereo_right") if stereo else ("front_camera",)
        cars = 1 + len(self.opponents)
        self._views = Views(self.model, self.data, self.image_size, cameras, cars, self._look)

        channels = 3 * len(cameras)
        self.observation_space = spaces.Dict(
            image=spaces.Box(0, 255, (*self.image_size, channels), np.uint8),
            velocity=spaces.Box(-VELOCITY_BOUND, VELOCITY_BOUND, (3,), np.float32),
        )
        p = self.params
        self.action_space = spaces.Box(
            low=np.array([-p.max_steer_rad, -p.max_brake_mps2], np.float32),
            high=np.array([p.max_steer_rad, p.max_accel_mps2], np.float32),
        )
        self._steer_target = 0.0
        self._episode: dict[str, Any] = {}
        self._variation_rng: dict[str, Any] | None = None  # the generator's state at the draw

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        if "start_s_m" in options:
            start_s = float(options["start_s_m"])
        elif self.random_start:
            start_s = float(self.np_random.uniform(0.0, self.track.length_m))
        else:
            start_s = self.start_s_m
        start_speed = options.get("start_speed_mps")
        if start_speed is not None and not 0.0 <= float(start_speed) <= 20.0:
            raise SafeRaceError(f"start_speed_mps must be between 0 and 20 m/s, got {start_speed}")
        variations = self._vary()
        start = start_s % self.track.length_m
        speed = self.reference.speed_at(start) if start_speed is None else start_speed
        mujoco.mj_resetData(self.model, self.data)
        self._car_io.set_pose(
            self.reference.pose_at(start), float(speed), self.params.wheel_radius_m
        )
        if self._traffic is not None:
            self._traffic.place(start, self.np_random)
        mujoco.mj_forward(self.model, self.data)
        self._projector.reset(start)
        self._steer_target = 0.0
        pose = self._car_io.pose()
        frenet = self._projector.to_frenet(*pose)
        self._episode = dict(
            steps=0,
            progress_m=0.0,
            last_s=frenet[0],
            lap=0,
            lap_start_s=0.0,
            lap_times_s=[],
            accel_mps2=0.0,
        )
        velocity = self._car_io.velocity()
        info = self._info(pose, frenet, velocity, progress_m=0.0, lap_completed=False)
        if self._traffic is not None:
            self._traffic.observe(info, first=True)
            info = self._traffic.ego_info(info, [], self.collision_penalty)
        return self._observation(velocity), {**info, **variations}

    def step(self, action):
        steer_cmd, accel_cmd = self._clipped(action)
        params = self._drivetrain
        self._steer_target = rate_limited(
            steer_cmd, self._steer_target, params.max_steer_rate_radps, self.control_dt_s
        )
        torques = wheel_torques(accel_cmd, *self._car_io.speeds(), params)
        self._car_io.set_controls(
            ackermann_angles(self._steer_target, params), torques.rear_nm, torques.front_nm
        )
        time_before = self.data.time
        traffic = self._traffic
        if traffic is None:
            self._car_io.step(self.substeps)
        else:
            traffic.drive()
            near = traffic.monitor.may_touch(self.control_dt_s)
            self._car_io.step(self.substeps, traffic.monitor.check if near else None)

        episode = self._episode
        pose = self._car_io.pose()
        frenet = self._projector.to_frenet(*pose)
        progress = wrap_arc(frenet[0] - episode["last_s"], self.track.length_m)
        episode["last_s"] = frenet[0]
        episode["steps"] += 1
        episode["accel_mps2"] = accel_cmd
        before = episode["progress_m"]
        episode["progress_m"] = before + progress
        lap_completed = self._count_lap(before, episode["progress_m"], time_before)

        velocity = self._car_io.velocity()
        info = self._info(pose, frenet, velocity, progress_m=progress, lap_completed=lap_completed)
        if traffic is not None:
            info = traffic.ego_info(info, traffic.observe(info), self.collision_penalty)
        reward = (
            info["reward_progress"] + info["reward_deviation"] + info.get("reward_collision", 0.0)
        )
        terminated = bool(
            info["fully_outside_lane"] or self._car_io.flipped() or self._ends_on_collision(info)
        )
        truncated = bool(episode["lap"] >= self.max_laps or episode["steps"] >= self.max_steps)
        return self._observation(velocity), reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self._views.chase(self.render_size)

    def close(self) -> None:
        self._views.close()

    @property
    def traffic(self) -> Traffic | None:
        """The opponents (None without)."""
        return self._traffic

    def car_observation(self, car: int) -> dict[str, np.ndarray]:
        """What car ``car`` (0: the ego car, 1...: the opponents) sees now: its onboard
        image(s) and its velocity, as the observation space defines them."""
        if car == 0:
            return self._observation(self._car_io.velocity())
        if self._traffic is None or not 0 < car <= len(self._traffic.cars):
            raise SafeRaceError(f"no car {car}: this env has {len(self.opponents)} opponents")
        return self._observation(self._traffic.cars[car - 1].io.velocity(), car)

    @property
    def drivetrain(self) -> DrivetrainParams:
        """The drivetrain of the car driven this episode (``params`` varied by
        ``physics_randomize``; ``params`` stays nominal, as a controller knows it)."""
        return self._drivetrain

    # ------------------------------------------------------------- pickling
    def __getstate__(self) -> dict[str, Any]:
        state = np.empty(mujoco.mj_stateSize(self.model, _STATE_SPEC))
        mujoco.mj_getState(self.model, self.data, state, _STATE_SPEC)
        return dict(
            kwargs=self._init_kwargs,
            physics=state,
            steer_target=self._steer_target,
            episode=self._episode,
            projector=self._projector.get_state(),
            np_random=self._np_random,
            variation_rng=self._variation_rng,
            noise_index=self._look.noise_index if self._look else 0,
            traffic=self._traffic.get_state() if self._traffic else None,
        )

    def __setstate__(self, state: dict[str, Any]) -> None:
        RacingEnv.__init__(self, **state["kwargs"])  # no subclass overrides __init__
        if state["variation_rng"] is not None:  # the same look and car, before any physics
            generator = type(state["np_random"].bit_generator)()
            generator.state = state["variation_rng"]
            self._np_random = np.random.Generator(generator)
            self._vary()
            if self._look is not None:
                self._look.noise_index = state["noise_index"]
        mujoco.mj_setState(self.model, self.data, state["physics"], _STATE_SPEC)
        mujoco.mj_forward(self.model, self.data)  # positions and sensors for the next step
        mujoco.mj_setState(self.model, self.data, state["physics"], _STATE_SPEC)  # warm start
        self._steer_target = state["steer_target"]
        self._episode = state["episode"]
        self._projector.set_state(state["projector"])
        self._np_random = state["np_random"]
        if self._traffic is not None:
            self._traffic.set_state(state["traffic"])

    # ------------------------------------------------------------- internals
    def _ends_on_collision(self, info: dict[str, Any]) -> bool:
        return self.terminate_on_collision and info.get("at_fault_collisions", 0) > 0

    def _vary(self) -> dict[str, dict[str, Any]]:
        """Draw this episode's look and car, apply them, and return the values drawn."""
        variations: dict[str, dict[str, Any]] = {}
        if self._look is None and self._car is None:
            return variations
        self._variation_rng = dict(self.np_random.bit_generator.state)  # a copy
        if self._look is not None:
            variations["look"] = self._look.apply(self.np_random)
            self._views.upload_look()
        if self._car is not None:
            self._drivetrain, variations["car"] = self._car.apply(self.np_random)
            mujoco.mj_setConst(self.model, self.data)  # what MuJoCo derives from the masses
        return variations

    def _count_lap(self, progress_before: float, progress_after: float, time_before: float) -> bool:
        episode = self._episode
        goal = (episode["lap"] + 1) * self.track.length_m
        if progress_after < goal:
            return False
        fraction = (goal - progress_before) / max(progress_after - progress_before, 1e-12)
        crossing_time = time_before + fraction * (self.data.time - time_before)
        episode["lap_times_s"].append(crossing_time - episode["lap_start_s"])
        episode["lap_start_s"] = crossing_time
        episode["lap"] += 1
        return True

    def _clipped(self, action) -> tuple[float, float]:
        """``(steer_rad, accel_mps2)`` within the action space; malformed actions raise."""
        try:
            steer, accel = (float(a) for a in np.ravel(action))
        except (TypeError, ValueError):
            raise SafeRaceError(f"action must be [steer_rad, accel_mps2], got {action!r}") from None
        if not (math.isfinite(steer) and math.isfinite(accel)):
            raise SafeRaceError(f"action must be finite, got {action!r}")
        p = self.params
        return (
            max(-p.max_steer_rad, min(p.max_steer_rad, steer)),
            max(-p.max_brake_mps2, min(p.max_accel_mps2, accel)),
        )

    def _observation(self, velocity: np.ndarray, car: int = 0) -> dict[str, np.ndarray]:
        return {"image": self._views.onboard(car), "velocity": velocity}

    def _info(
        self,
        pose: tuple[float, float, float],
        frenet: tuple[float, float, float],
        velocity: np.ndarray,
        progress_m: float,
        lap_completed: bool,
    ) -> dict[str, Any]:
        s, e_y, e_psi = (float(v) for v in frenet)
        w_right, w_left = (float(w) for w in self.track.widths(s))
        ref_offset = float(self.reference.offset_at(s))
        deviation = e_y - ref_offset
        half = self.car_half_width_m
        outside = e_y + half > w_left or e_y - half < -w_right
        fully_outside = e_y - half > w_left or e_y + half < -w_right
        x, y, yaw = pose
        v_x, v_y, r = velocity.tolist()
        episode = self._episode
        lap_times = list(episode["lap_times_s"])
        return {
            "s_m": s,
            "e_y_m": e_y,
            "e_psi_rad": e_psi,
            "kappa_radpm": self.track.centerline.curvature_scalar(s),
            "ref_offset_m": ref_offset,
            "ref_speed_mps": float(self.reference.speed_at(s)),
            "deviation_m": deviation,
            "w_left_m": w_left,
            "w_right_m": w_right,
            "x_m": x,
            "y_m": y,
            "yaw_rad": yaw,
            "v_x_mps": v_x,
            "v_y_mps": v_y,
            "yaw_rate_radps": r,
            "steer_rad": self._steer_target,
            "steer_angle_rad": self._car_io.steer_angle(),
            "accel_mps2": episode["accel_mps2"],
            "time_s": float(self.data.time),
            "progress_m": episode["progress_m"],
            "lap": episode["lap"],
            "lap_time_s": lap_times[-1] if lap_times else None,
            "lap_times_s": lap_times,
            "lap_completed": lap_completed,
            "outside_lane": outside,
            "fully_outside_lane": fully_outside,
            "cost": 1.0 if outside else 0.0,
            "reward_progress": progress_m,
            "reward_deviation": -self.deviation_weight * deviation * deviation,
        }


class CenterLineEnv(RacingEnv):
    """``saferace/CenterLine-v0``: follow the track's center line (see :class:`RacingEnv`)."""

    reference_kind = "center"


class RacingLineEnv(RacingEnv):
    """``saferace/RacingLine-v0``: follow the minimum-curvature racing line (:class:`RacingEnv`)."""

    reference_kind = "racing"
