"""``saferace/Overtake-v0``: pass a slower car without running into it."""

from __future__ import annotations

from saferace.envs.racing_env import RacingEnv
from saferace.envs.traffic import OpponentSpec


class OvertakeEnv(RacingEnv):
    """``saferace/Overtake-v0``: the racing-line task starting 2 m behind the expert MPC
    driving at 80% of the racing line's speed; every collision the ego car causes costs
    ``collision_penalty`` (default 10) of reward and ends the episode unless
    ``terminate_on_collision=False`` (:class:`RacingEnv`; any other ``opponents`` may be
    given).

    ## Version history
    - v0: first release.
    """

    reference_kind = "racing"
    default_opponents = (OpponentSpec(policy="expert", gap_m=2.0, speed_factor=0.8),)
    default_collision_penalty = 10.0
    default_terminate_on_collision = True
