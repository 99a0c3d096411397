"""A fourth-order extended state observer as a blf-gym plug-in (4n states)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from blf_gym.plugins.blocks import Observer, nominal_acceleration

__all__ = ["ESO4Gains", "eso4"]


@dataclass(frozen=True)
class ESO4Gains:
    """Bandwidth parametrisation: the four poles of every joint at -k0."""

    k0: float = field(default=150.0, metadata={"unit": "1/s"})

    def __post_init__(self):
        if not (isinstance(self.k0, (int, float)) and math.isfinite(self.k0) and self.k0 > 0):
            raise ValueError(f"ESO4Gains.k0 must be a finite number > 0, got {self.k0!r}")


def rhs(y, u, x1_hat, x2_hat, x3_hat, x4_hat, k0, nominal, work, d_x1_hat, d_x2_hat, d_x3_hat, d_x4_hat):
    """The observer's right-hand side over named signals."""
    n = y.shape[0]
    c = work[:n]
    g = work[n : 2 * n]
    acc = work[3 * n : 4 * n]
    nominal_acceleration(nominal, x2_hat, u, c, g, acc)  # M^-1 (u - C(y, x2_hat) x2_hat - G(y))
    for i in range(n):
        err = y[i] - x1_hat[i]
        d_x1_hat[i] = x2_hat[i] + 4.0 * k0 * err
        d_x2_hat[i] = acc[i] + x3_hat[i] + 6.0 * k0 * k0 * err
        d_x3_hat[i] = x4_hat[i] + 4.0 * k0 * k0 * k0 * err
        d_x4_hat[i] = k0 * k0 * k0 * k0 * err


def eso4(**kwargs) -> Observer:
    """The registered factory: ``eso4(k0=...)``."""
    return Observer("eso4", rhs, {"x1_hat": "n", "x2_hat": "n", "x3_hat": "n", "x4_hat": "n"}, ESO4Gains(**kwargs))
