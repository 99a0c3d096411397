"""The LESO + barrier-Lyapunov law with integral action on the tracking error, as a blf-gym plug-in.

Every function below is plain Python over blf-gym's named signals: its parameter names are the
signals it reads (y, x2_hat, q_d, k_a, the gains K1, K2, Ki, ...) and the outputs it writes (u_law,
z1, ...). blf-gym compiles them into its closed-loop kernel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from blf_gym.plugins.blocks import Controller, coriolis_times, gravity, mass_times

__all__ = ["IntegralGains", "proposed_integral"]


@dataclass(frozen=True)
class IntegralGains:
    """Gains: the paper's Table 2 backstepping gains, the barrier guard, and the integral gain."""

    K1: tuple = field(default=(20.0, 20.0, 15.0), metadata={"unit": "1/s"})
    K2: tuple = field(default=(45.0, 45.0, 15.0), metadata={"unit": "N m s/rad"})
    Ki: tuple = field(default=(40.0, 40.0, 10.0), metadata={"unit": "N m/(rad s)"})
    barrier_clip: float = field(default=0.95, metadata={"unit": "-"})

    def __post_init__(self):
        for name in ("K1", "K2", "Ki"):
            v = tuple(float(x) for x in getattr(self, name))
            if len(v) != 3 or not all(math.isfinite(x) and x >= 0 for x in v):
                raise ValueError(f"IntegralGains.{name} must be 3 finite numbers >= 0, got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)
        if not 0.0 < self.barrier_clip < 1.0:
            raise ValueError(f"IntegralGains.barrier_clip must be in (0, 1), got {self.barrier_clip!r}")


def output(y, x2_hat, x3_hat, q_d, qd_d, qdd_d, k_a, k_a_dot, k_a_ddot, k_b, k_b_dot, k_b_ddot, K1, K2, Ki,
           barrier_clip, s, nominal, work, u_law, z1, z2_hat, integral):
    """u_law = -K2 z2 + C(y, x2_hat) alpha1 + G(y) + M(y) (alpha1' - x3_hat) - kappa(z1) - Ki s."""
    n = y.shape[0]
    a1 = work[:n]
    a1d = work[n : 2 * n]
    ca = work[2 * n : 3 * n]
    g = work[3 * n : 4 * n]
    ma = work[4 * n : 5 * n]
    ra = k_a_dot / k_a
    rb = k_b_dot / k_b
    lam = math.sqrt(ra * ra + rb * rb)
    lam_d = 0.0
    if lam > 0.0:
        lam_d = (ra * (k_a_ddot * k_a - k_a_dot * k_a_dot) / (k_a * k_a)
                 + rb * (k_b_ddot * k_b - k_b_dot * k_b_dot) / (k_b * k_b)) / lam
    for i in range(n):
        e = y[i] - q_d[i]
        k1 = K1[i] + lam
        z1[i] = e
        a1[i] = qd_d[i] - k1 * e
        # alpha1' from the estimated velocity, minus the estimated disturbance (M is applied once)
        a1d[i] = qdd_d[i] - k1 * (x2_hat[i] - qd_d[i]) - lam_d * e - x3_hat[i]
    coriolis_times(nominal, x2_hat, a1, ca)
    gravity(nominal, g)
    mass_times(nominal, a1d, ma)
    for i in range(n):
        e = z1[i]
        if e > 0.0:
            c = min(e, barrier_clip * k_a)
            kappa = c / (k_a * k_a - c * c)
        else:
            c = max(e, -barrier_clip * k_b)
            kappa = c / (k_b * k_b - c * c)
        z2_hat[i] = x2_hat[i] - a1[i]
        integral[i] = s[i]
        u_law[i] = -K2[i] * z2_hat[i] + ca[i] + g[i] + ma[i] - kappa - Ki[i] * s[i]


def update(y, q_d, d_s):
    """s' = y - q_d, the measured tracking error."""
    for i in range(y.shape[0]):
        d_s[i] = y[i] - q_d[i]


def proposed_integral(**kwargs) -> Controller:
    """The registered factory: keyword arguments override the gains (K1, K2, Ki, barrier_clip)."""
    return Controller("proposed_integral", output, IntegralGains(**kwargs),
                      outputs={"u_law": "n", "z1": "n", "z2_hat": "n", "integral": "n"},
                      states={"s": "n"}, update=update)
