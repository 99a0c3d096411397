"""Funnel control with the LESO's velocity: the model-free high-gain alternative for time-varying
output constraints (Ilchmann, Ryan and Sangwin, ESAIM COCV 7, 2002), in the form for relative
degree two of Berger, Le and Reis (Automatica 87, 2018) (docs/model.md section 13).

The bounds (-k_b(t), k_a(t)) are the same on every joint. The funnel is the largest one centred on
the reference inside them, of half-width psi = min(k_a, k_b) and phi = 1/psi, so that the law drives
the error to zero, as the benchmark's RMSE asks (a funnel centred between the two bounds would track
their midpoint, (k_a - k_b)/2, about -0.6 degrees once they settle). With a = 1 / (1 - s),

    e0 = phi e,        e1 = phi (de/dt) / k_e + a(|e0|^2) e0,
    u  = M(y) (f (qdd_d - x3_hat) - k_u a(|e1|^2) e1) + f (C(y, x2_hat) x2_hat + G(y))

where |.| is the Euclidean norm over the joints and de/dt = x2_hat - qd_d is read from the
observer's velocity. |e0| < 1 keeps every joint inside its bounds. The rate k_e (1/s) sets the time
scale of the inner level: with k_e = 1 it is the published e1 = phi de/dt + a(|e0|^2) e0, whose
error decays as exp(-t) at best, slow beside the paper's K1 = 20 1/s.

* With ``feedforward`` f = 0 it is the published law, model-free but for its input gain M(y): the
  arm's input gain M^-1 is then close to the identity, which is positive definite as the theory
  asks, and one k_u (rad/s^2) suits joints whose inertias differ by a factor of a hundred (a scalar
  torque gain that keeps the wrist integrable at 0.1 ms is too weak for the shoulder). Its gain a
  grows without bound as the error nears the funnel's edge; that is what makes it robust, and
  stiff: at 0.1 ms the gain that keeps the integration stable cannot follow the 0.5 Hz reference's
  258 rad/s^2 at its folds (docs/model.md section 13).
* With f = 1 (the default) the LESO's estimates and the nominal model cancel what they can (the
  reference's acceleration, Coriolis, gravity and the estimated lumped disturbance), as the paper's
  laws do, and the funnel term handles the rest. The added terms are bounded functions of the
  state and time, so the funnel's guarantee holds under the same assumptions.

Guard (as the proposed law's ``barrier_clip``): a(s) is evaluated with s clipped to ``funnel_clip``^2,
so the gain stays finite (at most 1 / (1 - funnel_clip^2) times k_u) for every finite state.

It publishes e0 and e1 (each per joint, dimensionless).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from numba import njit

from blf_gym.plugins.blocks import Controller, coriolis_times
from blf_gym.model.params import ArmParams

from .params import params_from

__all__ = ["FunnelGains", "funnel", "funnel_output"]


@dataclass(frozen=True)
class FunnelGains:
    """The funnel controller's gains and guard. k_e and k_u were chosen by ``python -m
    baselines.gains`` on the presets and training-suite seeds 0-7 only, under a torque budget of 1.25
    times the proposed law's RMS torque (docs/gains/funnel/gains.md, docs/model.md section 13)."""

    k_e: float = field(default=320.0, metadata={"unit": "1/s"})
    """Rate of the inner level: e1 = phi (de/dt) / k_e + a(|e0|^2) e0 (> 0)."""
    k_u: float = field(default=6400.0, metadata={"unit": "rad/s^2"})
    """Acceleration scale of the law: u = -k_u M(y) a(|e1|^2) e1 (> 0)."""
    funnel_clip: float = field(default=0.99, metadata={"unit": "-"})
    """The gains a(|e0|^2) and a(|e1|^2) are evaluated with each norm clipped to this (in (0, 1))."""
    feedforward: float = field(default=1.0, metadata={"unit": "-"})
    """Weight f of the model and disturbance compensation (0: the published model-free law, 1: full)."""
    nominal: ArmParams = field(default_factory=ArmParams)
    """The arm model of the input gain M(y) and the compensation (paper Table 1)."""

    def __post_init__(self) -> None:
        for name in ("k_e", "k_u", "funnel_clip", "feedforward"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"FunnelGains.{name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.k_e <= 0:
            raise ValueError(f"FunnelGains.k_e must be > 0 1/s, got {self.k_e!r}")
        if self.k_u <= 0:
            raise ValueError(f"FunnelGains.k_u must be > 0 rad/s^2, got {self.k_u!r}")
        if not 0.0 < self.funnel_clip < 1.0:
            raise ValueError(f"FunnelGains.funnel_clip must be in (0, 1), got {self.funnel_clip!r}")
        if not 0.0 <= self.feedforward <= 1.0:
            raise ValueError(f"FunnelGains.feedforward must be in [0, 1], got {self.feedforward!r}")


@njit(cache=True, error_model="numpy", inline="always")
def funnel_output(y, x2_hat, x3_hat, q_d, qd_d, qdd_d, k_a, k_b, k_e, k_u, funnel_clip, feedforward, nominal,
                  work, u_law, e0, e1):
    """The funnel law for relative degree two (see the module docstring)."""
    n = y.shape[0]
    phi = 1.0 / min(k_a, k_b)
    cap = funnel_clip * funnel_clip
    s0 = 0.0
    for i in range(n):
        e0[i] = phi * (y[i] - q_d[i])
        s0 += e0[i] * e0[i]
    a0 = 1.0 / (1.0 - min(s0, cap))
    s1 = 0.0
    for i in range(n):
        e1[i] = phi * (x2_hat[i] - qd_d[i]) / k_e + a0 * e0[i]
        s1 += e1[i] * e1[i]
    a1 = 1.0 / (1.0 - min(s1, cap))
    f = feedforward
    v = work[:n]
    cv = work[n : 2 * n]
    for i in range(n):
        v[i] = f * (qdd_d[i] - x3_hat[i]) - k_u * a1 * e1[i]
    coriolis_times(nominal, x2_hat, x2_hat, cv)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += nominal[i * n + j] * v[j]
        u_law[i] = acc + f * (cv[i] + nominal[n * n + i])


def funnel(**kwargs: Any) -> Controller:
    """Funnel control on the LESO's velocity estimate; keyword arguments override :class:`FunnelGains`."""
    params = params_from(FunnelGains, kwargs, "funnel gain")
    return Controller("funnel", funnel_output, params, outputs={"u_law": "n", "e0": "n", "e1": "n"})
