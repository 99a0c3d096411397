"""The plant's uncertainties: joint friction, the input dead-zone and the external-force schedule.

Compiled scalar functions used inside the closed-loop kernel; their parameters come from the
packed plant vector (:meth:`blf_gym.model.params.Scenario.pack_plant`).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit import vmath

__all__ = ["friction", "friction_exponent", "friction_from", "dead_zone", "force_active", "dead_zone_array"]


@njit(cache=True, error_model="numpy", inline="always")
def _tanh(z):
    # tanh through one exp (libm's tanh goes through expm1 and costs about twice as much); the
    # absolute error is below 2e-16, which is what the friction term needs.
    return _tanh_from(z, vmath.exp(_tanh_exponent(z)))


@njit(cache=True, error_model="numpy", inline="always")
def _tanh_exponent(z):
    return -2.0 * abs(z)


@njit(cache=True, error_model="numpy", inline="always")
def _tanh_from(z, e):
    r = (1.0 - e) / (1.0 + e)
    return r if z >= 0.0 else -r


@njit(cache=True, error_model="numpy", inline="always")
def friction(qd, viscous, coulomb, tanh_slope):
    """tau_fric = b qd + c tanh(psi qd) for one joint (paper eq. 2), N m."""
    z = tanh_slope * qd
    return friction_from(qd, viscous, coulomb, z, vmath.exp(_tanh_exponent(z)))


@njit(cache=True, error_model="numpy", inline="always")
def friction_exponent(qd, tanh_slope):
    """The exponent -2 |psi qd| whose exponential gives the friction's tanh."""
    return _tanh_exponent(tanh_slope * qd)


@njit(cache=True, error_model="numpy", inline="always")
def friction_from(qd, viscous, coulomb, z, e):
    """:func:`friction` given z = psi qd and e = e^(-2 |z|) (the closed loop's kernel evaluates the
    exponentials of every joint and of the bounds in one loop)."""
    return viscous * qd + coulomb * _tanh_from(z, e)


@njit(cache=True, error_model="numpy", inline="always")
def dead_zone(tau, slope_right, slope_left, break_right, break_left):
    """The asymmetric dead-zone H(tau) of paper eq. (3), N m."""
    if tau >= break_right:
        return slope_right * (tau - break_right)
    if tau <= break_left:
        return slope_left * (tau - break_left)
    return 0.0


@njit(cache=True, error_model="numpy", inline="always")
def force_active(t, onset):
    """1.0 once the external force is on (step at ``onset``), else 0.0."""
    return 1.0 if t >= onset else 0.0


def dead_zone_array(tau: np.ndarray, slope_right: float = 1.0, slope_left: float = 1.2,
                    break_right: float = 0.2, break_left: float = -0.2) -> np.ndarray:
    """Vectorized :func:`dead_zone` for NumPy arrays (plots and tests)."""
    tau = np.asarray(tau, dtype=float)
    return np.where(tau >= break_right, slope_right * (tau - break_right),
                    np.where(tau <= break_left, slope_left * (tau - break_left), 0.0))
