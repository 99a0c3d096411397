"""The classical robot-control baselines: PD with gravity compensation and computed-torque control,
each as a full-state law and on the LESO's estimates (docs/model.md section 16).

With e = y - q_d, and ė = v - qd_d for the velocity v the law uses (the true velocity in the
full-state laws, the LESO's x2_hat otherwise):

* **PD + gravity compensation** (``pd_gravity``, ``pd_gravity_leso``):
  u = G(y) - Kp e - Kd ė (Kp in N m/rad, Kd in N m s/rad). On the LESO it also subtracts
  M(y) x3_hat, the estimated lumped disturbance as a torque, as LESOBC does.
* **Computed torque** (``computed_torque``, ``computed_torque_leso``): feedback linearisation on
  the nominal model, u = M(y) a + C(y, v) v + G(y) with the commanded acceleration
  a = qdd_d - Kd ė - Kp e (Kp in 1/s^2, Kd in 1/s), so that on the nominal arm the error obeys
  ë + Kd ė + Kp e = 0; on the LESO, a also subtracts x3_hat (rad/s^2).

None of the four knows the time-varying bounds: they are the baselines every robot-control
comparison shows first, with no certificate. Their gains were chosen by the same grid search,
selection episodes and torque budget as PPC's and the tuned law's (``python -m baselines.gains``,
docs/gains/); the defaults below are those choices, and where the search found no point within the
budget (computed torque) the gains say so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from numba import njit

from blf_gym.plugins.blocks import Controller, coriolis_times
from blf_gym.model.params import ArmParams

from .params import params_from, positive_vector

__all__ = ["PDGains", "CTCGains", "PD_GRAVITY", "pd_gravity", "pd_gravity_leso", "computed_torque", "computed_torque_leso",
           "pd_gravity_output", "pd_gravity_leso_output", "computed_torque_output", "computed_torque_leso_output"]


@dataclass(frozen=True)
class PDGains:
    """PD with gravity compensation: per-joint stiffness and damping. The defaults are the point the
    grid search chose for ``pd_gravity_leso`` (docs/gains/pd_gravity_leso); ``pd_gravity`` has its
    own (:data:`PD_GRAVITY`). Both were chosen on the paper's 3-link arm: an arm of another number of
    links (``nominal``) is given Kp and Kd (ValueError naming the gain otherwise)."""

    # paper: the search's point on the paper's 3-link arm
    Kp: tuple[float, ...] = field(default=(6400.0, 6400.0, 1600.0), metadata={"unit": "N m/rad"})
    """Proportional gain per joint, N m/rad (each > 0)."""
    Kd: tuple[float, ...] = field(default=(10.0, 10.0, 2.5), metadata={"unit": "N m s/rad"})
    """Derivative gain per joint, N m s/rad (each > 0)."""
    nominal: ArmParams = field(default_factory=ArmParams)
    """The controller's model of the arm (its gravity and, on the LESO, its inertia)."""

    def __post_init__(self) -> None:
        n = self.nominal.n_links
        object.__setattr__(self, "Kp", positive_vector("PDGains", "Kp", self.Kp, n, one_for_all=True))
        object.__setattr__(self, "Kd", positive_vector("PDGains", "Kd", self.Kd, n, one_for_all=True))


@dataclass(frozen=True)
class CTCGains:
    """Computed torque: the error dynamics' stiffness and damping per joint. No point of the grid
    search met both conditions (docs/gains/computed_torque_leso): on the LESO only Kp = 102,400 1/s^2
    kept every bound on the selection episodes, at 1.32-1.75 times the law's RMS torque against the
    budget's 1.25; the defaults are the one of those with the least torque. The full-state law kept
    the bounds at no point. The defaults are one number for every joint, so they hold for an arm of
    any number of links."""

    Kp: tuple[float, ...] = field(default=102400.0, metadata={"unit": "1/s^2"})
    """Proportional gain of the commanded acceleration per joint, 1/s^2 (each > 0)."""
    Kd: tuple[float, ...] = field(default=80.0, metadata={"unit": "1/s"})
    """Derivative gain of the commanded acceleration per joint, 1/s (each > 0); 2 sqrt(Kp) is
    critical damping of the nominal error dynamics."""
    nominal: ArmParams = field(default_factory=ArmParams)
    """The controller's model of the arm (M, C, G of the feedback linearisation)."""

    def __post_init__(self) -> None:
        n = self.nominal.n_links
        object.__setattr__(self, "Kp", positive_vector("CTCGains", "Kp", self.Kp, n, one_for_all=True))
        object.__setattr__(self, "Kd", positive_vector("CTCGains", "Kd", self.Kd, n, one_for_all=True))


@njit(cache=True, error_model="numpy", inline="always")
def _pd(y, v, x3_hat, use_dist, q_d, qd_d, Kp, Kd, nominal, u):
    n = y.shape[0]
    nn = n * n
    for i in range(n):
        ui = nominal[nn + i] - Kp[i] * (y[i] - q_d[i]) - Kd[i] * (v[i] - qd_d[i])
        if use_dist:
            for j in range(n):
                ui -= nominal[i * n + j] * x3_hat[j]
        u[i] = ui


@njit(cache=True, error_model="numpy", inline="always")
def _ctc(y, v, x3_hat, use_dist, q_d, qd_d, qdd_d, Kp, Kd, nominal, work, u):
    n = y.shape[0]
    nn = n * n
    a = work[:n]
    cv = work[n : 2 * n]
    for i in range(n):
        a[i] = qdd_d[i] - Kd[i] * (v[i] - qd_d[i]) - Kp[i] * (y[i] - q_d[i])
        if use_dist:
            a[i] -= x3_hat[i]
    coriolis_times(nominal, v, v, cv)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += nominal[i * n + j] * a[j]
        u[i] = acc + cv[i] + nominal[nn + i]


@njit(cache=True, error_model="numpy", inline="always")
def pd_gravity_output(y, qd_true, q_d, qd_d, Kp, Kd, nominal, u_law):
    """PD on the true velocity plus the nominal gravity torque."""
    _pd(y, qd_true, qd_true, False, q_d, qd_d, Kp, Kd, nominal, u_law)


@njit(cache=True, error_model="numpy", inline="always")
def pd_gravity_leso_output(y, x2_hat, x3_hat, q_d, qd_d, Kp, Kd, nominal, u_law):
    """PD on the LESO's velocity plus the nominal gravity torque, minus M(y) x3_hat."""
    _pd(y, x2_hat, x3_hat, True, q_d, qd_d, Kp, Kd, nominal, u_law)


@njit(cache=True, error_model="numpy", inline="always")
def computed_torque_output(y, qd_true, q_d, qd_d, qdd_d, Kp, Kd, nominal, work, u_law):
    """Computed torque on the nominal model with the true velocity."""
    _ctc(y, qd_true, qd_true, False, q_d, qd_d, qdd_d, Kp, Kd, nominal, work, u_law)


@njit(cache=True, error_model="numpy", inline="always")
def computed_torque_leso_output(y, x2_hat, x3_hat, q_d, qd_d, qdd_d, Kp, Kd, nominal, work, u_law):
    """Computed torque on the nominal model with the LESO's velocity, the commanded acceleration
    less the estimated disturbance x3_hat."""
    _ctc(y, x2_hat, x3_hat, True, q_d, qd_d, qdd_d, Kp, Kd, nominal, work, u_law)


PD_GRAVITY = {"Kp": (12800.0, 12800.0, 3200.0), "Kd": (40.0, 40.0, 10.0)}  # paper: its 3-link arm
"""The full-state PD's gains, the grid search's choice (docs/gains/pd_gravity) on the paper's 3-link
arm; an arm of another number of links is given Kp and Kd."""


def pd_gravity(**kwargs: Any) -> Controller:
    """PD with gravity compensation on the true velocity (full state, no observer in the law)."""
    return Controller("pd_gravity", pd_gravity_output, params_from(PDGains, {**PD_GRAVITY, **kwargs},
                                                                   "controller gain"))


def pd_gravity_leso(**kwargs: Any) -> Controller:
    """PD with gravity compensation on the LESO's velocity, with its disturbance estimate."""
    return Controller("pd_gravity_leso", pd_gravity_leso_output, params_from(PDGains, kwargs, "controller gain"))


def computed_torque(**kwargs: Any) -> Controller:
    """Computed-torque control on the nominal model with the true velocity."""
    return Controller("computed_torque", computed_torque_output, params_from(CTCGains, kwargs, "controller gain"))


def computed_torque_leso(**kwargs: Any) -> Controller:
    """Computed-torque control on the nominal model with the LESO's estimates."""
    return Controller("computed_torque_leso", computed_torque_leso_output,
                      params_from(CTCGains, kwargs, "controller gain"))
