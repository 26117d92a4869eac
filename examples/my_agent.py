"""A worked ``MODULE:FACTORY`` agent: pure pursuit of the reference line, a little faster
than the built-in ``pure-pursuit``. From this folder:

    saferace eval --agent my_agent:make --task CenterLine --track lab --out rows.jsonl

``make(env)`` gets the (possibly wrapped) task and returns anything with
``act(observation, info) -> [steer_rad, accel_mps2]``, or a plain callable of the same.
"""

from __future__ import annotations

from saferace.agents.pure_pursuit import PurePursuit, PurePursuitSettings


def make(env) -> PurePursuit:
    return PurePursuit.for_env(env, PurePursuitSettings(speed_scale=0.8))
