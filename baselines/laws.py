"""The three control laws of the paper's Section 4.2 as plug-in functions over named signals.

Each is the ``output`` function of a :class:`blf_gym.plugins.blocks.Controller`; its parameter names are the
signals it reads (:mod:`blf_gym.plugins.blocks`) and the outputs it writes. Symbols map to the paper as:
e1 = q - q_d (tracking error, z1), alpha1 (virtual velocity), e2 = v - alpha1 (z2), K1, K2 (Table 2),
k_a/k_b (the error bounds), x3_hat (estimated lumped disturbance).

All three share the backstepping core ``u0 = -K2 e2 + C(y, v) alpha1 + G(y) + M(y) alpha1'`` with
alpha1' computed analytically from the velocity v the law uses (docs/model.md section 5):

* **BC** (full state, v = true qd): alpha1 = qd_d - K1 e1, u = u0 - e1.
* **LESOBC** (v = x2_hat): the same, u = u0 - e1 - M x3_hat.
* **Proposed** (LESO + BLF, v = x2_hat): alpha1 = qd_d - (K1 + lambda1) e1 with
  lambda1 = sqrt((k_a'/k_a)^2 + (k_b'/k_b)^2), u = u0 - kappa - M x3_hat, with the barrier term
  kappa = (h / (k_a^2 - e^2) + (1 - h) / (k_b^2 - e^2)) e, h = 1 if e1 > 0 else 0.

Barrier guard (docs/model.md section 5): the barrier is singular at the bound and changes sign beyond it, so
kappa is evaluated with e1 clipped to ``barrier_clip`` times the bound on its side. The law is
then finite for every finite state, and its stiffness near the bound is limited (the closed loop
stays integrable with ODE3 at 0.1 ms for barrier_clip = 0.95).

LESOBC and the proposed law also publish z1 = e1 and z2_hat = x2_hat - alpha1; the proposed law its
barrier term kappa (1/rad) too.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from blf_gym.plugins.blocks import coriolis_times
from blf_gym.model.bounds import log_rate

__all__ = ["bc_output", "lesobc_output", "proposed_output", "barrier_term"]

_BC, _LESOBC, _PROPOSED = 0, 1, 2


@njit(cache=True, error_model="numpy", inline="always")
def barrier_term(e1, k_a, k_b, clip):
    """kappa for one joint, with the guard: |e1| clipped to ``clip`` times the bound on its side."""
    if e1 > 0.0:
        e = min(e1, clip * k_a)
        return e / (k_a * k_a - e * e)
    e = max(e1, -clip * k_b)
    return e / (k_b * k_b - e * e)


@njit(cache=True, error_model="numpy", inline="always")
def _backstepping(kind, y, v, x3_hat, q_d, qd_d, qdd_d, ka, kad, kadd, kb, kbd, kbdd, K1, K2, clip, nominal,
                  work, u, z1, z2, kappa):
    n = y.shape[0]
    nn = n * n
    e1 = work[:n]
    a1 = work[n : 2 * n]
    a1d = work[2 * n : 3 * n]
    ca = work[3 * n : 4 * n]
    lam = 0.0
    lam_d = 0.0
    if kind == _PROPOSED:
        ra, ra_d = log_rate(ka, kad, kadd)
        rb, rb_d = log_rate(kb, kbd, kbdd)
        lam = np.sqrt(ra * ra + rb * rb)
        if lam > 0.0:
            lam_d = (ra * ra_d + rb * rb_d) / lam
    for i in range(n):
        k1 = K1[i] + lam
        e = y[i] - q_d[i]
        ed = v[i] - qd_d[i]
        e1[i] = e
        a1[i] = qd_d[i] - k1 * e
        a1d[i] = qdd_d[i] - k1 * ed - lam_d * e
    coriolis_times(nominal, v, a1, ca)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += nominal[i * n + j] * a1d[j]
        e2 = v[i] - a1[i]
        ui = -K2[i] * e2 + ca[i] + nominal[nn + i] + acc
        if kind == _PROPOSED:
            kap = barrier_term(e1[i], ka, kb, clip)
            kappa[i] = kap
            ui -= kap
        else:
            ui -= e1[i]
        if kind != _BC:
            dist = 0.0
            for j in range(n):
                dist += nominal[i * n + j] * x3_hat[j]
            ui -= dist
            z1[i] = e1[i]
            z2[i] = e2
        u[i] = ui


@njit(cache=True, error_model="numpy", inline="always")
def bc_output(y, qd_true, q_d, qd_d, qdd_d, K1, K2, barrier_clip, nominal, work, u_law):
    """Backstepping control (BC): full state (reads the true velocity), no disturbance compensation."""
    n = y.shape[0]
    _backstepping(_BC, y, qd_true, work[4 * n : 5 * n], q_d, qd_d, qdd_d, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0,
                  K1, K2, barrier_clip, nominal, work, u_law, work[5 * n : 6 * n], work[6 * n : 7 * n],
                  work[7 * n : 8 * n])


@njit(cache=True, error_model="numpy", inline="always")
def lesobc_output(y, x2_hat, x3_hat, q_d, qd_d, qdd_d, K1, K2, barrier_clip, nominal, work, u_law, z1, z2_hat):
    """Backstepping on the LESO's velocity, minus M(y) x3_hat (LESOBC)."""
    n = y.shape[0]
    _backstepping(_LESOBC, y, x2_hat, x3_hat, q_d, qd_d, qdd_d, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, K1, K2,
                  barrier_clip, nominal, work, u_law, z1, z2_hat, work[4 * n : 5 * n])


@njit(cache=True, error_model="numpy", inline="always")
def proposed_output(y, x2_hat, x3_hat, q_d, qd_d, qdd_d, k_a, k_a_dot, k_a_ddot, k_b, k_b_dot, k_b_ddot, K1, K2,
                    barrier_clip, nominal, work, u_law, z1, z2_hat, barrier):
    """The paper's LESO + barrier-Lyapunov backstepping law (eqs. 18-21) with the barrier guard."""
    _backstepping(_PROPOSED, y, x2_hat, x3_hat, q_d, qd_d, qdd_d, k_a, k_a_dot, k_a_ddot, k_b, k_b_dot, k_b_ddot,
                  K1, K2, barrier_clip, nominal, work, u_law, z1, z2_hat, barrier)
