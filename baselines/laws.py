"""The three control laws of the paper's Section 4.2 as pure compiled functions.

Each has the blf_gym law signature
``law(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work)``
(see :mod:`blf_gym.controller`) with ``gains = [K1 (n), K2 (n), barrier_clip]``. Symbols map to
the paper as: e1 = q - q_d (tracking error), alpha1 (virtual velocity), e2 = v - alpha1, K1, K2
(Table 2), k_a/k_b (the error bounds), x3_hat (estimated lumped disturbance).

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
"""

from __future__ import annotations

import numpy as np
from numba import njit

from blf_gym.dynamics import coriolis_times_into

__all__ = ["bc_law", "lesobc_law", "proposed_law", "barrier_term", "GAIN_LAYOUT"]

GAIN_LAYOUT = "[K1_1..K1_n, K2_1..K2_n, barrier_clip]"

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
def _backstepping(kind, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work):
    n = y.shape[0]
    nn = n * n
    M = model[:nn]
    g = model[nn : nn + n]
    trig = model[nn + n : nn + 3 * n]
    e1 = work[:n]
    a1 = work[n : 2 * n]
    a1d = work[2 * n : 3 * n]
    ca = work[3 * n : 4 * n]
    dyn = work[4 * n : 7 * n]
    v = qd_true if kind == _BC else xhat[n : 2 * n]

    lam = 0.0
    lam_d = 0.0
    if kind == _PROPOSED:
        ka, kad, kadd, kb, kbd, kbdd = bnd[0], bnd[1], bnd[2], bnd[3], bnd[4], bnd[5]
        ra = kad / ka
        rb = kbd / kb
        lam = np.sqrt(ra * ra + rb * rb)
        if lam > 0.0:
            ra_d = (kadd * ka - kad * kad) / (ka * ka)
            rb_d = (kbdd * kb - kbd * kbd) / (kb * kb)
            lam_d = (ra * ra_d + rb * rb_d) / lam
    for i in range(n):
        k1 = gains[i] + lam
        e = y[i] - ref[i]
        ed = v[i] - ref[n + i]
        e1[i] = e
        a1[i] = ref[n + i] - k1 * e
        a1d[i] = ref[2 * n + i] - k1 * ed - lam_d * e
    coriolis_times_into(trig, v, a1, nominal, ca, dyn)
    clip = gains[2 * n]
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += M[i * n + j] * a1d[j]
        e2 = v[i] - a1[i]
        ui = -gains[n + i] * e2 + ca[i] + g[i] + acc
        if kind == _PROPOSED:
            ui -= barrier_term(e1[i], bnd[0], bnd[3], clip)
        else:
            ui -= e1[i]
        if kind != _BC:
            dist = 0.0
            for j in range(n):
                dist += M[i * n + j] * xhat[2 * n + j]
            ui -= dist
        u[i] = ui


@njit(cache=True, error_model="numpy", inline="always")
def bc_law(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work):
    """Backstepping control (BC): full state, no observer, no disturbance compensation."""
    _backstepping(_BC, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work)


@njit(cache=True, error_model="numpy", inline="always")
def lesobc_law(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work):
    """Backstepping on the LESO's velocity, minus M(y) x3_hat (LESOBC)."""
    _backstepping(_LESOBC, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work)


@njit(cache=True, error_model="numpy", inline="always")
def proposed_law(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work):
    """The paper's LESO + barrier-Lyapunov backstepping law (eqs. 18-21) with the barrier guard."""
    _backstepping(_PROPOSED, y, qd_true, xhat, ref, bnd, nominal, model, gains, u, work)
