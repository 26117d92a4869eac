"""A safety filter of one's own (``saferace.safety.filter_protocol``): loaded as
``MODULE:FACTORY`` from the current folder, handed the perception's estimate, the car's
sensors and the map but never the simulator's state; its answers clipped and counted; a
filter that raises ends its run with a report; the minimal example keeps reckless drivers
inside on the true state."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import saferace  # noqa: F401  (registers the tasks)
from saferace.errors import ConfigError, SafeRaceError
from saferace.eval.agents import make_agent
from saferace.eval.filter_config import USERS_FILTER_SETTINGS
from saferace.eval.filters import FilterConfig, apply_filter
from saferace.eval.leaderboard import filter_words, row_filter
from saferace.eval.runner import evaluate, make_task_env, max_steps_for, run_episode
from saferace.safety.filter_protocol import (
    FilterSetup,
    FilterView,
    ProtocolSafetyFilter,
)

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
EXAMPLE = "brake_near_edge_filter:make"
#: All a filter may read: the perception's estimate, the car's sensors, the map's position.
VIEW_FIELDS = {
    "mean", "lower", "upper", "in_doubt", "velocity", "steer_angle_rad", "s_m", "opponents",
    "time_s",
}  # fmt: skip
SETUP_FIELDS = {
    "track", "params", "action_low", "action_high", "control_dt_s", "car_half_width_m", "seed",
}  # fmt: skip


class Spy:
    """Passes the driver's action on, keeping what it is handed; ``answer`` replaces the
    action, ``fail_at`` raises on that step."""

    def __init__(
        self, setup: FilterSetup, answer: np.ndarray | None = None, fail_at: int | None = None
    ) -> None:
        self.setup, self.answer, self.fail_at = setup, answer, fail_at
        self.views: list[FilterView] = []

    def reset(self, seed: int | None = None) -> None:
        self.views.clear()

    def certify(self, action: np.ndarray, view: FilterView) -> np.ndarray:
        self.views.append(view)
        if self.fail_at is not None and len(self.views) == self.fail_at:
            raise ValueError("a bug in the filter")
        return action if self.answer is None else self.answer


def spied(env: gym.Env, **spy_arguments) -> tuple[ProtocolSafetyFilter, list[Spy]]:
    made: list[Spy] = []

    def factory(setup: FilterSetup) -> Spy:
        made.append(Spy(setup, **spy_arguments))
        return made[0]

    return ProtocolSafetyFilter(env, factory, name="spy", seed=0), made


def lab(seconds: float = 5.0) -> gym.Env:
    return gym.make(
        "saferace/CenterLine-v0", track="lab", image_size=(16, 16),
        max_episode_steps=max_steps_for(seconds),
    )  # fmt: skip


@pytest.fixture
def in_examples(monkeypatch: pytest.MonkeyPatch) -> None:
    """The current folder is the examples', as a user's own folder (found without help)."""
    monkeypatch.chdir(EXAMPLES)
    monkeypatch.setattr(sys, "path", [entry for entry in sys.path if entry not in ("", ".")])
    monkeypatch.delitem(sys.modules, EXAMPLE.partition(":")[0], raising=False)


@pytest.mark.parametrize("driver", ["drift", "weave", "speeding"])
def test_the_minimal_example_keeps_reckless_drivers_inside_on_the_true_state(in_examples, driver):
    safety = FilterConfig(kind=EXAMPLE)
    env = make_task_env("CenterLine", "lab", 1, safety, 0, max_steps=max_steps_for(20.0))
    assert isinstance(env, ProtocolSafetyFilter)
    result = run_episode(env, make_agent(driver, env, seed=0), seed=0)
    env.close()
    assert result.summary["time_outside_lane_s"] == 0.0
    assert result.summary["intervention_rate"] > 0.05  # it was needed
    assert result.summary["clipped_steps"] == 0  # it answers within the limits
    assert filter_words(safety) == f"{EXAMPLE} on the true state"


def test_without_the_example_the_same_drivers_leave():
    for driver in ("drift", "weave", "speeding"):
        env = make_task_env("CenterLine", "lab", 1, FilterConfig(), 0, max_steps=max_steps_for(20))
        result = run_episode(env, make_agent(driver, env, seed=0), seed=0)
        env.close()
        assert result.summary["time_outside_lane_s"] > 0.0, driver


class ScrambledTruth(gym.Wrapper):
    """The task with the simulator's state of the car in ``info`` replaced by noise."""

    TRUTH = ("e_y_m", "e_psi_rad", "kappa_radpm", "x_m", "y_m", "yaw_rad", "v_y_mps")

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.rng = np.random.default_rng(0)

    def reset(self, **kwargs):
        observation, info = self.env.reset(**kwargs)
        return observation, self.scrambled(info)

    def step(self, action):
        *result, info = self.env.step(action)
        return (*result, self.scrambled(info))

    def scrambled(self, info: dict) -> dict:
        return {**info, **{name: float(self.rng.normal()) for name in self.TRUTH}}


class FixedSource:
    """A state source that sees the same lane state whatever happens."""

    reads_image = True

    def reset(self, seed: int | None = None) -> None:
        pass

    def samples(self, observation: dict, info: dict) -> np.ndarray:
        return np.array([[0.1, 0.02, 0.0], [0.12, 0.0, 0.0]])


def test_a_filter_is_handed_the_perception_sensors_and_map_but_no_truth():
    """The same actions in the same task, once with the car's true state in ``info``
    scrambled: a filter fed a fixed perception sees the very same views (and a copy of the
    map, not the env's)."""
    assert {field.name for field in dataclasses.fields(FilterSetup)} == SETUP_FIELDS
    assert {field.name for field in dataclasses.fields(FilterView)} == VIEW_FIELDS
    seen = []
    for wrap in (lambda env: env, ScrambledTruth):
        env = lab()
        wrapped = ProtocolSafetyFilter(wrap(env), Spy, FixedSource(), "spy", seed=0)
        method = wrapped.method
        assert isinstance(method, Spy) and method.setup.track is not env.unwrapped.track
        wrapped.reset(seed=0)
        for step in range(15):
            wrapped.step(np.array([0.2 * np.sin(step), 1.0]))
        seen.append(method.views)
        env.close()
    plain, scrambled = seen
    assert len(plain) == 15
    for one, other in zip(plain, scrambled, strict=True):
        for name in VIEW_FIELDS:
            np.testing.assert_array_equal(getattr(one, name), getattr(other, name), err_msg=name)
    assert plain[-1].velocity[0] > 0.0 and plain[-1].s_m > plain[0].s_m
    assert plain[0].mean[0] == pytest.approx(0.11) and plain[0].lower[0] < 0.11 < plain[0].upper[0]


class Unresettable(Spy):
    """A filter whose reset raises."""

    def reset(self, seed: int | None = None) -> None:
        raise RuntimeError("no")


@pytest.mark.parametrize(
    ("factory", "words"),
    [
        (lambda setup: 1 / 0, "spy raised when made: ZeroDivisionError"),
        (lambda setup: Unresettable(setup), "spy raised in reset: RuntimeError: no"),
    ],
)
def test_a_filter_that_raises_made_or_reset_ends_each_run_at_its_first_step(factory, words):
    env = lab()
    wrapped = ProtocolSafetyFilter(env, factory, name="spy", seed=0)
    for seed in (0, 1):
        wrapped.reset(seed=seed)
        *_, truncated, info = wrapped.step(np.zeros(2))
        assert truncated and words in info["filter_error"]
    env.close()


def test_an_answer_outside_the_limits_is_clipped_and_counted():
    env = lab(2.0)
    wrapped, _ = spied(env, answer=np.array([5.0, 100.0]))
    applied: list[np.ndarray] = []
    result = run_episode(
        wrapped,
        lambda observation, info: np.zeros(2),
        seed=0,
        on_step=lambda observation, info, action: applied.append(action),
    )
    env.close()
    high = env.action_space.high  # type: ignore[attr-defined]
    np.testing.assert_allclose(applied, np.tile(high, (len(applied), 1)), rtol=1e-6)
    assert result.summary["clipped_steps"] == len(applied) > 0
    assert result.summary["intervention_rate"] == 1.0


def test_a_filter_that_raises_ends_its_run_with_a_report():
    env = lab()
    wrapped, made = spied(env, fail_at=7)
    result = run_episode(wrapped, lambda observation, info: np.array([0.0, 1.0]), seed=0)
    assert result.truncated and not result.terminated
    assert len(result.steps["steer_rad"]) == 7
    assert result.filter_error is not None
    assert "spy raised at 0.30 s: ValueError: a bug in the filter" in result.filter_error
    assert result.ending == f"ended: {result.filter_error}"
    wrapped.reset(seed=1)  # the next run starts clean
    assert wrapped.error is None and made[0].views == []
    env.close()


@pytest.mark.parametrize("answer", [np.array([np.nan, 0.0]), np.zeros(3)])
def test_an_answer_that_is_no_action_ends_the_run(answer):
    env = lab()
    wrapped, _ = spied(env, answer=answer)
    wrapped.reset(seed=0)
    *_, truncated, info = wrapped.step(np.zeros(2))
    assert truncated
    assert "must return 2 finite numbers" in info["filter_error"]
    env.close()


def test_env_checker_passes_behind_a_filter_of_ones_own(in_examples):
    """What users check before they train: a valid gymnasium env, its info the same for the
    same seed and actions."""
    env = apply_filter(lab(), FilterConfig(kind=EXAMPLE))
    check_env(env, skip_render_check=True)
    env.close()


def test_a_factory_that_makes_no_filter_is_refused():
    env = lab()
    with pytest.raises(SafeRaceError, match="no safety filter"):
        ProtocolSafetyFilter(env, lambda setup: object(), name="nothing")  # type: ignore[arg-type]
    env.close()


def test_a_filter_of_ones_own_is_loaded_from_the_current_folder(in_examples):
    env = apply_filter(lab(), FilterConfig(kind=EXAMPLE), seed=0)
    assert isinstance(env, ProtocolSafetyFilter) and env.name == EXAMPLE
    assert type(env.method).__name__ == "BrakeNearEdge"
    env.close()


@pytest.mark.parametrize(
    ("setting", "value"), [("slack", "l1"), ("opponent_noise_m", 0.1), ("map_curvature", True)]
)
def test_our_filters_settings_are_refused_for_ones_own(setting, value):
    with pytest.raises(ConfigError, match=setting):
        FilterConfig(kind=EXAMPLE, **{setting: value})


@pytest.mark.parametrize("kind", ["cbff", "module:", ":factory"])
def test_a_filter_name_that_is_none_of_ours_nor_module_factory_is_refused(kind):
    with pytest.raises(ConfigError, match="MODULE:FACTORY"):
        FilterConfig(kind=kind)


def test_an_eval_row_says_what_the_filter_raised_and_keeps_only_its_settings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    (tmp_path / "late_bug.py").write_text(
        "class LateBug:\n"
        "    def reset(self, seed=None):\n        pass\n"
        "    def certify(self, action, view):\n"
        "        if view.time_s > 0.52:\n            raise KeyError('gone')\n"
        "        return action\n"
        "def make(setup):\n    return LateBug()\n"
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.delitem(sys.modules, "late_bug", raising=False)
    safety = FilterConfig(kind="late_bug:make", state_noise=(0.05, 0.05))
    (row,) = evaluate("drift", "CenterLine", "lab", [0], progress=False, safety=safety)
    assert row["filter_error"] == "late_bug:make raised at 0.55 s: KeyError: 'gone'"
    assert row["ending"] == f"ended: {row['filter_error']}"
    assert set(row["filter"]) == set(USERS_FILTER_SETTINGS)
    assert row_filter(row) == safety
