"""Every car a learner: a PettingZoo ``ParallelEnv`` of a racing task with several cars.

Agent ``car0`` is the task's own car and ``car1``... are its ``external`` opponents; each
has its own onboard camera (the other cars in view) and velocity, and a reward of the task's
form (progress less the squared deviation from the reference). ``car0``'s info is the
task's; the others' is their state (pose, Frenet state, speed, lane, progress) with the
task's ``lap``, ``cost``, reward terms and collisions. A car whose episode ends (out of
the lane, flipped, ``max_laps`` of progress or ``max_steps``) leaves ``agents`` and brakes
to a stop where it is; the race goes on while any car is in it. A collision is in the
infos of both cars; the car at fault loses the task's ``collision_penalty`` (0 unless
given) of reward.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pettingzoo import ParallelEnv

from saferace.envs import racing_env
from saferace.envs.traffic import EGO, EXTERNAL, OpponentSpec
from saferace.errors import SafeRaceError
from saferace.names import TASK_IDS

#: How far apart the cars start if not told (m, the first car ahead).
START_SPACING_M = 1.5


class RacingParallelEnv(ParallelEnv):
    """``cars`` rc10s on ``track`` in task ``task`` (``CenterLine`` or ``RacingLine``):
    ``start_gaps_m`` is each other car's start along the track from ``car0``'s (negative:
    behind; by default 1.5 m apart behind it), ``start_offsets_m`` their lateral offsets;
    other keyword arguments go to the task (image size, stereo, looks, ``max_laps``,
    ``collision_penalty``...)."""

    metadata = {"name": "saferace_racing_v0", "render_modes": ["rgb_array"], "render_fps": 20}  # noqa: RUF012

    def __init__(
        self,
        cars: int = 2,
        task: str = "RacingLine",
        start_gaps_m: list[float] | None = None,
        start_offsets_m: list[float] | None = None,
        **env_kwargs: Any,
    ) -> None:
        if cars < 1:
            raise SafeRaceError(f"cars must be at least 1, got {cars}")
        if task not in TASK_IDS:
            raise SafeRaceError(f"task must be one of {', '.join(TASK_IDS)}, got {task!r}")
        gaps = start_gaps_m or [-START_SPACING_M * k for k in range(1, cars)]
        offsets = start_offsets_m or [0.0] * (cars - 1)
        if len(gaps) != cars - 1 or len(offsets) != cars - 1:
            raise SafeRaceError(f"give {cars - 1} start gaps and offsets, one per other car")
        opponents = [
            OpponentSpec(policy=EXTERNAL, gap_m=gap, start_offset_m=offset, speed_factor=1.0)
            for gap, offset in zip(gaps, offsets, strict=True)
        ]
        env_class = getattr(racing_env, f"{task}Env")
        self.env: racing_env.RacingEnv = env_class(opponents=opponents, **env_kwargs)
        self.possible_agents = [EGO, *self.env.traffic.names] if cars > 1 else [EGO]
        self.agents: list[str] = []
        self.render_mode = self.env.render_mode
        self.metadata = {**self.metadata, "render_fps": self.env.metadata["render_fps"]}

    def observation_space(self, agent: str):
        return self.env.observation_space

    def action_space(self, agent: str):
        return self.env.action_space

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        self._steps = 0
        self._last_progress: dict[str, float] = {}
        observations = {EGO: observation}
        infos = {EGO: info}
        for index, car in enumerate(self._opponent_cars(), start=1):
            observations[car.name] = self.env.car_observation(index)
            infos[car.name] = dict(car.state)
        return observations, infos

    def step(self, actions: dict[str, np.ndarray]):
        missing = set(self.agents) - set(actions)
        if missing:
            raise SafeRaceError(f"actions missing for {sorted(missing)}")
        env = self.env
        brake = np.array([0.0, -env.params.max_brake_mps2], np.float32)
        traffic = env.traffic
        if traffic is not None:
            traffic.set_external_actions(
                {name: actions[name] for name in self.agents if name != EGO}
            )
        ego_action = actions.get(EGO, brake) if EGO in self.agents else brake
        observation, reward, terminated, truncated, info = env.step(ego_action)
        self._steps += 1
        observations, rewards, terminations, truncations, infos = (
            {EGO: observation},
            {EGO: reward},
            {EGO: terminated},
            {EGO: truncated},
            {EGO: info},
        )
        collisions = info.get("collisions", [])
        for index, car in enumerate(self._opponent_cars(), start=1):
            if car.name not in self.agents:
                continue
            state = car.state
            progress = state["progress_m"] - self._last_progress.get(car.name, 0.0)
            deviation = state["e_y_m"] - float(env.reference.offset_at(state["s_m"]))
            at_fault = sum(collision["at_fault"] == car.name for collision in collisions)
            parts = {
                "reward_progress": progress,
                "reward_deviation": -env.deviation_weight * deviation * deviation,
                "reward_collision": -env.collision_penalty * at_fault,
            }
            rewards[car.name] = sum(parts.values())
            observations[car.name] = env.car_observation(index)
            terminations[car.name] = bool(
                state["fully_outside_lane"]
                or car.io.flipped()
                or (env.terminate_on_collision and at_fault > 0)
            )
            truncations[car.name] = bool(
                state["progress_m"] >= env.max_laps * env.track.length_m
                or self._steps >= env.max_steps
            )
            infos[car.name] = {
                **state,
                **parts,
                "lap": int(state["progress_m"] // env.track.length_m),
                "cost": 1.0 if state["outside_lane"] else 0.0,
                "collisions": [c for c in collisions if car.name in c["cars"]],
                "at_fault_collisions": at_fault,
            }
        infos[EGO] = {
            **info,
            "collisions": [c for c in collisions if EGO in c["cars"]],
        }
        self._last_progress = {car.name: car.state["progress_m"] for car in self._opponent_cars()}
        live = [name for name in self.agents if name in observations]
        self.agents = [name for name in live if not (terminations[name] or truncations[name])]
        keep = set(live)
        return tuple(
            {name: value for name, value in part.items() if name in keep}
            for part in (observations, rewards, terminations, truncations, infos)
        )

    def render(self):
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    def _opponent_cars(self):
        traffic = self.env.traffic
        return [] if traffic is None else traffic.cars
