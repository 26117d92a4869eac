"""The one registry of SafeRace task ids."""

from __future__ import annotations

import gymnasium as gym

#: Task id -> entry point. Both tasks share the car and scene; they differ in reference line.
TASKS = {
    "saferace/CenterLine-v0": "saferace.envs.racing_env:CenterLineEnv",
    "saferace/RacingLine-v0": "saferace.envs.racing_env:RacingLineEnv",
}


def register_tasks() -> None:
    """Register every task id with gymnasium (idempotent)."""
    for task_id, entry_point in TASKS.items():
        if task_id not in gym.registry:
            gym.register(id=task_id, entry_point=entry_point, disable_env_checker=True)
