"""Time-varying output-error bounds k_a(t), k_b(t) and their time derivatives (paper eq. 17).

The tracking error e1 = q - q_d must stay in the open interval (-k_b(t), k_a(t)).
Constraint margins follow the g(t, q) <= 0 convention: g_upper = e1 - k_a and g_lower = -k_b - e1,
and a sample violates when max(g_upper, g_lower) >= 0.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .params import BoundParams

__all__ = ["bounds_into", "error_bounds", "BOUND_LEN"]

BOUND_LEN = 6
"""Length of the vector written by :func:`bounds_into`."""


@njit(cache=True, error_model="numpy", inline="always")
def bounds_into(t, bp, out):
    """Write ``[k_a, k_a', k_a'', k_b, k_b', k_b'']`` at time ``t`` into ``out``.

    ``bp`` is :meth:`BoundParams.pack`: [upper_amplitude, upper_floor, lower_amplitude,
    lower_floor, decay_rate].
    """
    r = bp[4]
    decay = np.exp(-r * t)
    a = bp[0] * decay
    b = bp[2] * decay
    out[0] = a + bp[1]
    out[1] = -r * a
    out[2] = r * r * a
    out[3] = b + bp[3]
    out[4] = -r * b
    out[5] = r * r * b


def error_bounds(t: np.ndarray | float, params: BoundParams = BoundParams()) -> tuple[np.ndarray, np.ndarray]:
    """(k_a(t), k_b(t)) in rad, vectorized over ``t`` (NumPy; for plots and tests)."""
    t = np.asarray(t, dtype=float)
    decay = np.exp(-params.decay_rate * t)
    return (params.upper_amplitude * decay + params.upper_floor,
            params.lower_amplitude * decay + params.lower_floor)
