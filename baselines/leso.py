"""Linear extended state observer (paper eqs. 8-10), with bandwidth parametrisation.

Only the joint angles y are measured. With gain k0 (observer poles all at -k0)::

    x1_hat' = x2_hat + 3 k0 (y - x1_hat)
    x2_hat' = F(y, x2_hat) + M(y)^-1 u + x3_hat + 3 k0^2 (y - x1_hat)
    x3_hat' = k0^3 (y - x1_hat)

with F(y, v) = -M(y)^-1 (C(y, v) v + G(y)) from the nominal model and u the torque actually
commanded (after any residual and the actuator limit, before the dead-zone, which therefore is part
of the lumped disturbance x3 the observer estimates).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from blf_gym.controller import model_length, nominal_model_into
from blf_gym.dynamics import ldl_solve_factored, coriolis_times_into

__all__ = ["leso_rhs", "LESO"]


@njit(cache=True, error_model="numpy", inline="always")
def leso_rhs(y, xhat, u, nominal, model, gains, dxhat, work):
    """Observer right-hand side (blf_gym observer signature); ``gains = [k0]``."""
    n = y.shape[0]
    k0 = gains[0]
    nn = n * n
    g = model[nn : nn + n]
    trig = model[nn + n : nn + 3 * n]
    chol = model[nn + 3 * n : 2 * nn + 3 * n]
    c = work[:n]
    r = work[n : 2 * n]
    acc = work[2 * n : 3 * n]
    dyn = work[3 * n : 6 * n]
    x2 = xhat[n : 2 * n]
    # F(y, x2_hat) + M^-1 u = M^-1 (u - C(y, x2_hat) x2_hat - G(y))
    coriolis_times_into(trig, x2, x2, nominal, c, dyn)
    for i in range(n):
        r[i] = u[i] - c[i] - g[i]
    ldl_solve_factored(chol, r, acc)
    l1 = 3.0 * k0
    l2 = 3.0 * k0 * k0
    l3 = k0 * k0 * k0
    for i in range(n):
        err = y[i] - xhat[i]
        dxhat[i] = xhat[n + i] + l1 * err
        dxhat[n + i] = acc[i] + xhat[2 * n + i] + l2 * err
        dxhat[2 * n + i] = l3 * err


class LESO:
    """A thin stateful observer for sampled use (baseline policies, notebooks).

    Integrates :func:`leso_rhs` with the same ODE3 scheme as the closed loop, holding y and u over
    each step of length ``dt``.
    """

    def __init__(self, k0: float = 200.0, nominal: np.ndarray | None = None, n: int = 3) -> None:
        from blf_gym.params import ArmParams

        if not (np.isfinite(k0) and k0 > 0):
            raise ValueError(f"LESO.k0 must be a finite number > 0, got {k0!r}")
        self.gains = np.array([float(k0)])
        self.nominal = ArmParams().pack() if nominal is None else np.asarray(nominal, dtype=float)
        self.n = n
        self.xhat = np.zeros(3 * n)
        self._work = np.empty(2 * n * n + 12 * n)

    def reset(self, y0: np.ndarray) -> np.ndarray:
        self.xhat = np.zeros(3 * self.n)
        self.xhat[: self.n] = y0
        return self.xhat.copy()

    def step(self, y: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """Advance by ``dt`` with measurement ``y`` and torque ``u`` held; return the new state."""
        self.xhat = _leso_ode3(self.xhat, np.asarray(y, float), np.asarray(u, float), self.nominal,
                               self.gains, float(dt), self._work)
        return self.xhat.copy()


@njit(cache=True, error_model="numpy")
def _leso_ode3(xhat, y, u, nominal, gains, dt, work):
    m = xhat.shape[0]
    model = np.empty(model_length(y.shape[0]))
    nominal_model_into(y, nominal, model, work)
    k1 = np.empty(m)
    k2 = np.empty(m)
    k3 = np.empty(m)
    xs = np.empty(m)
    leso_rhs(y, xhat, u, nominal, model, gains, k1, work)
    for i in range(m):
        xs[i] = xhat[i] + 0.5 * dt * k1[i]
    leso_rhs(y, xs, u, nominal, model, gains, k2, work)
    for i in range(m):
        xs[i] = xhat[i] + 0.75 * dt * k2[i]
    leso_rhs(y, xs, u, nominal, model, gains, k3, work)
    out = np.empty(m)
    for i in range(m):
        out[i] = xhat[i] + dt * ((2.0 / 9.0) * k1[i] + (1.0 / 3.0) * k2[i] + (4.0 / 9.0) * k3[i])
    return out
