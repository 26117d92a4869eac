"""Linear interpolation of a quantity sampled along a closed track."""

from __future__ import annotations

from bisect import bisect_right
from typing import overload

import numpy as np


class PeriodicInterpolator:
    """``f(s)`` interpolating ``values`` at increasing ``s_m`` in ``[0, period)``, wrapping around.

    Scalars take a bisect on Python lists (about a microsecond, for per-step use);
    arrays go through ``numpy.interp``. ``np.interp(..., period=...)`` sorts its
    inputs on every call, which costs tens of microseconds.
    """

    def __init__(self, s_m: np.ndarray, values: np.ndarray, period_m: float) -> None:
        s_m = np.asarray(s_m, dtype=float)
        values = np.asarray(values, dtype=float)
        self.period_m = float(period_m)
        # Extend by one sample on each side so that every s in [0, period) has neighbours.
        self._s = np.concatenate([[s_m[-1] - period_m], s_m, [s_m[0] + period_m]])
        self._v = np.concatenate([[values[-1]], values, [values[0]]])
        self._s_list = self._s.tolist()
        self._v_list = self._v.tolist()

    @overload
    def __call__(self, s_m: float) -> float: ...
    @overload
    def __call__(self, s_m: np.ndarray) -> np.ndarray: ...
    @overload
    def __call__(self, s_m: np.ndarray | float) -> np.ndarray | float: ...
    def __call__(self, s_m: np.ndarray | float) -> np.ndarray | float:
        """The value at ``s_m``: a float for a Python (or NumPy 64-bit) scalar, else an array."""
        if isinstance(s_m, float | int):
            s = s_m % self.period_m
            i = bisect_right(self._s_list, s) - 1
            s0, s1 = self._s_list[i], self._s_list[i + 1]
            v0, v1 = self._v_list[i], self._v_list[i + 1]
            return v0 + (v1 - v0) * (s - s0) / (s1 - s0)
        return np.interp(np.mod(s_m, self.period_m), self._s, self._v)
