"""The barrier filter: a learned residual that cannot undo the proposed law's barrier (docs/model.md
section 11).

The proposed law's proof rests on V2 = V1 + 1/2 z2^T M(x1) z2 (the paper's eq. 32), with V1 the
barrier-Lyapunov function of the tracking error z1. A residual torque r added to the law's enters
dV2/dt as z2^T r. At every integration stage the filter keeps the estimated term z2_hat^T r_f below
a budget beta(m) that shrinks to 0 as the smallest normalized margin m to the bounds falls to m0:

* m_i = (k_a - z1_i) / k_a when z1_i >= 0, else (k_b + z1_i) / k_b (1 on the reference, 0 on the
  bound), from the measured error; m = min_i m_i;
* beta(m) = gamma(m) * max(beta_max, |r|^2 / gain_max), gamma(m) = clip((m - m0) / (m1 - m0), 0, 1): the
  floor |r|^2 / gain_max bounds the filter's own feedback gain (see gain_max);
* r is first clipped to the actuator box (u_law + r within +-u_max; untouched when already inside),
  then scaled: r_f = theta r with theta = min(gamma, beta / (z2_hat^T r)) when z2_hat^T r > 0, else
  gamma: the size of r_f shrinks to 0 at m0 too, so the term the estimate cannot see,
  (x2 - x2_hat)^T r_f, vanishes there as well;
* r_f = 0 while u_law itself saturates, and while the hand-back monitor sees the observer's
  innovation |y - x1_hat| above ``handback`` on a joint (off by default): the law then acts alone.

It publishes ``theta`` and ``beta`` and two monitors the kernel counts per integration step:
``breach`` (the condition z2_hat^T r_f <= beta failed by more than 1e-12, which the construction
rules out) and ``assumptions`` (0 when an assumption of the guarantee fails: the true error beyond
the barrier guard, u_law saturated, the observer's velocity error above ``e2_max``, or the
measurement noise above ``noise_fraction`` of the true margin). The monitors read the true state;
r_f reads only the law's own signals at the measured angles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from numba import njit

from blf_gym.plugins.blocks import ResidualFilter

from .params import params_from

__all__ = ["BarrierFilterParams", "barrier_filter", "barrier_apply", "innovation_exceeds", "FILTER_OUTPUTS"]

FILTER_OUTPUTS = {"r_f": "n", "theta": 1, "beta": 1, "breach": 1, "assumptions": 1, "handed_back": 1}


@dataclass(frozen=True)
class BarrierFilterParams:
    """The budget beta(m) and the stated sizes of the guarantee's assumptions."""

    beta_max: float = field(default=5.0, metadata={"unit": "N m rad/s"})
    """Budget far from the bounds (m >= m1) for z2_hat^T r_f (>= 0)."""
    m0: float = field(default=0.25, metadata={"unit": "-"})
    """Normalized margin at and below which the budget is 0: the residual may then only lower V2."""
    m1: float = field(default=0.5, metadata={"unit": "-"})
    """Normalized margin at and above which the budget is beta_max (m0 < m1 <= 1)."""
    gain_max: float = field(default=5.0, metadata={"unit": "N m s/rad"})
    """The budget is at least |r|^2 / gain_max (times the ramp), which bounds the filter's own feedback
    gain |d r_f / d z2_hat| by gain_max: a third of the law's smallest K2, so the filtered loop stays
    integrable at h = 0.1 ms (an exact projection onto z2_hat^T r <= beta_max has a gain of
    |r|^2 / beta_max, which destabilises ODE3 for an 8 N m residual)."""
    e2_max: float = field(default=2.0, metadata={"unit": "rad/s"})
    """Assumption monitor: the observer's velocity error |x2_hat - qd| stays below this."""
    noise_fraction: float = field(default=0.1, metadata={"unit": "-"})
    """Assumption monitor: the measurement noise |y - q| stays below this fraction of the true margin."""
    handback: float = field(default=0.0, metadata={"unit": "rad"})
    """Hand-back monitor (>= 0; 0 turns it off): while the observer's innovation |y_i - x1_hat_i|
    exceeds this on any joint, r_f = 0 and the law acts alone (output ``handed_back`` 1). It is the
    assumption monitor r_f can read: the LESO's error dynamics give x2 - x2_hat = 3 k0 (y - x1_hat)
    once its fast transient has passed, so an innovation above e2_max / (3 k0) (3.3e-3 rad at the
    defaults) means the velocity-error assumption has failed (:func:`innovation_exceeds`)."""

    def __post_init__(self) -> None:
        o = "BarrierFilterParams"
        for name in ("beta_max", "m0", "m1", "gain_max", "e2_max", "noise_fraction", "handback"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{o}.{name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.beta_max < 0:
            raise ValueError(f"{o}.beta_max must be >= 0 N m rad/s, got {self.beta_max!r}")
        if not (0.0 <= self.m0 < self.m1 <= 1.0):
            raise ValueError(f"{o}: margins must satisfy 0 <= m0 < m1 <= 1, got m0 = {self.m0!r}, m1 = {self.m1!r}")
        if self.gain_max <= 0:
            raise ValueError(f"{o}.gain_max must be > 0 N m s/rad, got {self.gain_max!r}")
        if self.handback < 0:
            raise ValueError(f"{o}.handback must be >= 0 rad (0: off), got {self.handback!r}")
        if self.e2_max <= 0 or not (0.0 < self.noise_fraction < 1.0):
            raise ValueError(f"{o}: e2_max must be > 0 rad/s and noise_fraction in (0, 1), got {self.e2_max!r}, "
                             f"{self.noise_fraction!r}")


@njit(cache=True, error_model="numpy", inline="always")
def barrier_apply(residual, u_law, z1, z2_hat, k_a, k_b, u_max, beta_max, m0, m1, gain_max, e2_max, noise_fraction,
                  handback, barrier_clip, y, q_true, qd_true, q_d, x1_hat, x2_hat, r_f, theta, beta, breach,
                  assumptions, handed_back):
    """The filter's ``apply`` over named signals (see the module docstring)."""
    n = residual.shape[0]
    lost = innovation_exceeds(y, x1_hat, handback)
    saturated = False
    m = 1.0
    for i in range(n):
        if abs(u_law[i]) >= u_max:
            saturated = True
        e = z1[i]
        mi = (k_a - e) / k_a if e >= 0.0 else (k_b + e) / k_b
        if mi < m:
            m = mi
    ramp = min(max((m - m0) / (m1 - m0), 0.0), 1.0)
    s = 0.0
    r2 = 0.0
    for i in range(n):
        v = u_law[i] + residual[i]
        if v > u_max:
            rc = u_max - u_law[i]
        elif v < -u_max:
            rc = -u_max - u_law[i]
        else:
            rc = residual[i]  # inside the box: untouched, so the inactive filter is the identity
        r_f[i] = rc
        s += z2_hat[i] * rc
        r2 += rc * rc
    b = ramp * max(beta_max, r2 / gain_max)
    # the taper: the size of r_f also goes to 0 with the margin, so that the term the estimate cannot
    # see, (z2 - z2_hat)^T r_f = (x2 - x2_hat)^T r_f, vanishes at m0 too
    big = b / ramp if ramp > 0.0 else 0.0  # max(beta_max, |r|^2 / gain_max)
    th = ramp
    if saturated or lost:
        th = 0.0
    elif ramp > 0.0 and s > big:
        th = b / s  # = ramp * big / s < ramp: the condition is met with equality
    if th < 1.0:
        for i in range(n):
            r_f[i] = th * r_f[i]
    theta[0] = th
    beta[0] = b
    c = 0.0
    for i in range(n):
        c += z2_hat[i] * r_f[i]
    breach[0] = 1.0 if c > b + 1e-12 * max(1.0, abs(b)) else 0.0
    ok = not saturated
    for i in range(n):
        e = q_true[i] - q_d[i]
        bound = k_a if e >= 0.0 else k_b
        if abs(e) > barrier_clip * bound:
            ok = False
        if abs(x2_hat[i] - qd_true[i]) > e2_max:
            ok = False
        if abs(y[i] - q_true[i]) > noise_fraction * (bound - abs(e)):
            ok = False
    assumptions[0] = 1.0 if ok else 0.0
    handed_back[0] = 1.0 if lost else 0.0


@njit(cache=True)
def innovation_exceeds(y, x1_hat, limit):
    """Whether the observer's innovation |y_i - x1_hat_i| exceeds ``limit`` on any joint (never when
    ``limit`` is 0): both filters' hand-back monitor."""
    if limit <= 0.0:
        return False
    for i in range(y.shape[0]):
        if abs(y[i] - x1_hat[i]) > limit:
            return True
    return False


def barrier_filter(**kwargs: Any) -> ResidualFilter:
    """The barrier filter of the proposed law; keyword arguments override :class:`BarrierFilterParams`."""
    params = params_from(BarrierFilterParams, kwargs, "barrier filter parameter")
    return ResidualFilter("barrier", barrier_apply, params, outputs=dict(FILTER_OUTPUTS))
