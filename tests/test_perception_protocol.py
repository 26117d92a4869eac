"""A perception method of one's own (``saferace.safety.uncertainty.perception``): loaded as
``MODULE:FACTORY`` from the current folder, handed the frame and the odometry only, its
answers checked; the minimal example keeps a drifting driver inside behind the filter."""

from __future__ import annotations

import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import saferace  # noqa: F401  (registers the tasks)
from saferace.errors import ConfigError, SafeRaceError
from saferace.eval.agents import make_agent
from saferace.eval.filters import FilterConfig, apply_filter
from saferace.eval.leaderboard import state_source_words
from saferace.eval.runner import make_task_env, max_steps_for, run_episode
from saferace.names import ADAPTIVE_FEEDBACK
from saferace.safety.uncertainty.perception import (
    Perception,
    PerceptionSetup,
    PerceptionStateSource,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
EXAMPLE = "road_centroid_perception:make"


class Spy:
    """Records what it is handed; sees the lane's middle, +-0.5 m, +-0.5 rad."""

    def __init__(self, setup: PerceptionSetup) -> None:
        self.setup = setup
        self.handed: list[tuple] = []

    def reset(self, seed: int | None = None) -> None:
        self.handed.clear()

    def perceive(self, image: np.ndarray, velocity: np.ndarray) -> Perception:
        self.handed.append((image, velocity))
        image[:] = 0  # its own copy: the observation stays as it was
        return Perception(np.zeros(2), np.array([-0.5, -0.5]), np.array([0.5, 0.5]))


@pytest.fixture
def in_examples(monkeypatch: pytest.MonkeyPatch) -> None:
    """The current folder is the examples', as a user's own folder (found without help)."""
    monkeypatch.chdir(EXAMPLES)
    monkeypatch.setattr(sys, "path", [entry for entry in sys.path if entry not in ("", ".")])
    monkeypatch.delitem(sys.modules, EXAMPLE.partition(":")[0], raising=False)


def test_the_minimal_example_keeps_a_drifting_driver_inside_behind_the_filter(in_examples):
    safety = FilterConfig(kind="cbf", state_source=EXAMPLE)
    assert safety.uncertainty == "robust"
    env = make_task_env("CenterLine", "lab", 1, safety, 0, max_steps=max_steps_for(20.0))
    assert isinstance(env.state_source, PerceptionStateSource)  # type: ignore[attr-defined]
    covered = []
    result = run_episode(
        env,
        make_agent("drift", env, seed=0),
        seed=0,
        on_step=lambda observation, info, action: covered.append(info["safety"]["covered"]),
    )
    env.close()
    assert result.summary["laps_completed"] == 1
    assert result.summary["time_outside_lane_s"] == 0.0
    assert np.mean(covered) > 0.9
    assert state_source_words(safety) == f"perceived by {EXAMPLE}"


def test_a_method_is_handed_its_own_copy_of_the_frame_and_the_odometry_only():
    env = gym.make("saferace/CenterLine-v0", track="lab", image_size=(16, 16))
    setup = PerceptionSetup((16, 16, 3), 0.05, env.unwrapped.track)  # type: ignore[attr-defined]
    spy = Spy(setup)
    source = PerceptionStateSource(spy, setup.track)
    observation, info = env.reset(seed=0)
    frame = observation["image"].copy()
    samples = source.samples(observation, info)
    ((image, velocity),) = spy.handed
    assert image.shape == (16, 16, 3) and velocity.shape == (3,)
    assert np.array_equal(observation["image"], frame)
    kappa = setup.track.centerline.curvature_scalar(float(info["s_m"]))
    assert samples.tolist() == [[0.0, 0.0, kappa]]
    lower, upper = source.interval(samples)
    assert lower.tolist() == [-0.5, -0.5, kappa] and upper.tolist() == [0.5, 0.5, kappa]
    assert source.monitor(samples) == (None, False)
    spy.perceive = lambda image, velocity: Perception(  # type: ignore[method-assign]
        np.zeros(2), np.full(2, -np.inf), np.full(2, np.inf), in_doubt=True
    )
    samples = source.samples(observation, info)
    assert source.monitor(samples) == (None, True)  # its doubt is the filter's alarm
    env.close()


@pytest.mark.parametrize(
    ("mean", "lower", "upper", "message"),
    [
        ([0.0], [-1.0, -1.0], [1.0, 1.0], "mean must be 2 numbers"),
        ([0.0, np.nan], [-1.0, -1.0], [1.0, 1.0], "mean must be 2 numbers"),
        ([0.0, np.inf], [-1.0, -1.0], [1.0, np.inf], "mean must be finite"),
        ([0.0, 0.0], [1.0, -1.0], [0.5, 1.0], "must lie within"),
        ([2.0, 0.0], [-1.0, -1.0], [1.0, 1.0], "must lie within"),
    ],
)
def test_a_malformed_perception_is_refused_in_one_line(mean, lower, upper, message: str):
    with pytest.raises(SafeRaceError, match=message):
        Perception(np.array(mean), np.array(lower), np.array(upper))


def test_what_is_no_perception_method_is_refused():
    env = gym.make("saferace/CenterLine-v0", track="lab", image_size=(16, 16))
    track = env.unwrapped.track  # type: ignore[attr-defined]
    with pytest.raises(SafeRaceError, match="no perception method"):
        PerceptionStateSource(object(), track)  # type: ignore[arg-type]
    answers_nonsense = Spy(PerceptionSetup((16, 16, 3), 0.05, track))
    answers_nonsense.perceive = lambda image, velocity: (0.0, 0.0)  # type: ignore[method-assign]
    source = PerceptionStateSource(answers_nonsense, track)
    observation, info = env.reset(seed=0)
    with pytest.raises(SafeRaceError, match="must return a Perception"):
        source.samples(observation, info)
    env.close()


@pytest.mark.parametrize(
    "chance_option",
    [
        {"uncertainty": "chance"},
        {"probabilistic": False, "uncertainty": "robust"},
        {"spread_scale": (2.0, 2.0, 2.0), "uncertainty": "robust"},
        {"fuse_odometry": True, "uncertainty": "robust"},
        {"adaptive": ADAPTIVE_FEEDBACK[0]},
    ],
)
def test_a_perception_of_ones_own_feeds_the_robust_filter_alone(chance_option: dict):
    """One estimate a step: no samples for chance constraints, to widen, fuse or adapt."""
    with pytest.raises(ConfigError, match="not for a perception method of your own"):
        FilterConfig(kind="cbf", state_source=EXAMPLE, **chance_option)


def test_a_state_source_is_ours_or_module_factory(in_examples):
    with pytest.raises(ConfigError, match="MODULE:FACTORY"):
        FilterConfig(kind="cbf", state_source="road_centroid_perception")
    env = gym.make("saferace/CenterLine-v0", track="lab", image_size=(16, 16))
    with pytest.raises(SafeRaceError, match="cannot load 'no_such_module:make'"):
        apply_filter(env, FilterConfig(kind="cbf", state_source="no_such_module:make"))
    env.close()
