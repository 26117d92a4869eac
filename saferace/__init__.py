"""SafeRace: safety-assured, end-to-end, vision-based autonomous racing in MuJoCo.

Importing ``saferace`` registers the gymnasium tasks ``saferace/CenterLine-v0``,
``saferace/RacingLine-v0`` and ``saferace/Overtake-v0``;
``gymnasium.make("saferace:saferace/RacingLine-v0")`` imports it for you.
"""

from saferace.version import __version__ as __version__


def register_envs() -> None:
    """Register the gymnasium task ids (also the ``gymnasium.envs`` entry point)."""
    from saferace.registry import register_tasks

    register_tasks()


register_envs()
