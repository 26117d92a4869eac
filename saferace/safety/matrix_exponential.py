"""The matrix exponentials of a batch of small matrices, compiled by numba.

Every control step the expert and the predictive filter discretise each of their 20 stages
exactly, by one matrix exponential each. ``scipy.linalg.expm`` treats a batch one matrix
at a time in Python (about 6 us each, 0.12-0.26 ms a step), and the same algorithm in
batched numpy calls still spent about 50 us a step on the calls themselves; compiled, a
9x9 exponential takes about 1 us. The algorithm is scipy's: scaling and squaring with a
diagonal Pade approximant of the degree and scaling that each matrix's 1-norm needs
(Higham 2005, "The scaling and squaring method for the matrix exponential revisited").
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Pade degrees with the largest 1-norm each is accurate to unit roundoff for (Higham
#: 2005, Table 2.3), and the coefficients of their numerators.
_PADE_DEGREES: tuple[tuple[int, float, tuple[float, ...]], ...] = (
    (3, 1.495585217958292e-2, (120.0, 60.0, 12.0, 1.0)),
    (5, 2.539398330063230e-1, (30240.0, 15120.0, 3360.0, 420.0, 30.0, 1.0)),
    (
        7,
        9.504178996162932e-1,
        (17297280.0, 8648640.0, 1995840.0, 277200.0, 25200.0, 1512.0, 56.0, 1.0),
    ),
    (
        9,
        2.097847961257068e0,
        (
            17643225600.0, 8821612800.0, 2075673600.0, 302702400.0, 30270240.0,
            2162160.0, 110880.0, 3960.0, 90.0, 1.0,
        ),
    ),
)  # fmt: skip
_THETA_13 = 5.371920351148152
_PADE_13: tuple[float, ...] = (
    64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
    129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0,
    40840800.0, 960960.0, 16380.0, 182.0, 1.0,
)  # fmt: skip


#: The same tables as arrays, for the compiled code: degrees, their 1-norm bounds, and
#: their numerators' coefficients (zero-padded).
_DEGREES = np.array([degree for degree, _, _ in _PADE_DEGREES])
_THETAS = np.array([theta for _, theta, _ in _PADE_DEGREES])
_COEFFICIENTS = np.array([c + (0.0,) * (10 - len(c)) for _, _, c in _PADE_DEGREES])
_COEFFICIENTS_13 = np.array(_PADE_13)


def expm_batch(matrices: np.ndarray) -> np.ndarray:
    """``exp(M)`` of each square matrix ``M`` over the last two axes of ``matrices``."""
    matrices = np.asarray(matrices, dtype=float)
    size = matrices.shape[-1]
    stacked = np.ascontiguousarray(np.moveaxis(matrices.reshape(-1, size, size), 0, -1))
    return np.moveaxis(expm_stacked(stacked), -1, 0).reshape(matrices.shape)


@njit(cache=True)
def expm_stacked(matrices: np.ndarray) -> np.ndarray:
    """``exp`` of each of a batch of square matrices stacked along the *last* axis
    (``(n, n, batch)``, C-contiguous): every operation loops over the batch innermost,
    where the CPU's vector units take several matrices at once. The batch's largest
    1-norm picks the degree and the scaling, as for a single matrix of that norm."""
    n, batch = matrices.shape[0], matrices.shape[2]
    norm = 0.0
    for b in range(batch):
        for j in range(n):
            column = 0.0
            for i in range(n):
                column += abs(matrices[i, j, b])
            norm = max(norm, column)
    index = 0
    while index < len(_DEGREES) and norm > _THETAS[index]:
        index += 1
    squarings = 0
    if index == len(_DEGREES):
        squarings = max(0, math.ceil(math.log2(norm / _THETA_13)))
    a = matrices / 2.0**squarings
    square = _matmul(a, a)
    if index < len(_DEGREES):  # odd = sum c_{2j+1} A^2j, even = sum c_2j A^2j
        coefficients = _COEFFICIENTS[index]
        odd = _identity(n, batch, coefficients[1])
        even = _identity(n, batch, coefficients[0])
        power = _identity(n, batch, 1.0)
        for j in range(1, _DEGREES[index] // 2 + 1):
            power = _matmul(power, square)
            odd += coefficients[2 * j + 1] * power
            even += coefficients[2 * j] * power
    else:  # degree 13 in Higham's nested form
        c = _COEFFICIENTS_13
        a4 = _matmul(square, square)
        a6 = _matmul(a4, square)
        odd = _matmul(a6, c[13] * a6 + c[11] * a4 + c[9] * square)
        odd += c[7] * a6 + c[5] * a4 + c[3] * square + _identity(n, batch, c[1])
        even = _matmul(a6, c[12] * a6 + c[10] * a4 + c[8] * square)
        even += c[6] * a6 + c[4] * a4 + c[2] * square + _identity(n, batch, c[0])
    odd = _matmul(a, odd)  # the numerator's odd part, times the matrix
    result = _solve(even - odd, even + odd)
    for _ in range(squarings):
        result = _matmul(result, result)
    return result


@njit(cache=True)
def _identity(n: int, batch: int, value: float) -> np.ndarray:
    out = np.zeros((n, n, batch))
    for i in range(n):
        out[i, i, :] = value
    return out


@njit(cache=True)
def _matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` of each pair of stacked matrices (``(n, n, batch)``)."""
    n, batch = a.shape[0], a.shape[2]
    out = np.zeros((n, n, batch))
    for i in range(n):
        for k in range(n):
            for j in range(n):
                for s in range(batch):
                    out[i, j, s] += a[i, k, s] * b[k, j, s]
    return out


@njit(cache=True)
def _solve(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``matrix^-1 rhs`` of each pair of stacked matrices, by Gaussian elimination with
    partial pivoting (each of the batch its own pivots; ``matrix`` is overwritten)."""
    n, batch = matrix.shape[0], matrix.shape[2]
    x = rhs.copy()
    for s in range(batch):  # the pivots: rows swapped per matrix of the batch
        for col in range(n):
            pivot = col
            for row in range(col + 1, n):
                if abs(matrix[row, col, s]) > abs(matrix[pivot, col, s]):
                    pivot = row
            if pivot != col:
                for j in range(n):
                    matrix[col, j, s], matrix[pivot, j, s] = matrix[pivot, j, s], matrix[col, j, s]
                    x[col, j, s], x[pivot, j, s] = x[pivot, j, s], x[col, j, s]
            for row in range(col + 1, n):
                factor = matrix[row, col, s] / matrix[col, col, s]
                for j in range(col, n):
                    matrix[row, j, s] -= factor * matrix[col, j, s]
                for j in range(n):
                    x[row, j, s] -= factor * x[col, j, s]
    for col in range(n - 1, -1, -1):
        for j in range(n):
            for k in range(col + 1, n):
                for s in range(batch):
                    x[col, j, s] -= matrix[col, k, s] * x[k, j, s]
            for s in range(batch):
                x[col, j, s] /= matrix[col, col, s]
    return x
