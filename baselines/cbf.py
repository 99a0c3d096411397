"""The CBF-QP filter: a second-order control barrier function on the funnel, solved in closed form
(docs/model.md section 14).

Per joint the error e = y - q_d must stay in (-k_b, k_a). Its two barriers, h_a = k_a - e and
h_b = k_b + e, have relative degree two in the torque, so the filter asks of each the second-order
(exponential) CBF condition

    h'' + (g1 + g2) h' + g1 g2 h >= 0,

which keeps h >= 0 when it holds from a start with h >= 0 and h' + g1 h >= 0 (Nguyen and Sreenath,
ACC 2016; Xiao and Belta, CDC 2019). With e' = x2_hat - qd_d from the observer, each condition is a
bound on the joint's acceleration:

    qdd_i <= qdd_d + k_a'' + c1 (k_a' - e') + c0 (k_a - e)      (upper, from h_a)
    qdd_i >= qdd_d - k_b'' - c1 (k_b' + e') - c0 (k_b + e)      (lower, from h_b)

with c1 = g1 + g2 and c0 = g1 g2. The acceleration a command produces is predicted from the nominal
model and the observer, a = M^-1 (u - C(y, x2_hat) x2_hat - G(y)) + x3_hat, so a residual r moves it
by M^-1 r. The filter solves

    min over r_f of |M^-1 (r_f - r)|^2   subject to   lb <= a_law + M^-1 r_f <= ub,

the least change of the *acceleration* the command asks for. In that metric the constraints
decouple by joint, and the QP's solution is a clip of each joint's acceleration to [lb_i, ub_i]
followed by r_f = M (a_f - a_law) (tests/test_cbf.py checks it against OSQP). The residual is first
clipped to the actuator box, as the barrier filter does. It filters the whole command: with a zero
residual it still acts if the law's own command breaks a condition (its gains are chosen so that,
on the selection episodes, it never does; at smaller rates it cuts the law's own reaction to the
force's onset and breaks the bounds the law alone keeps).

Counted cases:

* ``infeasible`` (1 in that stage): a joint whose lower bound exceeds its upper one (then its
  acceleration is set to their midpoint), or a torque limit that stops r_f from meeting a condition
  (the limit wins). Either makes ``assumptions`` 0 too, so the kernel counts it.
* ``breach``: the condition fails by more than the round-off tolerance in a stage that was feasible,
  which the construction rules out.
* ``handed_back`` (1 in that stage): the hand-back monitor (``handback``, off by default) saw the
  observer's innovation |y - x1_hat| above it on a joint, so r_f = 0 and the law acts alone.
* ``assumptions`` is 0 when an assumption of the guarantee fails: infeasibility, the observer's
  velocity error above ``e2_max``, or the measurement noise above ``noise_fraction`` of the true
  margin (the monitors read the true state; r_f reads only measured signals).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from numba import njit

from blf_gym.plugins.blocks import ResidualFilter, mass_solve, mass_times, nominal_acceleration

from .filters import innovation_exceeds
from .params import params_from

__all__ = ["CBFFilterParams", "cbf_filter", "cbf_apply", "CBF_OUTPUTS"]

CBF_OUTPUTS = {"r_f": "n", "active": 1, "infeasible": 1, "breach": 1, "assumptions": 1, "handed_back": 1}


@dataclass(frozen=True)
class CBFFilterParams:
    """The CBF's class-K rates and the stated sizes of its assumptions."""

    gamma1: float = field(default=400.0, metadata={"unit": "1/s"})
    """First rate of the second-order condition (> 0). 400 is the smallest rate of the grid 50-1,200
    with which the filter leaves the law's own episodes untouched (zero residual) on the presets and
    training-suite seeds 0-7 (``python -m baselines.gains proposed --filter cbf``,
    docs/gains/cbf/gains.md); a smaller rate acts earlier, and at 50-200 it breaks the law."""
    gamma2: float = field(default=400.0, metadata={"unit": "1/s"})
    """Second rate (> 0); c1 = gamma1 + gamma2 and c0 = gamma1 gamma2."""
    e2_max: float = field(default=2.0, metadata={"unit": "rad/s"})
    """Assumption monitor: the observer's velocity error |x2_hat - qd| stays below this."""
    noise_fraction: float = field(default=0.1, metadata={"unit": "-"})
    """Assumption monitor: the measurement noise |y - q| stays below this fraction of the true margin."""
    handback: float = field(default=0.0, metadata={"unit": "rad"})
    """Hand-back monitor (>= 0; 0 turns it off), as the barrier filter's
    (:attr:`baselines.filters.BarrierFilterParams.handback`): while the observer's innovation exceeds
    it on a joint, r_f = 0 and the law's command passes unfiltered."""

    def __post_init__(self) -> None:
        o = "CBFFilterParams"
        for name in ("gamma1", "gamma2", "e2_max", "noise_fraction", "handback"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{o}.{name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("gamma1", "gamma2"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{o}.{name} must be > 0 1/s, got {getattr(self, name)!r}")
        if self.e2_max <= 0:
            raise ValueError(f"{o}.e2_max must be > 0 rad/s, got {self.e2_max!r}")
        if not 0.0 < self.noise_fraction < 1.0:
            raise ValueError(f"{o}.noise_fraction must be in (0, 1), got {self.noise_fraction!r}")
        if self.handback < 0:
            raise ValueError(f"{o}.handback must be >= 0 rad (0: off), got {self.handback!r}")


# long: the filter's apply is inlined into the kernel's step as one block (its checks, the QP's
# closed form and its fall-backs share the per-joint work array); a split adds calls per joint
@njit(cache=True, error_model="numpy", inline="always")
def cbf_apply(residual, u_law, y, x2_hat, x3_hat, q_d, qd_d, qdd_d, k_a, k_a_dot, k_a_ddot, k_b, k_b_dot, k_b_ddot,
              u_max, gamma1, gamma2, e2_max, noise_fraction, handback, q_true, qd_true, x1_hat, nominal, work,
              r_f, active, infeasible, breach, assumptions, handed_back):
    """The filter's ``apply`` over named signals (see the module docstring)."""
    n = residual.shape[0]
    c1 = gamma1 + gamma2
    c0 = gamma1 * gamma2
    t1 = work[:n]
    t2 = work[n : 2 * n]
    a_law = work[2 * n : 3 * n]
    da = work[3 * n : 4 * n]
    lo = work[4 * n : 5 * n]
    hi = work[5 * n : 6 * n]
    rc = work[6 * n : 7 * n]
    # the acceleration the law's command asks for
    nominal_acceleration(nominal, x2_hat, u_law, t1, t2, a_law)
    for i in range(n):
        a_law[i] += x3_hat[i]
    # the residual within the actuator box (untouched when already inside)
    for i in range(n):
        v = u_law[i] + residual[i]
        rc[i] = u_max - u_law[i] if v > u_max else (-u_max - u_law[i] if v < -u_max else residual[i])
    mass_solve(nominal, rc, da)
    act = 0
    infeas = False
    for i in range(n):
        e = y[i] - q_d[i]
        ed = x2_hat[i] - qd_d[i]
        hi[i] = qdd_d[i] + k_a_ddot + c1 * (k_a_dot - ed) + c0 * (k_a - e)
        lo[i] = qdd_d[i] - k_b_ddot - c1 * (k_b_dot + ed) - c0 * (k_b + e)
        a = a_law[i] + da[i]
        if lo[i] > hi[i]:
            infeas = True
            act += 1
            a = 0.5 * (lo[i] + hi[i])
        elif a > hi[i]:
            act += 1
            a = hi[i]
        elif a < lo[i]:
            act += 1
            a = lo[i]
        t2[i] = a - a_law[i]
    lost = innovation_exceeds(y, x1_hat, handback)
    handed_back[0] = 1.0 if lost else 0.0
    if lost:  # the hand-back: the law's command passes unfiltered
        act = 0
        infeas = False
        for i in range(n):
            rc[i] = 0.0
    if act == 0:
        for i in range(n):
            r_f[i] = rc[i]  # inactive: the identity, bit for bit
    else:
        mass_times(nominal, t2, r_f)
        for i in range(n):  # the actuator box wins over the condition
            v = u_law[i] + r_f[i]
            if v > u_max:
                r_f[i] = u_max - u_law[i]
            elif v < -u_max:
                r_f[i] = -u_max - u_law[i]
    # what r_f achieves, checked against the condition
    mass_solve(nominal, r_f, da)
    bad = False
    for i in range(n):
        a = a_law[i] + da[i]
        tol = 1e-9 * max(1.0, abs(lo[i]), abs(hi[i]))
        if not lost and lo[i] <= hi[i] and (a > hi[i] + tol or a < lo[i] - tol):
            bad = True  # (handed back, the condition is not asked of the law's command)
    if bad and act > 0:
        infeas = True  # the torque limit stopped the filter: counted as infeasible
        bad = False
    active[0] = act
    infeasible[0] = 1.0 if infeas else 0.0
    breach[0] = 1.0 if bad else 0.0
    ok = not infeas
    for i in range(n):
        e = q_true[i] - q_d[i]
        bound = k_a if e >= 0.0 else k_b
        if abs(x2_hat[i] - qd_true[i]) > e2_max:
            ok = False
        if abs(y[i] - q_true[i]) > noise_fraction * (bound - abs(e)):
            ok = False
    assumptions[0] = 1.0 if ok else 0.0


def cbf_filter(**kwargs: Any) -> ResidualFilter:
    """The CBF-QP filter; keyword arguments override :class:`CBFFilterParams`."""
    params = params_from(CBFFilterParams, kwargs, "CBF filter parameter")
    return ResidualFilter("cbf", cbf_apply, params, outputs=dict(CBF_OUTPUTS))
