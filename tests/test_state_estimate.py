"""What a filter reads each step (:mod:`saferace.safety.uncertainty.estimate`): the agent's
action checked, the state source's interval with the map's curvature pinned, unbounded
intervals in doubt, and the decision's record of the state, each worked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from saferace.safety.uncertainty.estimate import checked_action, estimate_state

DEFAULT_STD, MIN_STD = np.array([0.1, 1.0]), np.array([0.02, 0.2])


@pytest.mark.parametrize("action", [[0.1, 0.2, 0.3], [0.1], [math.nan, 0.0], [0.0, math.inf]])
def test_an_action_of_another_shape_or_not_finite_is_refused(action: list[float]):
    with pytest.raises(ValueError, match="2 finite numbers"):
        checked_action(action, None, DEFAULT_STD, MIN_STD)


def test_an_actions_spread_is_the_agents_or_the_default_and_never_below_the_floor():
    nominal, spread = checked_action([0.1, -1.0], None, DEFAULT_STD, MIN_STD)
    assert nominal.tolist() == [0.1, -1.0] and spread.tolist() == [0.1, 1.0]
    assert checked_action([0.1, -1.0], [0.001, 0.5], DEFAULT_STD, MIN_STD)[1].tolist() == [
        0.02,
        0.5,
    ]


class BoxSource:
    """Two samples ``centre +- [0.1, 0.02, 0.3]`` (mean the centre, std those) and the
    interval ``lower .. upper``."""

    def __init__(self, lower: list[float], upper: list[float]) -> None:
        self.lower, self.upper = np.array(lower), np.array(upper)

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset."""

    def samples(self, observation: dict, info: dict) -> np.ndarray:
        centre, spread = np.array([0.2, 0.05, 0.5]), np.array([0.1, 0.02, 0.3])
        return np.stack([centre - spread, centre + spread])

    def interval(self, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.lower.copy(), self.upper.copy()


INFO = {"e_y_m": 0.25, "e_psi_rad": 0.04, "kappa_radpm": 0.9}  # the truth


def test_the_map_pins_the_curvature_and_the_record_checks_what_the_source_gave():
    source = BoxSource([0.0, 0.0, 0.0], [0.3, 0.1, 0.6])  # holds e_y and e_psi, not kappa
    pinned = estimate_state(source, {}, INFO, 1.645, 0.4)
    assert pinned.map_curvature and pinned.lower[2] == pinned.upper[2] == 0.4
    record = pinned.fields(INFO, 0.4)
    assert record["covered"]  # the map's curvature is not checked against the truth
    assert record["state_mean"] == pytest.approx([0.2, 0.05, 0.4])
    assert record["state_std"] == pytest.approx([0.1, 0.02, 0.0])
    own = estimate_state(source, {}, INFO, 1.645, None)
    assert not own.map_curvature and own.upper[2] == 0.6
    record = own.fields(INFO, 0.5)
    assert not record["covered"]  # the source's curvature (up to 0.6) misses 0.9
    assert record["state_std"] == pytest.approx([0.1, 0.02, 0.3])


@pytest.mark.parametrize(
    ("lower", "upper", "covered"),
    [
        ([0.0, 0.0, 0.0], [0.3, 0.1, 1.0], True),
        ([0.0, 0.05, 0.0], [0.3, 0.1, 1.0], False),  # e_psi 0.04 below the interval
        ([0.26, 0.0, 0.0], [0.3, 0.1, 1.0], False),  # e_y 0.25 below it
        ([0.0, 0.0, 0.0], [0.2, 0.1, 1.0], False),  # e_y above it
    ],
)
def test_the_record_covers_the_truth_only_where_every_checked_output_lies_inside(
    lower: list[float], upper: list[float], covered: bool
):
    estimate = estimate_state(BoxSource(lower, upper), {}, INFO, 1.645, None)
    assert estimate.fields(INFO, 0.5)["covered"] is covered


@pytest.mark.parametrize("side", ["lower", "upper"])
def test_an_interval_unbounded_on_one_side_is_in_doubt(side: str):
    bounds = {"lower": [0.0, 0.0, 0.0], "upper": [0.3, 0.1, 1.0]}
    bounds[side] = [-math.inf if side == "lower" else math.inf, *bounds[side][1:]]
    estimate = estimate_state(BoxSource(bounds["lower"], bounds["upper"]), {}, INFO, 1.645, 0.4)
    assert not estimate.bounded and estimate.alarm
    bounded = estimate_state(BoxSource([0.0, 0.0, 0.0], [0.3, 0.1, 1.0]), {}, INFO, 1.645, 0.4)
    assert bounded.bounded and not bounded.alarm
