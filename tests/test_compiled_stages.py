"""The plans' compiled per-stage work: the stages laid along the map match the loop over
the path's own scalar evaluations, and the models' generated code is compiled once and
loaded from the cache by the next process."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import sympy as sp

from saferace.safety.frenet_stages import MIN_STAGE_LENGTH_M, stages_along_map
from saferace.safety.model_code import stage_linearisation
from saferace.track import Track, wrap_angle
from saferace.track.track_io import write_track_csv


def python_stages(path, travels_m, offsets_m, s0_m):
    """The stages' arc lengths and mean curvatures, with the path's scalar evaluations."""
    s_stage, kappas = [s0_m], []
    for travel_m, e_y in zip(travels_m, offsets_m, strict=True):
        s_m = s_stage[-1]
        kappa, heading = path.curvature_and_heading_scalar(s_m)
        length = travel_m / (1.0 - kappa * e_y)
        if length >= MIN_STAGE_LENGTH_M:
            kappa = wrap_angle(path.heading_scalar(s_m + length) - heading) / length
        kappas.append(kappa)
        s_stage.append(s_m + travel_m / (1.0 - kappa * e_y))
    return np.array(s_stage), np.array(kappas)


def test_the_stages_along_the_map_are_the_paths_own_across_the_lap_line_and_pi():
    """From 3 m before the lap line on ``technical``, and from 1 m before its heading
    wraps from pi to -pi; offsets either side, and a stage too short to average over (its
    curvature is the start's)."""
    path = Track.load("technical").centerline
    rng = np.random.default_rng(0)
    travels = rng.uniform(0.1, 0.4, 20)
    travels[7] = 0.5 * MIN_STAGE_LENGTH_M
    offsets = rng.uniform(-0.4, 0.4, 20)
    samples = np.arange(0.0, path.length_m, 0.05)
    headings = np.array([path.heading_scalar(s) for s in samples])
    wraps = samples[np.flatnonzero(np.abs(np.diff(headings)) > math.pi)[0]]
    for s0 in (path.length_m - 3.0, wraps - 1.0):
        s_stage, kappas = stages_along_map(
            travels, offsets, s0, path.piece_array, path.knot_spacing_m, path.length_m
        )
        expected_s, expected_kappas = python_stages(path, travels, offsets, s0)
        np.testing.assert_allclose(s_stage, expected_s, rtol=0, atol=1e-12)
        np.testing.assert_allclose(kappas, expected_kappas, rtol=0, atol=1e-12)
        assert kappas[7] == path.curvature_scalar(s_stage[7])
        assert not math.isclose(kappas[8], path.curvature_scalar(s_stage[8]))
        assert s_stage[0] < (path.length_m if s0 > wraps else wraps) < s_stage[-1]


def test_the_stages_round_a_circle_advance_as_its_parallels_say(tmp_path: Path):
    """On a circle of 5 m (anticlockwise), a car 0.4 m inside the centre line travels on a
    circle of 4.6 m: each stage's travel d moves the arc length by d 5 / 4.6, and its mean
    curvature is 1/5; 0.4 m outside, by d 5 / 5.4."""
    angles = np.linspace(0.0, 2.0 * math.pi, 400, endpoint=False)
    path_file = tmp_path / "circle.csv"
    write_track_csv(path_file, 5.0 * np.cos(angles), 5.0 * np.sin(angles), 0.6, 0.6)
    path = Track.load(str(path_file)).centerline
    travels = np.full(12, 0.3)
    for offset_m in (0.4, -0.4):
        s_stage, kappas = stages_along_map(
            travels, np.full(12, offset_m), 2.0, path.piece_array, path.knot_spacing_m,
            path.length_m,
        )  # fmt: skip
        np.testing.assert_allclose(np.diff(s_stage), 0.3 * 5.0 / (5.0 - offset_m), rtol=2e-3)
        np.testing.assert_allclose(kappas, 0.2, rtol=2e-3)


def test_the_compiled_piece_evaluation_is_the_splines_own():
    """A path's scalar position, heading and curvature (the compiled cubic pieces) match
    scipy's spline, also before the start and past the lap line."""
    path = Track.load("technical").centerline
    s = np.random.default_rng(1).uniform(-path.length_m, 2.0 * path.length_m, 500)
    scalar = np.array([path.eval_scalar(value) for value in s])
    np.testing.assert_allclose(scalar[:, :2], path.position(s), rtol=0, atol=1e-9)
    curvature = [path.curvature_scalar(value) for value in s]
    np.testing.assert_allclose(curvature, path.curvature(s), rtol=1e-7, atol=1e-9)
    turn = np.array([path.heading_scalar(value) for value in s]) - path.heading(s)
    np.testing.assert_allclose(np.angle(np.exp(1j * turn)), 0.0, atol=1e-9)


LOAD = """
from saferace.safety.models import FrenetModel, _stage_linearisation
from saferace.safety.vehicle_params import load_params
import numpy as np
model = FrenetModel("kinematic", load_params())
xs = np.ones((3, model.n_state + 1))
model.discretize_stages_with_steering_lag(xs, np.zeros((3, 2)), np.zeros(3), 0.05, 0.04)
stats = _stage_linearisation("kinematic").stats
print(sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))
"""


def test_a_models_code_is_compiled_once_and_loaded_by_the_next_process(tmp_path: Path):
    environment = os.environ | {"SAFERACE_CACHE": str(tmp_path)}
    command = [sys.executable, "-c", LOAD]
    done = [
        subprocess.run(command, env=environment, capture_output=True, text=True, check=True)
        for _ in range(2)
    ]
    runs = [run.stdout.split() for run in done]
    assert runs == [["0", "1"], ["1", "0"]]  # compiled (a miss), then loaded (a hit)
    said = "compiling the kinematic model's equations for this machine, once"
    assert said in done[0].stderr and said not in done[1].stderr  # said where it waits
    (module,) = (tmp_path / "model_code").glob("kinematic_*.py")
    assert "def linearised(" in module.read_text()


def test_without_a_cache_to_write_to_the_code_compiles_in_a_folder_of_its_own(tmp_path: Path):
    blocked = tmp_path / "a file"
    blocked.write_text("")
    environment = os.environ | {"SAFERACE_CACHE": str(blocked / "cache")}
    command = [sys.executable, "-c", LOAD]
    run = subprocess.run(command, env=environment, capture_output=True, text=True, check=True)
    assert run.stdout.split() == ["0", "1"]


def test_changed_equations_under_the_same_models_name_are_new_code(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    """The generated code is keyed by its source, not by the model's name: a model whose
    equations change (``x p + steer`` to ``x p - accel``) is compiled afresh, never served
    the old code from the cache."""
    cache = tmp_path / "not" / "made" / "yet"  # the cache's folders are made as needed
    monkeypatch.setenv("SAFERACE_CACHE", str(cache))
    x, steer, accel, kappa, p = sp.symbols("x steer accel kappa p")
    arguments = (np.array([[2.0]]), np.array([1.0]), np.array([3.0]), np.zeros(1), np.array([5.0]))
    values = [
        stage_linearisation("toy", (x,), (steer, accel), kappa, (p,), [output])(*arguments)
        for output in (x * p + steer, x * p - accel)
    ]
    assert [float(value[0, 0]) for value in values] == [11.0, 7.0]  # 2*5 + 1, 2*5 - 3
    assert len(list((cache / "model_code").glob("toy_*.py"))) == 2
