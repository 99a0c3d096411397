"""What an inner controller and an observer must provide to run inside the compiled closed loop.

``blf_gym`` never imports a controller. A controller is an :class:`InnerController`: a numba
``@njit`` function with the fixed signature below, its packed gains, and its nominal model. The
closed-loop kernel (:mod:`blf_gym.simulate`) calls it at **every ODE3 stage**, as Simulink's
continuous blocks are evaluated in the paper's set-up. Observers are :class:`Observer` objects
with the same idea. Named ones are found through the entry-point groups ``blf_gym.controllers``
and ``blf_gym.observers`` (the ``baselines`` package registers ``bc``, ``lesobc``, ``proposed``
and ``leso``), so the dependency points from ``baselines`` to ``blf_gym`` only.

Law signature (all arrays float64, C-contiguous; n joints)::

    law(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u_out, work) -> None

    t        float       time, s
    y        (n,)        measured joint angles, rad (true angles plus measurement noise)
    qd_true  (n,)        true joint velocities, rad/s; only a full-state law (BC) may read it
    xhat     (3n,)       observer state [x1_hat, x2_hat, x3_hat] (angles, velocities, lumped
                         disturbance in rad/s^2)
    ref      (3n,)       [q_d, qd_d, qdd_d]
    bnd      (6,)        [k_a, k_a', k_a'', k_b, k_b', k_b''] (same bound on every joint)
    nominal  (2n+1,)     the controller's nominal arm, ArmParams.pack()
    model    (2n^2+3n,)  the nominal model at the measured angles y, computed once per stage by
                         the kernel and shared by the law and the observer: [M(y) flat row-major
                         (n^2), G(y) (n), cos of the absolute link angles (n), their sines (n),
                         the LDL^T factor of M(y) flat row-major: unit lower factor below the
                         diagonal, 1/D on it, scratch above (n^2)]; pass its trig part to
                         blf_gym.dynamics.coriolis_times_into for C(y, v) w, and its factor to
                         blf_gym.dynamics.ldl_solve_factored for M(y)^-1 b
    gains    (G,)        the controller's own packed gains
    u_out    (n,)        write the commanded torque here, N m (finite, always)
    work     (WORK,)     scratch of length work_length(n); contents undefined on entry

Observer signature::

    rhs(y, xhat, u, nominal, model, gains, dxhat_out, work) -> None

where ``u`` is the torque actually commanded (after the residual and the actuator limit, before
the dead-zone) and ``dxhat_out`` (3n,) receives the observer state's time derivative.

A user's own controller: write such a function with ``@numba.njit(cache=True)`` at module level,
wrap it as ``InnerController(name, law, gains, nominal)``, and pass the object wherever a
controller name is accepted. ``tests/test_controller_plugin.py`` shows an example.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import Any, Callable

import numpy as np
from numba import njit

from .dynamics import abs_trig_into, ldl_factor_into, gravity_into, mass_matrix_into
from .params import ArmParams

__all__ = [
    "InnerController",
    "model_length",
    "nominal_model_into",
    "Observer",
    "work_length",
    "zero_law",
    "NO_CONTROLLER",
    "make_controller",
    "make_observer",
    "available_controllers",
]


@njit(cache=True, error_model="numpy", inline="always")
def work_length(n):
    """Length of the ``work`` scratch array handed to a law or an observer for n joints."""
    return 2 * n * n + 12 * n


@njit(cache=True, error_model="numpy", inline="always")
def model_length(n):
    """Length of the ``model`` array handed to a law or an observer for n joints."""
    return 2 * n * n + 3 * n


@njit(cache=True, error_model="numpy", inline="always")
def nominal_model_into(y, nominal, model, work):
    """Fill ``model`` = [M(y), G(y), cos theta, sin theta, LDL^T factor of M(y)] of the nominal arm (see
    above). ``work`` needs ``n`` entries."""
    n = y.shape[0]
    nn = n * n
    trig = model[nn + n : nn + 3 * n]
    abs_trig_into(y, trig)
    mass_matrix_into(trig, nominal, model[:nn], work)
    gravity_into(trig, nominal, model[nn : nn + n], work)
    ldl_factor_into(model[:nn], model[nn + 3 * n : 2 * nn + 3 * n])


@njit(cache=True, error_model="numpy", inline="always")
def zero_law(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u_out, work):
    """The empty inner controller (plain RL): commands zero torque."""
    for i in range(u_out.shape[0]):
        u_out[i] = 0.0


def _checked_plugin(fn_field: str, fn: Any, gains_field: str, gains: Any) -> np.ndarray:
    """Check a plug-in's compiled function and return its gains as a flat float64 array."""
    if not hasattr(fn, "py_func"):
        raise ValueError(f"{fn_field} must be a numba @njit function with the signature documented "
                         f"in blf_gym.controller, got {type(fn).__name__}")
    g = np.ascontiguousarray(np.asarray(gains, dtype=np.float64)).ravel()
    if not np.all(np.isfinite(g)):
        raise ValueError(f"{gains_field} must be finite, got {g}")
    return g


@dataclass(frozen=True, eq=False)
class InnerController:
    """A control law that runs inside the compiled closed loop at every ODE3 stage."""

    name: str
    """Label used in results (``policy``)."""
    law: Any
    """numba-compiled function with the law signature (module docstring)."""
    gains: np.ndarray
    """Packed float64 gains handed to ``law``."""
    nominal: ArmParams = field(default_factory=ArmParams)
    """The controller's own model of the arm (stays the paper's when the plant is randomized)."""
    full_state: bool = False
    """True if the law reads the true velocity (BC); documented so results can say so."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "gains", _checked_plugin("InnerController.law", self.law,
                                                          "InnerController.gains", self.gains))


@dataclass(frozen=True, eq=False)
class Observer:
    """A state observer integrated with the plant inside the compiled closed loop."""

    name: str
    rhs: Any
    """numba-compiled function with the observer signature (module docstring)."""
    gains: np.ndarray
    nominal: ArmParams = field(default_factory=ArmParams)
    initial_state: Callable[[np.ndarray], np.ndarray] | None = None
    """Maps the initial measured angles (n,) to xhat(0) (3n,); default [y0, 0, 0]."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "gains", _checked_plugin("Observer.rhs", self.rhs,
                                                          "Observer.gains", self.gains))

    def initial(self, y0: np.ndarray) -> np.ndarray:
        if self.initial_state is not None:
            return np.asarray(self.initial_state(y0), dtype=np.float64)
        n = y0.shape[0]
        out = np.zeros(3 * n)
        out[:n] = y0
        return out


NO_CONTROLLER = InnerController("none", zero_law, np.zeros(0))
"""The inner controller of plain mode: zero torque, so the agent's action is the whole input."""


def _group(name: str) -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=name)}


def available_controllers() -> list[str]:
    """Names accepted by :func:`make_controller` (``none`` plus the registered plug-ins)."""
    return ["none", *sorted(_group("blf_gym.controllers"))]


def available_observers() -> list[str]:
    """Names accepted by :func:`make_observer` (the registered plug-ins)."""
    return sorted(_group("blf_gym.observers"))


def make_controller(spec: "str | InnerController", **kwargs: Any) -> InnerController:
    """An :class:`InnerController` from a registered name (``bc``, ``lesobc``, ``proposed``,
    ``none``) or an existing object. ``kwargs`` go to the plug-in's factory (e.g. gains)."""
    if isinstance(spec, InnerController):
        if kwargs:
            raise ValueError("keyword arguments only apply when the controller is given by name")
        return spec
    if spec == "none":
        return NO_CONTROLLER
    eps = _group("blf_gym.controllers")
    if spec not in eps:
        raise ValueError(
            f"unknown controller {spec!r}; accepted values: {available_controllers()} "
            "(or an InnerController object). If 'bc', 'lesobc' or 'proposed' are missing, "
            "install the project (pip install -e .) so its entry points are registered."
        )
    obj = eps[spec].load()(**kwargs)
    if not isinstance(obj, InnerController):
        raise ValueError(f"entry point {spec!r} did not produce an InnerController")
    return obj


def make_observer(spec: "str | Observer" = "leso", **kwargs: Any) -> Observer:
    """An :class:`Observer` from a registered name (``leso``) or an existing object."""
    if isinstance(spec, Observer):
        if kwargs:
            raise ValueError("keyword arguments only apply when the observer is given by name")
        return spec
    eps = _group("blf_gym.observers")
    if spec not in eps:
        raise ValueError(
            f"unknown observer {spec!r}; accepted values: {sorted(eps)} (or an Observer object)"
        )
    obj = eps[spec].load()(**kwargs)
    if not isinstance(obj, Observer):
        raise ValueError(f"entry point {spec!r} did not produce an Observer")
    return obj
