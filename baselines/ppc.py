"""Prescribed-performance control (PPC) with the LESO: the classical alternative to a barrier
Lyapunov function for time-varying output constraints (Bechlioulis and Rovithakis, IEEE TAC 53(9),
2008), written as backstepping on the transformed error (docs/model.md section 12).

Per joint, the error e = y - q_d must stay in (-k_b(t), k_a(t)). PPC maps that interval onto the
whole real line,

    eps = ln((e + k_b) / (k_a - e)) - ln(k_b / k_a)          (eps = 0 at e = 0)

so that any bounded eps means the error is inside its bounds. With r = 1/(e + k_b) + 1/(k_a - e)
> 0, d eps/dt = r de/dt + s, where s collects the bounds' rates. The virtual velocity
alpha1 = qd_d + (-K1 eps - s) / r gives d eps/dt = -K1 eps + r z2 (z2 = v - alpha1), and the torque

    u = M(y) (alpha1' - x3_hat) + C(y, x2_hat) alpha1 + G(y) - K2 z2_hat - r eps

makes V = 1/2 eps^T eps + 1/2 z2^T M z2 decrease as -K1 eps^2 - z2^T K2 z2, up to the observer's
errors: the law is the paper's, with its barrier term kappa replaced by r eps. alpha1' is computed
analytically from the velocity estimate x2_hat, as the paper's laws do.

Guard (as the proposed law's ``barrier_clip``): the transformation is singular at the bounds, so it
is evaluated with e clipped to ``barrier_clip`` times the bound on its side; the law is then finite
for every finite state.

It publishes z1 = e, z2_hat = x2_hat - alpha1 and the transformed error ``epsilon``.
"""

from __future__ import annotations

import math
from typing import Any

from numba import njit

from blf_gym.plugins.blocks import Controller, coriolis_times
from blf_gym.model.bounds import log_rate

from .controllers import controller_gains, member_defaults

__all__ = ["ppc", "ppc_output", "PPC_GAINS", "PPC_MEMBER_GAINS"]

PPC_GAINS: dict[str, Any] = {"K1": (1280.0, 1280.0, 960.0), "K2": (11.25, 11.25, 3.75)}  # paper: its 3-link arm
"""The PPC's gains where they differ from :class:`baselines.controllers.ControllerGains`' defaults
(the paper's K1, K2 and the guard): the paper's K1 times 64 and K2 times 1/4, chosen by
``python -m baselines.gains`` on the presets and training-suite seeds 0-7 only, under a torque
budget of 1.25 times the law's RMS torque (docs/gains/ppc/gains.md, docs/model.md section 12). Chosen
on the paper's 3-link arm; on an arm of another number of links (``nominal``) they are carried to it
by docs/family.md's rule unless K1 and K2 are given."""


@njit(cache=True, error_model="numpy", inline="always")
def ppc_output(y, x2_hat, x3_hat, q_d, qd_d, qdd_d, k_a, k_a_dot, k_a_ddot, k_b, k_b_dot, k_b_ddot, K1, K2,
               barrier_clip, nominal, work, u_law, z1, z2_hat, epsilon):
    """The prescribed-performance law with the LESO (see the module docstring)."""
    n = y.shape[0]
    nn = n * n
    a1 = work[:n]
    a1d = work[n : 2 * n]
    ca = work[2 * n : 3 * n]
    reps = work[3 * n : 4 * n]
    # the rates of ln k_a and ln k_b and their derivatives (the e-free part of s)
    la, la_d = log_rate(k_a, k_a_dot, k_a_ddot)
    lb, lb_d = log_rate(k_b, k_b_dot, k_b_ddot)
    for i in range(n):
        e_raw = y[i] - q_d[i]
        e = min(max(e_raw, -barrier_clip * k_b), barrier_clip * k_a)
        ed = x2_hat[i] - qd_d[i]
        pa = 1.0 / (k_a - e)
        pb = 1.0 / (e + k_b)
        eps = math.log((e + k_b) * k_a) - math.log((k_a - e) * k_b)
        r = pa + pb
        s = k_b_dot * pb - k_a_dot * pa - lb + la
        eps_d = r * ed + s
        r_d = -(k_a_dot - ed) * pa * pa - (ed + k_b_dot) * pb * pb
        s_d = (k_b_ddot * pb - k_b_dot * (ed + k_b_dot) * pb * pb
               - k_a_ddot * pa + k_a_dot * (k_a_dot - ed) * pa * pa - lb_d + la_d)
        g = -K1[i] * eps - s
        g_d = -K1[i] * eps_d - s_d
        a1[i] = qd_d[i] + g / r
        a1d[i] = qdd_d[i] + (g_d * r - g * r_d) / (r * r)
        reps[i] = r * eps
        z1[i] = e_raw
        epsilon[i] = eps
    coriolis_times(nominal, x2_hat, a1, ca)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += nominal[i * n + j] * (a1d[j] - x3_hat[j])
        e2 = x2_hat[i] - a1[i]
        z2_hat[i] = e2
        u_law[i] = -K2[i] * e2 + ca[i] + nominal[nn + i] + acc - reps[i]


PPC_MEMBER_GAINS: dict[int, dict[str, float]] = {  # chosen by the searches named below
    2: {"K1": 640.0, "K2": 12.390671665762405},
    4: {"K1": 1280.0, "K2": 26.942644011767488},
    5: {"K1": 1280.0, "K2": 22.128259433048658},
    6: {"K1": 2560.0, "K2": 20.503601833576987},
    7: {"K1": 1280.0, "K2": 19.092879177475517}}
"""PPC's gains on the task family's other members (docs/family.md, "Gains"), chosen per member by the
same search as on the paper's arm (``python -m baselines.gains ppc --n-links N``, the same 40-point
grid carried: K1 over the same eight values, K2 the law's carried first gain times 1/8 to 2, on the
member's presets and training-suite seeds 0-7 only, under the same torque budget;
docs/gains/family/ppc_n<N>). Each is the first entry of a vector of the carried shape: the vectors
the rule carries to the member, scaled to it."""


def ppc(**kwargs: Any) -> Controller:
    """Prescribed-performance control with the LESO's velocity and disturbance estimates; keyword
    arguments override :class:`baselines.controllers.ControllerGains` (K1 is the transformed
    error's rate, 1/s). On a member of the task family its gains are the member's
    (:data:`PPC_MEMBER_GAINS`)."""
    defaults = member_defaults(kwargs.get("nominal"), PPC_MEMBER_GAINS, PPC_GAINS)
    return Controller("ppc", ppc_output, controller_gains(kwargs, defaults),
                      outputs={"u_law": "n", "z1": "n", "z2_hat": "n", "epsilon": "n"})
