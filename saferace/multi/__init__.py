"""Several learners in one race: the PettingZoo parallel env (``pip install 'saferace[multi]'``)."""

from __future__ import annotations

from typing import Any

from saferace.extras import require


def parallel_env(**kwargs: Any):
    """A :class:`saferace.multi.parallel.RacingParallelEnv` (PettingZoo ``ParallelEnv``)."""
    require("pettingzoo", "multi", "the PettingZoo parallel env")
    from saferace.multi.parallel import RacingParallelEnv

    return RacingParallelEnv(**kwargs)
