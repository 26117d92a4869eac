"""The batched matrix exponential against 50-digit ones, on every branch of its algorithm."""

from __future__ import annotations

import mpmath
import numpy as np
import pytest

from saferace.safety.matrix_exponential import expm_batch


def exact_expm(matrix: np.ndarray) -> np.ndarray:
    """``exp(matrix)`` in 50 digits (scipy's own is off by 1e-11 at a 1-norm of 200)."""
    with mpmath.workdps(50):
        return np.array(mpmath.expm(mpmath.matrix(matrix.tolist())).tolist(), dtype=float)


@pytest.mark.parametrize("norm", [0.0149, 0.25, 0.95, 2.09, 5.3, 60.0, 200.0])
def test_each_degree_and_scaling_matches_the_exact_exponential(norm: float):
    """1-norms just below each Pade degree's threshold (3, 5, 7, 9: where its highest
    powers weigh most), and above the last (degree 13 with none, a few and many
    squarings). Positive entries make the powers as large as the norm allows."""
    rng = np.random.default_rng(int(norm * 1000))
    matrices = np.abs(rng.normal(size=(4, 9, 9)))
    matrices *= norm / np.abs(matrices).sum(axis=-2).max()
    exact = np.array([exact_expm(m) for m in matrices])
    scale = np.abs(exact).max(axis=(-2, -1), keepdims=True)
    np.testing.assert_allclose(expm_batch(matrices) / scale, exact / scale, rtol=0, atol=1e-12)


def test_a_batch_of_mixed_norms_and_leading_axes():
    rng = np.random.default_rng(3)
    matrices = rng.normal(size=(2, 3, 5, 5)) * np.array([0.01, 1.0, 30.0])[None, :, None, None]
    exact = np.array([[exact_expm(m) for m in row] for row in matrices])
    result = expm_batch(matrices)
    assert result.shape == matrices.shape
    scale = np.abs(exact).max(axis=(-2, -1), keepdims=True)
    np.testing.assert_allclose(result / scale, exact / scale, rtol=0, atol=1e-12)


def test_a_rotation_and_a_zero_matrix():
    """Hand-computed: exp of a skew generator turns by its angle, exp(0) is the identity."""
    angle = 2.5
    generator = np.array([[0.0, -angle], [angle, 0.0]])
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    result = expm_batch(np.stack([generator, np.zeros((2, 2))]))
    np.testing.assert_allclose(result[0], rotation, atol=1e-14)
    np.testing.assert_allclose(result[1], np.eye(2), rtol=0, atol=1e-15)
