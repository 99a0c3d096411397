"""Parameters of the plant, the reference, the error bounds and the simulation.

This module is the one place where defaults live. Every field carries its unit in the docstring
and every dataclass validates itself at construction, raising ``ValueError`` that names the field
and the accepted range. The paper's set-up (Tran et al., Electronics 2020, 9, 1355, Section 4.1,
Tables 1-2) is available as two named presets, ``"paper-0.1hz"`` and ``"paper-0.5hz"``
(:func:`preset`).

The compiled kernels do not take dataclasses; :meth:`Scenario.pack_plant` and friends flatten
them into float64 arrays whose layout is documented next to each ``pack_*`` method.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal

import numpy as np

from blf_gym.jit.layout import (ARM, BOUNDS_PACK, PLANT, PLANT_TAIL, REFERENCE, REFERENCE_JOINT_PACK, REFERENCE_KINDS,
                                REFERENCE_PACK)

__all__ = [
    "MAX_DURATION",
    "ArmParams",
    "FrictionParams",
    "DeadZoneParams",
    "ForceParams",
    "ReferenceParams",
    "BoundParams",
    "SimParams",
    "Scenario",
    "PRESETS",
    "preset",
    "joint_scenario",
    "with_sim",
    "REFERENCE_PACK",
    "REFERENCE_JOINT_PACK",
    "REFERENCE_KINDS",
    "reference_length",
    "DT_MIN",
    "check_real",
    "check_reals",
    "check_int",
    "check_bool",
    "check_choice",
    "check_instance",
]


DT_MIN = 1e-7
"""Smallest accepted integration step ``SimParams.dt``, s (10 000 steps per 1 ms sample)."""

MAX_DURATION = 3600.0
"""Longest accepted episode, s (``SimParams.duration``, the env's ``duration``). What follows an
episode is kept per 1 ms sample: the inner path's trajectory, and the env's default score reward,
which holds the law's running error over the whole episode (24 bytes per sample and arm, 86 MB per
arm at this limit). A longer episode (1e6 s asked for 22 GiB at construction) is refused rather
than allocated; the paper's episodes are 30 s."""


# ---- validation helpers ---------------------------------------------------------------------
# One set of checks for every parameter of the package (dataclass fields, env keyword arguments,
# variations, reset options, seeds). Each raises ValueError naming the field and what it accepts,
# and returns the value normalized (a Python float / int / bool / str / tuple of floats).
# ``owner`` is a class name ("SimParams": the label is "SimParams.dt"), ends with a colon
# ("PlanarBLFEnv:": the label is "PlanarBLFEnv: dt") or is empty (the label is ``name`` itself).


def _label(owner: str, name: str) -> str:
    if not owner:
        return name
    return f"{owner} {name}" if owner.endswith(":") else f"{owner}.{name}"


def is_bool(value: Any) -> bool:
    """True for ``bool`` and ``numpy.bool_``."""
    return isinstance(value, (bool, np.bool_))


def is_real(value: Any) -> bool:
    """True for a real number: int, float, numpy integer/float scalars (and 0-d arrays of them);
    False for bools, strings, complex numbers, None and containers."""
    if isinstance(value, (float, int, np.floating, np.integer)):  # fast path: no ABC check
        return not isinstance(value, bool)
    if isinstance(value, np.ndarray):
        return value.ndim == 0 and value.dtype.kind in "iuf"
    return isinstance(value, numbers.Real) and not is_bool(value)


def is_integer(value: Any) -> bool:
    """True for int and numpy integer scalars (and 0-d integer arrays), never for bools."""
    if isinstance(value, (int, np.integer)):
        return not isinstance(value, bool)
    if isinstance(value, np.ndarray):
        return value.ndim == 0 and value.dtype.kind in "iu"
    return isinstance(value, numbers.Integral) and not is_bool(value)


def _fmt(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _range_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {_fmt(lo)}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {_fmt(hi)}"
    return ""


def real_text(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
              hi_open: bool = False, unit: str = "", none_ok: bool = False) -> str:
    """What :func:`check_real` accepts, in words (for error messages)."""
    rng = _range_text(lo, hi, lo_open, hi_open)
    u = (f" {unit}" if rng else f" (in {unit})") if unit else ""
    return ("None or " if none_ok else "") + "a finite real number" + rng + u


def check_real(owner: str, name: str, value: Any, lo: float | None = None, hi: float | None = None, *,
               lo_open: bool = False, hi_open: bool = False, unit: str = "", none_ok: bool = False,
               hint: str = "") -> Any:
    """``value`` as a float if it is a finite real number in the given range (``lo_open`` /
    ``hi_open`` exclude the ends); None if it is None and ``none_ok``; else ValueError
    ``"<owner>.<name> must be a finite real number ..., got <repr>"``. Bools, strings and
    complex numbers are refused; numpy integer and float scalars are accepted, a float32 or float16
    as the decimal it prints as (np.float32(0.01) is 0.01, not 0.009999999776)."""
    if type(value) is float and math.isfinite(value) and (lo is None or value > lo) and (hi is None or value < hi):
        return value  # the common case, checked in full below only when it is not this one
    if value is None and none_ok:
        return None
    v = math.nan
    if is_real(value):
        try:
            v = float(value)
            if isinstance(value, (np.floating, np.ndarray)) and np.asarray(value).dtype.itemsize < 8:
                # a float32 (or float16) is read as the decimal it prints as, the number its user
                # wrote: np.float32(0.01) is 0.01, not 0.009999999776 (which is no multiple of 1 ms)
                v = float(str(np.asarray(value)[()]))
        except (OverflowError, ValueError, TypeError):
            v = math.nan
    if not (math.isfinite(v) and (lo is None or v > lo or (v == lo and not lo_open))
            and (hi is None or v < hi or (v == hi and not hi_open))):
        raise ValueError(f"{_label(owner, name)} must be "
                         f"{real_text(lo, hi, lo_open=lo_open, hi_open=hi_open, unit=unit, none_ok=none_ok)}"
                         f"{hint}, got {value!r}")
    return v


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity mask where the OS has one, else
    ``os.cpu_count()``): the most numba threads an env or a batch accepts."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # macOS and Windows have no affinity call
        return max(1, os.cpu_count() or 1)


def check_int(owner: str, name: str, value: Any, lo: int | None = None, hi: int | None = None, *,
              none_ok: bool = False, hint: str = "") -> Any:
    """``value`` as an int if it is an integer (int or numpy integer, not a bool or a float) in
    [lo, hi]; None if it is None and ``none_ok``; else ValueError naming the field."""
    if value is None and none_ok:
        return None
    ok = is_integer(value)
    v = int(value) if ok else 0
    if not (ok and (lo is None or v >= lo) and (hi is None or v <= hi)):
        what = ("None or " if none_ok else "") + "an integer" + _range_text(lo, hi, False, False)
        got = repr(value)
        if len(got) > 80:  # e.g. 10**400: its 401 digits say nothing more than its size
            got = f"{got[:20]}...{got[-10:]} ({len(got)} characters)"
        raise ValueError(f"{_label(owner, name)} must be {what}{hint}, got {got}")
    return v


def check_bool(owner: str, name: str, value: Any) -> bool:
    """``value`` as a bool if it is a bool or ``numpy.bool_`` (not 0/1, not a string)."""
    if not is_bool(value):
        raise ValueError(f"{_label(owner, name)} must be a bool (True or False), got {value!r}")
    return bool(value)


def check_choice(owner: str, name: str, value: Any, choices: Any, *, extra: str = "") -> str:
    """``value`` if it is a string among ``choices``; else ValueError listing them (plus
    ``extra``, e.g. " or a Scenario")."""
    if not (isinstance(value, str) and value in choices):
        raise ValueError(f"{_label(owner, name)} must be one of {list(choices)}{extra}, got {value!r}")
    return value


def check_reals(owner: str, name: str, value: Any, length: int | None = None,
                lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                hi_open: bool = False, unit: str = "", min_length: int = 1) -> tuple[float, ...]:
    """``value`` as a tuple of floats if it is a sequence (list, tuple or 1-d array) of ``length``
    (or at least ``min_length``) real numbers, each as :func:`check_real` with ``lo`` / ``hi``;
    a bad entry is named as ``<name>[i]``."""
    def refuse(got: str) -> ValueError:
        each = real_text(lo, hi, lo_open=lo_open, hi_open=hi_open, unit=unit)
        what = (f"a sequence of {length} real numbers" if length is not None
                else f"a sequence of at least {min_length} real number(s)")
        return ValueError(f"{_label(owner, name)} must be {what} (each {each}), got {got}{value!r}")

    if isinstance(value, np.ndarray):
        if value.ndim != 1 or value.dtype.kind not in "iuf":
            raise refuse("")
        items: list[Any] = list(value)
    elif isinstance(value, (list, tuple)):
        items = list(value)
    else:
        raise refuse("")
    if (length is not None and len(items) != length) or len(items) < min_length:
        raise refuse(f"{len(items)} entries: ")
    if all(type(v) is float and math.isfinite(v) and (lo is None or v > lo) and (hi is None or v < hi)
           for v in items):
        return tuple(items)  # the common case (check_real's own fast path, without a label per entry)
    return tuple(check_real(owner, f"{name}[{i}]", v, lo, hi, lo_open=lo_open, hi_open=hi_open, unit=unit)
                 for i, v in enumerate(items))


def check_instance(owner: str, name: str, value: Any, cls: type) -> Any:
    """``value`` if it is an instance of ``cls``; else ValueError naming the field."""
    if not isinstance(value, cls):
        raise ValueError(f"{_label(owner, name)} must be a blf_gym.model.params.{cls.__name__}, got {value!r}")
    return value


def _set(obj: Any, name: str, value: Any) -> None:
    object.__setattr__(obj, name, value)


@dataclass(frozen=True)
class ArmParams:
    """An n-link planar arm with a point mass at the distal end of each link (paper Table 1).

    The same class describes the true plant and the nominal model a controller uses; the two are
    kept apart so that a randomized plant can differ from the controller's model.
    """

    lengths: tuple[float, ...] = field(default=(0.35, 0.30, 0.15), metadata={"unit": "m"})
    """Link lengths l_i, m (each > 0)."""
    masses: tuple[float, ...] = field(default=(0.23, 0.20, 0.10), metadata={"unit": "kg"})
    """Point masses m_i at the distal end of each link, kg (each > 0)."""
    gravity: float = field(default=9.81, metadata={"unit": "m/s^2"})
    """Gravitational acceleration along -y, m/s^2 (>= 0)."""

    def __post_init__(self) -> None:
        lengths = check_reals("ArmParams", "lengths", self.lengths, lo=0.0, lo_open=True, unit="m")
        # one mass per link
        masses = check_reals("ArmParams", "masses", self.masses, len(lengths), lo=0.0, lo_open=True,
                             unit="kg")
        _set(self, "lengths", lengths)
        _set(self, "masses", masses)
        _set(self, "gravity", check_real("ArmParams", "gravity", self.gravity, lo=0.0, unit="m/s^2"))

    @property
    def n_links(self) -> int:
        return len(self.lengths)

    def pack(self) -> np.ndarray:
        """Layout :data:`blf_gym.jit.layout.ARM`: ``[lengths (n), masses (n), gravity]``, length 2n + 1."""
        parts = {"lengths": self.lengths, "masses": self.masses, "gravity": (self.gravity,)}
        return np.array([v for p in ARM for v in parts[p]], dtype=np.float64)


@dataclass(frozen=True)
class FrictionParams:
    """Joint friction tau_fric = b qd + c tanh(psi qd), the same on every joint (paper eq. 2)."""

    viscous: float = field(default=0.5, metadata={"unit": "N m s/rad"})
    """Viscous coefficient b, N m s/rad (>= 0)."""
    coulomb: float = field(default=0.2, metadata={"unit": "N m"})
    """Coulomb level c, N m (>= 0)."""
    tanh_slope: float = field(default=10.0, metadata={"unit": "s/rad"})
    """Smoothing slope psi of the Coulomb term, s/rad (> 0)."""

    def __post_init__(self) -> None:
        _set(self, "viscous", check_real("FrictionParams", "viscous", self.viscous, lo=0.0, unit="N m s/rad"))
        _set(self, "coulomb", check_real("FrictionParams", "coulomb", self.coulomb, lo=0.0, unit="N m"))
        _set(self, "tanh_slope", check_real("FrictionParams", "tanh_slope", self.tanh_slope, lo=0.0,
                                            lo_open=True, unit="s/rad"))


@dataclass(frozen=True)
class DeadZoneParams:
    """Asymmetric input dead-zone H(tau) on every joint (paper eq. 3).

    H(tau) = slope_right (tau - break_right) for tau >= break_right; 0 between the break points;
    slope_left (tau - break_left) for tau <= break_left.
    """

    slope_right: float = field(default=1.0, metadata={"unit": "-"})
    """h_r, dimensionless (> 0)."""
    slope_left: float = field(default=1.2, metadata={"unit": "-"})
    """h_l, dimensionless (> 0)."""
    break_right: float = field(default=0.2, metadata={"unit": "N m"})
    """tau_r, N m (>= 0)."""
    break_left: float = field(default=-0.2, metadata={"unit": "N m"})
    """tau_l, N m (<= 0)."""

    def __post_init__(self) -> None:
        o = "DeadZoneParams"
        _set(self, "slope_right", check_real(o, "slope_right", self.slope_right, lo=0.0, lo_open=True))
        _set(self, "slope_left", check_real(o, "slope_left", self.slope_left, lo=0.0, lo_open=True))
        _set(self, "break_right", check_real(o, "break_right", self.break_right, lo=0.0, unit="N m"))
        _set(self, "break_left", check_real(o, "break_left", self.break_left, hi=0.0, unit="N m"))


@dataclass(frozen=True)
class ForceParams:
    """External end-effector wrench, a step switched on at ``onset`` (Section 4.1).

    It enters the model as printed in the paper's eq. (1): ``J(q)^T f_ext`` on the left-hand side,
    so the wrench that acts on the arm is ``-f_ext``. With the default ``(40, 0, 0)`` the arm is
    pushed towards -x.
    """

    wrench: tuple[float, float, float] = field(default=(40.0, 0.0, 0.0), metadata={"unit": "N, N, N m"})
    """f_ext = (f_x N, f_y N, moment N m) in the base frame."""
    onset: float = field(default=20.0, metadata={"unit": "s"})
    """Switch-on time, s (>= 0). The paper's Section 4.1 says 20 s and its results text 15 s;
    20 s is the default here."""

    def __post_init__(self) -> None:
        _set(self, "wrench", check_reals("ForceParams", "wrench", self.wrench, 3))  # (f_x, f_y, moment)
        _set(self, "onset", check_real("ForceParams", "onset", self.onset, lo=0.0, unit="s"))


Branch = Literal["smooth", "standard"]


@dataclass(frozen=True)
class ReferenceParams:
    """The task's reference, one of two kinds.

    ``kind="circle"`` (default, the paper's Section 4.1): the end effector runs on the circle
    x_d = cx + r cos(2 pi f t), y_d = cy + r sin(2 pi f t) with a fixed angle phi_d. Joint references
    come from inverse kinematics (3 links only). The paper's circle puts the wrist on a circle that
    touches the inner workspace boundary |w| = |l1 - l2|, where the elbow folds and the Jacobian is
    singular. ``branch="smooth"`` (default) passes through the fold analytically; ``"standard"``
    keeps q2 in [0, pi] and so has a velocity jump at every fold. The centre, radius and orientation
    must keep that tangency (checked by the scenario).

    ``kind="joint"``: one sinusoid per joint, q_d,j(t) = offsets[j] + amplitudes[j] sin(2 pi f t +
    phases[j]), for an arm of any number of links (one entry per link in each of the three tuples;
    the circle's fields are then unused). Smooth, with analytic derivatives.
    """

    frequency: float = 0.1
    """f, Hz (> 0)."""
    center: tuple[float, float] = (0.4, 0.0)
    """(cx, cy), m."""
    radius: float = 0.2
    """r, m (> 0)."""
    orientation: float = 0.0
    """phi_d, the end-effector's absolute angle, rad."""
    branch: Branch = "smooth"
    """Inverse-kinematics branch: "smooth" or "standard"."""
    kind: str = "circle"
    """"circle" (the paper's Cartesian circle, 3 links) or "joint" (one sinusoid per joint, any n)."""
    amplitudes: tuple[float, ...] = field(default=(), metadata={"unit": "rad"})
    """kind="joint": each joint's amplitude, rad (>= 0)."""
    phases: tuple[float, ...] = field(default=(), metadata={"unit": "rad"})
    """kind="joint": each joint's phase, rad."""
    offsets: tuple[float, ...] = field(default=(), metadata={"unit": "rad"})
    """kind="joint": each joint's centre angle, rad."""

    def __post_init__(self) -> None:
        o = "ReferenceParams"
        _set(self, "frequency", check_real(o, "frequency", self.frequency, lo=0.0, lo_open=True, unit="Hz"))
        _set(self, "center", check_reals(o, "center", self.center, 2, unit="m"))
        _set(self, "radius", check_real(o, "radius", self.radius, lo=0.0, lo_open=True, unit="m"))
        _set(self, "orientation", check_real(o, "orientation", self.orientation, unit="rad"))
        check_choice(o, "branch", self.branch, ("smooth", "standard"))
        check_choice(o, "kind", self.kind, REFERENCE_KINDS)
        if self.kind == "circle":
            for name in ("amplitudes", "phases", "offsets"):
                if tuple(getattr(self, name)) != ():
                    raise ValueError(f"ReferenceParams.{name} applies to kind='joint' only; the circle's joint "
                                     f"references come from its inverse kinematics (got {getattr(self, name)!r})")
            return
        amps = check_reals(o, "amplitudes", self.amplitudes, lo=0.0, unit="rad")
        if not amps:
            raise ValueError("ReferenceParams.amplitudes must give one amplitude per joint for kind='joint' "
                             "(rad, >= 0), got ()")
        _set(self, "amplitudes", amps)
        _set(self, "phases", check_reals(o, "phases", self.phases, len(amps), unit="rad"))
        _set(self, "offsets", check_reals(o, "offsets", self.offsets, len(amps), unit="rad"))


@dataclass(frozen=True)
class BoundParams:
    """Time-varying bounds on the tracking error e1 = q - q_d, the same on every joint (eq. 17).

    e1 must stay in (-k_b(t), k_a(t)) with k_a(t) = upper_amplitude exp(-decay_rate t) + upper_floor
    and k_b(t) = lower_amplitude exp(-decay_rate t) + lower_floor (paper Table 2).
    """

    upper_amplitude: float = 0.5
    """Decaying part of k_a, rad (>= 0)."""
    upper_floor: float = 0.02
    """Steady value of k_a, rad (> 0)."""
    lower_amplitude: float = 0.6
    """Decaying part of k_b, rad (>= 0)."""
    lower_floor: float = 0.04
    """Steady value of k_b, rad (> 0)."""
    decay_rate: float = 0.6
    """Decay rate, 1/s (>= 0)."""

    def __post_init__(self) -> None:
        o = "BoundParams"
        for name, lo_open, unit in (("upper_amplitude", False, "rad"), ("upper_floor", True, "rad"),
                                    ("lower_amplitude", False, "rad"), ("lower_floor", True, "rad"),
                                    ("decay_rate", False, "1/s")):
            _set(self, name, check_real(o, name, getattr(self, name), lo=0.0, lo_open=lo_open, unit=unit))

    def pack(self) -> np.ndarray:
        """Layout :data:`BOUNDS_PACK`: ``[upper_amplitude, upper_floor, lower_amplitude, lower_floor,
        decay_rate]``."""
        return np.array([getattr(self, name) for name in BOUNDS_PACK], dtype=np.float64)


@dataclass(frozen=True)
class SimParams:
    """Integration and actuator settings (docs/model.md section 6)."""

    dt: float = 1e-4
    """ODE3 (Bogacki-Shampine) step h, s. Must divide ``sample_period``. The paper's 1 ms diverges
    with its gains on this plant; 0.1 ms is the default."""
    duration: float = 30.0
    """Episode length, s (> 0, a whole number of sample periods)."""
    sample_period: float = 1e-3
    """Grid on which trajectories are recorded and metrics computed, s."""
    max_torque: float = 150.0
    """Per-joint actuator limit applied to every policy alike, N m (> 0). The paper's laws are
    unbounded; the default is above the largest torque any paper case commands."""
    divergence_limit: float = 1e6
    """A state entry above this magnitude (or non-finite) counts as divergence (> 0)."""
    error_rtol: float = 0.2
    """Relative tolerance of the instability detector (> 0): ODE3's embedded error estimate of a
    step is compared with error_atol + error_rtol |x|. These are loose on purpose: they flag a step
    outside the integrator's stability region, not an inaccurate one. They were set from a list of
    runs judged by halving the step (docs/model.md, "Integration"): stable runs whose estimate is
    excited by measurement noise up to 1e-3 rad or by a light payload stay below 0.9 of it, runs
    outside the stability region (the paper's 1 ms step) exceed it by 2x or more from the first
    steps."""
    error_atol: float = 2e-2
    """Absolute tolerance of the instability detector, in the state's units (> 0)."""
    unstable_steps: int = 100
    """That many consecutive steps above tolerance count as numerical divergence (>= 1). A
    saturating actuator can keep an unstable integration finite; this still catches it."""

    def __post_init__(self) -> None:
        o = "SimParams"
        _set(self, "sample_period", check_real(o, "sample_period", self.sample_period, DT_MIN, unit="s"))
        _set(self, "dt", check_real(o, "dt", self.dt, DT_MIN, self.sample_period, unit="s",
                                    hint=f" dividing sample_period={self.sample_period} s exactly"))
        _set(self, "duration", check_real(o, "duration", self.duration, lo=0.0, hi=MAX_DURATION, lo_open=True,
                                          unit="s", hint=" (blf_gym.model.params.MAX_DURATION: an episode's signals and "
                                          "the score reward's reference are kept per 1 ms sample)"))
        for name, unit in (("max_torque", "N m"), ("divergence_limit", ""), ("error_rtol", ""), ("error_atol", "")):
            _set(self, name, check_real(o, name, getattr(self, name), lo=0.0, lo_open=True, unit=unit))
        _set(self, "unstable_steps", check_int(o, "unstable_steps", self.unstable_steps, lo=1))
        ratio = self.sample_period / self.dt
        if abs(ratio - round(ratio)) > 1e-9 * ratio or round(ratio) < 1:
            raise ValueError(
                f"SimParams.dt must divide sample_period={self.sample_period} s exactly "
                f"(e.g. 1e-4, 5e-5, 1e-3; at least {DT_MIN:g} s), got dt={self.dt}"
            )
        n = self.duration / self.sample_period
        if abs(n - round(n)) > 1e-9 * n:
            raise ValueError(
                f"SimParams.duration must be a whole number of sample periods "
                f"({self.sample_period} s), got {self.duration}"
            )

    @property
    def steps_per_sample(self) -> int:
        return int(round(self.sample_period / self.dt))

    @property
    def n_samples(self) -> int:
        return int(round(self.duration / self.sample_period))

    @property
    def n_steps(self) -> int:
        return self.n_samples * self.steps_per_sample


def reference_length(n: int) -> int:
    """Length of the packed reference of an n-link scenario (:data:`blf_gym.jit.layout.REFERENCE`)."""
    return REFERENCE.length(n)


def plant_length(n: int) -> int:
    """Length of the packed plant vector of an n-link scenario (:data:`blf_gym.jit.layout.PLANT`)."""
    return PLANT.length(n)


@dataclass(frozen=True)
class Scenario:
    """Everything that defines one closed-loop experiment except the controller.

    The true plant is ``arm`` with ``friction``, ``dead_zone`` and ``force``; the controller keeps
    its own nominal model (see :mod:`baselines.controllers`).
    """

    name: str = "paper-0.1hz"
    """A label used in results (``scenario`` field)."""
    arm: ArmParams = field(default_factory=ArmParams)
    friction: FrictionParams = field(default_factory=FrictionParams)
    dead_zone: DeadZoneParams = field(default_factory=DeadZoneParams)
    force: ForceParams = field(default_factory=ForceParams)
    reference: ReferenceParams = field(default_factory=ReferenceParams)
    bounds: BoundParams = field(default_factory=BoundParams)
    sim: SimParams = field(default_factory=SimParams)
    initial_error: tuple[float, ...] = (0.0, 0.0, 0.0)
    """e1(0) = q(0) - q_d(0) per joint, rad; must lie strictly inside the bounds at t = 0."""
    angle_noise_std: float = 0.0
    """Standard deviation of white noise added to the measured angles at each step, rad (>= 0)."""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ValueError(f"Scenario.name must be a string, got {self.name!r}")
        for name, cls in (("arm", ArmParams), ("friction", FrictionParams), ("dead_zone", DeadZoneParams),
                          ("force", ForceParams), ("reference", ReferenceParams), ("bounds", BoundParams),
                          ("sim", SimParams)):
            check_instance("Scenario", name, getattr(self, name), cls)
        n = self.arm.n_links
        r = self.reference
        if r.kind == "circle" and n != 3:
            raise ValueError(
                f"Scenario.arm must have 3 links for the reference kind 'circle': the paper's reference (a "
                f"Cartesian circle with a fixed orientation) is solved by 3-link inverse kinematics; got {n}. "
                f"For another number of links give ReferenceParams(kind='joint', ...) (see joint_scenario)"
            )
        if r.kind == "joint" and len(r.amplitudes) != n:
            raise ValueError(f"Scenario.reference: kind 'joint' needs one amplitude, phase and offset per joint "
                             f"({n} for this arm), got {len(r.amplitudes)}")
        if n != 3 and tuple(self.initial_error) == (0.0, 0.0, 0.0):
            _set(self, "initial_error", (0.0,) * n)  # the default: no initial error on any joint
        e0 = check_reals("Scenario", "initial_error", self.initial_error, n, unit="rad")
        _set(self, "initial_error", e0)
        b = self.bounds
        ka0 = b.upper_amplitude + b.upper_floor
        kb0 = b.lower_amplitude + b.lower_floor
        for i, e in enumerate(e0):
            if not (-kb0 < e < ka0):
                raise ValueError(
                    f"Scenario.initial_error[{i}]={e} must lie inside the bounds at t=0, "
                    f"the open interval ({-kb0}, {ka0}) rad"
                )
        _set(self, "angle_noise_std", check_real("Scenario", "angle_noise_std", self.angle_noise_std, lo=0.0,
                                                 unit="rad"))
        if r.kind == "circle":
            self._check_reference_geometry()

    def _check_reference_geometry(self) -> None:
        l1, l2, l3 = self.arm.lengths
        r = self.reference
        wcx = r.center[0] - l3 * math.cos(r.orientation)
        wcy = r.center[1] - l3 * math.sin(r.orientation)
        dist = math.hypot(wcx, wcy)
        inner = abs(l1 - l2)
        if abs((dist - r.radius) - inner) > 1e-9 or l1 <= l2:
            raise ValueError(
                "Scenario.reference: the wrist circle (centre "
                f"{(round(wcx, 6), round(wcy, 6))}, radius {r.radius}) must touch the inner "
                f"workspace boundary |w| = l1 - l2 = {inner} m from outside, with l1 > l2, as the "
                "paper's circle does; this is what the analytic inverse kinematics solves. "
                "Change the centre or radius together, or keep the paper's values."
            )

    # ---- packing for the compiled kernel -------------------------------------------------
    def pack_plant(self) -> np.ndarray:
        """Layout :data:`blf_gym.jit.layout.PLANT`: ``arm.pack()`` (2n+1), then the entries of
        :data:`PLANT_TAIL`, in its order."""
        f, d, w, s = self.friction, self.dead_zone, self.force, self.sim
        values = {
            "viscous": f.viscous, "coulomb": f.coulomb, "tanh_slope": f.tanh_slope,
            "slope_right": d.slope_right, "slope_left": d.slope_left, "break_right": d.break_right,
            "break_left": d.break_left, "f_x": w.wrench[0], "f_y": w.wrench[1], "moment": w.wrench[2],
            "onset": w.onset, "max_torque": s.max_torque, "divergence_limit": s.divergence_limit,
            "error_rtol": s.error_rtol, "error_atol": s.error_atol, "unstable_steps": float(s.unstable_steps),
        }
        tail = [values[name] for name in PLANT_TAIL]
        return np.concatenate([self.arm.pack(), np.asarray(tail, dtype=np.float64)])

    def pack_reference(self) -> np.ndarray:
        """Layout :data:`REFERENCE_PACK`, then :data:`REFERENCE_JOINT_PACK` (a block of n each);
        length :func:`reference_length`."""
        r = self.reference
        n = self.arm.n_links
        if r.kind == "joint":
            head = {name: 0.0 for name in REFERENCE_PACK}
            head.update(frequency=r.frequency, cos_beta=1.0, kind=float(REFERENCE_KINDS.index("joint")))
            blocks = {"cos_phase": np.cos(r.phases), "sin_phase": np.sin(r.phases), "amplitude": r.amplitudes,
                      "offset": r.offsets}
            joints = np.concatenate([np.asarray(blocks[p], dtype=np.float64) for p in REFERENCE_JOINT_PACK])
            return np.concatenate([np.array([head[name] for name in REFERENCE_PACK], dtype=np.float64), joints])
        return np.concatenate([self._pack_circle(), np.zeros(len(REFERENCE_JOINT_PACK) * n)])

    def _pack_circle(self) -> np.ndarray:
        r = self.reference
        l3 = self.arm.lengths[2]
        wcx = r.center[0] - l3 * math.cos(r.orientation)
        wcy = r.center[1] - l3 * math.sin(r.orientation)
        dist = math.hypot(wcx, wcy)
        k = math.sqrt(r.radius * dist / (self.arm.lengths[0] * self.arm.lengths[1]))
        values = {
            "frequency": r.frequency, "center_x": r.center[0], "center_y": r.center[1], "radius": r.radius,
            "orientation": r.orientation, "branch": 0.0 if r.branch == "smooth" else 1.0, "wrist_x": wcx,
            "wrist_y": wcy, "k": k, "cos_beta": wcx / dist, "sin_beta": wcy / dist, "beta": math.atan2(wcy, wcx),
            "kind": float(REFERENCE_KINDS.index("circle")),
        }
        return np.array([values[name] for name in REFERENCE_PACK], dtype=np.float64)


def _paper(frequency: float, name: str) -> Scenario:
    return Scenario(name=name, reference=ReferenceParams(frequency=frequency))


PRESETS: dict[str, Scenario] = {
    "paper-0.1hz": _paper(0.1, "paper-0.1hz"),
    "paper-0.5hz": _paper(0.5, "paper-0.5hz"),
}
"""The paper's two simulation cases (Section 4.2.1 and 4.2.2)."""


def with_sim(owner: str, sc: Scenario, sim_overrides: dict[str, Any]) -> Scenario:
    """``sc`` with :class:`SimParams` fields replaced, unknown names refused by name (``owner``
    says whose argument they were)."""
    unknown = sorted(set(sim_overrides) - {f.name for f in fields(SimParams)})
    if unknown:
        raise ValueError(f"{owner}: unknown SimParams field(s) {unknown}; accepted: "
                         f"{[f.name for f in fields(SimParams)]}")
    return replace(sc, sim=replace(sc.sim, **sim_overrides)) if sim_overrides else sc


def preset(name: str, **sim_overrides: Any) -> Scenario:
    """The named paper preset, optionally with :class:`SimParams` fields replaced (e.g. ``dt``)."""
    if not (isinstance(name, str) and name in PRESETS):
        raise ValueError(f"unknown preset {name!r}; accepted values: {sorted(PRESETS)}")
    return with_sim("preset", PRESETS[name], sim_overrides)


def joint_scenario(n: int, frequency: float = 0.1, amplitude: float = 0.5, name: str | None = None,
                   **sim_overrides: Any) -> Scenario:
    """A simple joint-space task for an arm of ``n`` links (n >= 1): the paper's reach (0.8 m) and
    total mass (0.53 kg) split evenly over the links, the paper's friction, dead zone, force and
    bounds, and one sinusoid per joint (``amplitude`` rad at ``frequency`` Hz, the joints' phases
    spread evenly over half a period, no offset, no initial error).

    It exists so that the kernel, the env and the plug-ins run at any n with a reference they can
    follow; it is not the paper's task (that is :data:`PRESETS`, 3 links), and not a tuned task
    family. ``sim_overrides`` replace :class:`SimParams` fields, as :func:`preset`'s do."""
    n = check_int("joint_scenario", "n", n, lo=1)
    arm = ArmParams(lengths=(0.8 / n,) * n, masses=(0.53 / n,) * n)
    ref = ReferenceParams(frequency=frequency, kind="joint", amplitudes=(float(amplitude),) * n,
                          phases=tuple(math.pi * j / n for j in range(n)), offsets=(0.0,) * n)
    sc = Scenario(name=name or f"joint-{n}link-{frequency:g}hz", arm=arm, reference=ref)
    if sim_overrides:
        sc = replace(sc, sim=replace(sc.sim, **sim_overrides))
    return sc
