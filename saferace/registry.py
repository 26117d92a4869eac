"""The one registry of SafeRace task ids (outside ``saferace.envs``, so that registering
the ids loads neither MuJoCo nor its OpenGL setup)."""

from __future__ import annotations

import gymnasium as gym

from saferace.names import TASK_IDS, TRAFFIC_TASK_IDS

#: Task id -> entry point. The tasks share the car and scene; they differ in reference line
#: and in the opponents they start among. Each takes ``faults`` (``saferace.faults``).
TASKS = {
    task_id: f"saferace.envs.tasks:{task}"
    for task, task_id in {**TASK_IDS, **TRAFFIC_TASK_IDS}.items()
}


def register_tasks() -> None:
    """Register every task id with gymnasium (idempotent)."""
    for task_id, entry_point in TASKS.items():
        if task_id not in gym.registry:
            gym.register(id=task_id, entry_point=entry_point, disable_env_checker=True)
