"""SafeRace: safety-assured, end-to-end, vision-based autonomous racing in MuJoCo."""

__version__ = "0.1.0"


def register_envs() -> None:
    """Register the gymnasium task ids (called through the ``gymnasium.envs`` entry point)."""
