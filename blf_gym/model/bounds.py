"""Time-varying output-error bounds k_a(t), k_b(t) and their time derivatives (paper eq. 17).

The tracking error e1 = q - q_d must stay in the open interval (-k_b(t), k_a(t)).
Constraint margins follow the g(t, q) <= 0 convention: g_upper = e1 - k_a and g_lower = -k_b - e1,
and a sample violates when max(g_upper, g_lower) >= 0.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit import vmath

from blf_gym.jit.layout import BOUND, BOUND_SIGNALS, BOUNDS
from blf_gym.model.params import BoundParams

__all__ = ["bounds_into", "bounds_exponent", "bounds_from", "error_bounds", "log_rate", "BOUND_SIGNALS", "BOUND_LEN"]

BOUND_LEN = BOUND.length()
"""Entries of the bound signal (:data:`blf_gym.jit.layout.BOUND`)."""
KA, KA_DOT, KA_DDOT, KB, KB_DOT, KB_DDOT = (BOUND.index(k) for k in ("k_a", "k_a_dot", "k_a_ddot", "k_b", "k_b_dot",
                                                                   "k_b_ddot"))
_AMP_A, _FLOOR_A, _AMP_B, _FLOOR_B, _RATE = (BOUNDS.index(k) for k in ("upper_amplitude", "upper_floor",
                                                                       "lower_amplitude", "lower_floor", "decay_rate"))


@njit(cache=True, error_model="numpy", inline="always")
def bounds_into(t, bp, out):
    """Write ``[k_a, k_a', k_a'', k_b, k_b', k_b'']`` at time ``t`` into ``out``.

    ``bp`` is :meth:`BoundParams.pack`, laid out as :data:`blf_gym.jit.layout.BOUNDS`.
    """
    bounds_from(vmath.exp(bounds_exponent(t, bp)), bp, out)


@njit(cache=True, error_model="numpy", inline="always")
def log_rate(k, k_dot, k_ddot):
    """``(k'/k, d/dt (k'/k))`` of a bound k > 0: the rate of ln k and its derivative (the proposed
    law's ra, rb and their rates; prescribed-performance control's e-free terms)."""
    return k_dot / k, (k_ddot * k - k_dot * k_dot) / (k * k)


@njit(cache=True, error_model="numpy", inline="always")
def bounds_exponent(t, bp):
    """-r t, the exponent of the bounds' decay at time ``t``."""
    return -bp[_RATE] * t


@njit(cache=True, error_model="numpy", inline="always")
def bounds_from(decay, bp, out):
    """:func:`bounds_into` given e^(-r t) (the closed loop's kernel evaluates it with the friction's
    exponentials in one loop)."""
    r = bp[_RATE]
    a = bp[_AMP_A] * decay
    b = bp[_AMP_B] * decay
    out[KA] = a + bp[_FLOOR_A]
    out[KA_DOT] = -r * a
    out[KA_DDOT] = r * r * a
    out[KB] = b + bp[_FLOOR_B]
    out[KB_DOT] = -r * b
    out[KB_DDOT] = r * r * b


def error_bounds(t: np.ndarray | float, params: BoundParams = BoundParams()) -> tuple[np.ndarray, np.ndarray]:
    """(k_a(t), k_b(t)) in rad, vectorized over ``t`` (NumPy; for plots and tests)."""
    t = np.asarray(t, dtype=float)
    decay = np.exp(-params.decay_rate * t)
    return (params.upper_amplitude * decay + params.upper_floor,
            params.lower_amplitude * decay + params.lower_floor)
