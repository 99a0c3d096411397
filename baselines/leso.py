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

from blf_gym.plugins.blocks import model_length, nominal_acceleration, nominal_length, nominal_model_into

__all__ = ["leso_rhs", "leso_ode3", "LESO"]


@njit(cache=True, error_model="numpy", inline="always")
def leso_rhs(y, u, x1_hat, x2_hat, x3_hat, k0, nominal, work, d_x1_hat, d_x2_hat, d_x3_hat):
    """The observer's ``rhs`` over named signals (blf_gym.plugins.blocks); ``k0`` is its bandwidth, 1/s."""
    n = y.shape[0]
    c = work[:n]
    g = work[n : 2 * n]
    acc = work[3 * n : 4 * n]
    # F(y, x2_hat) + M^-1 u = M^-1 (u - C(y, x2_hat) x2_hat - G(y))
    nominal_acceleration(nominal, x2_hat, u, c, g, acc)
    l1 = 3.0 * k0
    l2 = 3.0 * k0 * k0
    l3 = k0 * k0 * k0
    for i in range(n):
        err = y[i] - x1_hat[i]
        d_x1_hat[i] = x2_hat[i] + l1 * err
        d_x2_hat[i] = acc[i] + x3_hat[i] + l2 * err
        d_x3_hat[i] = l3 * err


class LESO:
    """A thin stateful observer for sampled use (baseline policies, notebooks).

    Integrates :func:`leso_rhs` with the same ODE3 scheme as the closed loop, holding y and u over
    each step of length ``dt``. ``nominal`` is the arm's ``ArmParams.pack()`` (default the paper's
    arm); the number of joints ``n`` is read from it (given, it must agree).
    """

    def __init__(self, k0: float = 200.0, nominal: np.ndarray | None = None, n: int | None = None) -> None:
        from blf_gym.model.params import ArmParams

        if not (np.isfinite(k0) and k0 > 0):
            raise ValueError(f"LESO.k0 must be a finite number > 0, got {k0!r}")
        self.gains = np.array([float(k0)])
        self.nominal = ArmParams().pack() if nominal is None else np.asarray(nominal, dtype=float)
        if self.nominal.ndim != 1 or self.nominal.size < 3 or self.nominal.size % 2 != 1:
            raise ValueError(f"LESO.nominal must be an ArmParams.pack() (2 n + 1 entries), got shape "
                             f"{self.nominal.shape}")
        links = (self.nominal.size - 1) // 2
        if n is not None and n != links:
            raise ValueError(f"LESO.n = {n!r} but the nominal arm has {links} links")
        n = self.n = links
        self.xhat = np.zeros(3 * n)
        self._work = np.empty(2 * n * n + 12 * n)

    def reset(self, y0: np.ndarray) -> np.ndarray:
        self.xhat = np.zeros(3 * self.n)
        self.xhat[: self.n] = y0
        return self.xhat.copy()

    def step(self, y: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """Advance by ``dt`` with measurement ``y`` and torque ``u`` held; return the new state."""
        self.xhat = leso_ode3(self.xhat, np.asarray(y, float), np.asarray(u, float), self.nominal,
                              self.gains, float(dt), self._work)
        return self.xhat.copy()


@njit(cache=True, error_model="numpy")
def leso_ode3(xhat, y, u, nominal, gains, dt, work):
    """The LESO's state ``xhat`` after one ODE3 step of ``dt`` with the sampled measurement ``y`` and
    torque ``u`` held (the sampled observer of :class:`LESO` and of the sampled policies)."""
    m = xhat.shape[0]
    n = y.shape[0]
    k0 = gains[0]
    model = np.zeros(nominal_length(n))
    nominal_model_into(y, nominal, model, work)
    o = model_length(n)
    for i in range(2 * n + 1):
        model[o + i] = nominal[i]
    k1 = np.empty(m)
    k2 = np.empty(m)
    k3 = np.empty(m)
    xs = np.empty(m)
    _rhs(y, u, xhat, k0, model, work, k1)
    for i in range(m):
        xs[i] = xhat[i] + 0.5 * dt * k1[i]
    _rhs(y, u, xs, k0, model, work, k2)
    for i in range(m):
        xs[i] = xhat[i] + 0.75 * dt * k2[i]
    _rhs(y, u, xs, k0, model, work, k3)
    out = np.empty(m)
    for i in range(m):
        out[i] = xhat[i] + dt * ((2.0 / 9.0) * k1[i] + (1.0 / 3.0) * k2[i] + (4.0 / 9.0) * k3[i])
    return out


@njit(cache=True, error_model="numpy", inline="always")
def _rhs(y, u, xhat, k0, nominal, work, dx):
    n = y.shape[0]
    leso_rhs(y, u, xhat[:n], xhat[n : 2 * n], xhat[2 * n :], k0, nominal, work, dx[:n], dx[n : 2 * n], dx[2 * n :])
