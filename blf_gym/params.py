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
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal

import numpy as np

__all__ = [
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
]


def _positive(owner: str, name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{owner}.{name} must be a finite number > 0, got {value!r}")


def _nonnegative(owner: str, name: str, value: float) -> None:
    if not (math.isfinite(value) and value >= 0.0):
        raise ValueError(f"{owner}.{name} must be a finite number >= 0, got {value!r}")


def _finite(owner: str, name: str, value: float) -> None:
    if not math.isfinite(value):
        raise ValueError(f"{owner}.{name} must be finite, got {value!r}")


def _as_tuple(owner: str, name: str, value: Any) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in np.atleast_1d(np.asarray(value, dtype=float)))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{owner}.{name} must be a sequence of numbers, got {value!r}") from exc
    return out


@dataclass(frozen=True)
class ArmParams:
    """An n-link planar arm with a point mass at the distal end of each link (paper Table 1).

    The same class describes the true plant and the nominal model a controller uses; the two are
    kept apart so that a randomized plant can differ from the controller's model.
    """

    lengths: tuple[float, ...] = (0.35, 0.30, 0.15)
    """Link lengths l_i, m (each > 0)."""
    masses: tuple[float, ...] = (0.23, 0.20, 0.10)
    """Point masses m_i at the distal end of each link, kg (each > 0)."""
    gravity: float = 9.81
    """Gravitational acceleration along -y, m/s^2 (>= 0)."""

    def __post_init__(self) -> None:
        lengths = _as_tuple("ArmParams", "lengths", self.lengths)
        masses = _as_tuple("ArmParams", "masses", self.masses)
        object.__setattr__(self, "lengths", lengths)
        object.__setattr__(self, "masses", masses)
        if len(lengths) < 1:
            raise ValueError("ArmParams.lengths must hold at least one link length")
        if len(masses) != len(lengths):
            raise ValueError(
                f"ArmParams.masses must have one entry per link ({len(lengths)}), got {len(masses)}"
            )
        for i, v in enumerate(lengths):
            _positive("ArmParams", f"lengths[{i}]", v)
        for i, v in enumerate(masses):
            _positive("ArmParams", f"masses[{i}]", v)
        _nonnegative("ArmParams", "gravity", self.gravity)

    @property
    def n_links(self) -> int:
        return len(self.lengths)

    def pack(self) -> np.ndarray:
        """Layout ``[lengths (n), masses (n), gravity]``, length 2n + 1."""
        return np.array([*self.lengths, *self.masses, self.gravity], dtype=np.float64)


@dataclass(frozen=True)
class FrictionParams:
    """Joint friction tau_fric = b qd + c tanh(psi qd), the same on every joint (paper eq. 2)."""

    viscous: float = 0.5
    """Viscous coefficient b, N m s/rad (>= 0)."""
    coulomb: float = 0.2
    """Coulomb level c, N m (>= 0)."""
    tanh_slope: float = 10.0
    """Smoothing slope psi of the Coulomb term, s/rad (> 0)."""

    def __post_init__(self) -> None:
        _nonnegative("FrictionParams", "viscous", self.viscous)
        _nonnegative("FrictionParams", "coulomb", self.coulomb)
        _positive("FrictionParams", "tanh_slope", self.tanh_slope)


@dataclass(frozen=True)
class DeadZoneParams:
    """Asymmetric input dead-zone H(tau) on every joint (paper eq. 3).

    H(tau) = slope_right (tau - break_right) for tau >= break_right; 0 between the break points;
    slope_left (tau - break_left) for tau <= break_left.
    """

    slope_right: float = 1.0
    """h_r, dimensionless (> 0)."""
    slope_left: float = 1.2
    """h_l, dimensionless (> 0)."""
    break_right: float = 0.2
    """tau_r, N m (>= 0)."""
    break_left: float = -0.2
    """tau_l, N m (<= 0)."""

    def __post_init__(self) -> None:
        _positive("DeadZoneParams", "slope_right", self.slope_right)
        _positive("DeadZoneParams", "slope_left", self.slope_left)
        _nonnegative("DeadZoneParams", "break_right", self.break_right)
        _finite("DeadZoneParams", "break_left", self.break_left)
        if self.break_left > 0.0:
            raise ValueError(f"DeadZoneParams.break_left must be <= 0, got {self.break_left!r}")


@dataclass(frozen=True)
class ForceParams:
    """External end-effector wrench, a step switched on at ``onset`` (Section 4.1).

    It enters the model as printed in the paper's eq. (1): ``J(q)^T f_ext`` on the left-hand side,
    so the wrench that acts on the arm is ``-f_ext``. With the default ``(40, 0, 0)`` the arm is
    pushed towards -x.
    """

    wrench: tuple[float, float, float] = (40.0, 0.0, 0.0)
    """f_ext = (f_x N, f_y N, moment N m) in the base frame."""
    onset: float = 20.0
    """Switch-on time, s (>= 0). The paper's Section 4.1 says 20 s and its results text 15 s;
    20 s is the default here."""

    def __post_init__(self) -> None:
        w = _as_tuple("ForceParams", "wrench", self.wrench)
        if len(w) != 3:
            raise ValueError(f"ForceParams.wrench must have 3 entries (f_x, f_y, moment), got {len(w)}")
        for i, v in enumerate(w):
            _finite("ForceParams", f"wrench[{i}]", v)
        object.__setattr__(self, "wrench", w)
        _nonnegative("ForceParams", "onset", self.onset)


Branch = Literal["smooth", "standard"]


@dataclass(frozen=True)
class ReferenceParams:
    """End-effector circle x_d = cx + r cos(2 pi f t), y_d = cy + r sin(2 pi f t), phi_d (Section 4.1).

    Joint references come from inverse kinematics (3 links only). The paper's circle puts the wrist
    on a circle that touches the inner workspace boundary |w| = |l1 - l2|, where the elbow folds and
    the Jacobian is singular. ``branch="smooth"`` (default) passes through the fold analytically;
    ``"standard"`` keeps q2 in [0, pi] and so has a velocity jump at every fold.
    The centre, radius and orientation must keep that tangency (checked by the scenario).
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

    def __post_init__(self) -> None:
        _positive("ReferenceParams", "frequency", self.frequency)
        c = _as_tuple("ReferenceParams", "center", self.center)
        if len(c) != 2:
            raise ValueError(f"ReferenceParams.center must have 2 entries, got {len(c)}")
        object.__setattr__(self, "center", c)
        _positive("ReferenceParams", "radius", self.radius)
        _finite("ReferenceParams", "orientation", self.orientation)
        if self.branch not in ("smooth", "standard"):
            raise ValueError(
                f"ReferenceParams.branch must be 'smooth' or 'standard', got {self.branch!r}"
            )


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
        _nonnegative("BoundParams", "upper_amplitude", self.upper_amplitude)
        _positive("BoundParams", "upper_floor", self.upper_floor)
        _nonnegative("BoundParams", "lower_amplitude", self.lower_amplitude)
        _positive("BoundParams", "lower_floor", self.lower_floor)
        _nonnegative("BoundParams", "decay_rate", self.decay_rate)

    def pack(self) -> np.ndarray:
        """Layout ``[upper_amplitude, upper_floor, lower_amplitude, lower_floor, decay_rate]``."""
        return np.array(
            [self.upper_amplitude, self.upper_floor, self.lower_amplitude, self.lower_floor,
             self.decay_rate],
            dtype=np.float64,
        )


@dataclass(frozen=True)
class SimParams:
    """Integration and actuator settings (SPEC section 6)."""

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
    error_rtol: float = 1e-2
    """Relative tolerance of the instability detector (> 0): ODE3's embedded error estimate of a
    step is compared with error_atol + error_rtol |x|. These are loose on purpose: they flag a step
    outside the integrator's stability region, not an inaccurate one."""
    error_atol: float = 1e-3
    """Absolute tolerance of the instability detector, in the state's units (> 0)."""
    unstable_steps: int = 100
    """That many consecutive steps above tolerance count as numerical divergence (>= 1). A
    saturating actuator can keep an unstable integration finite; this still catches it."""

    def __post_init__(self) -> None:
        _positive("SimParams", "dt", self.dt)
        _positive("SimParams", "duration", self.duration)
        _positive("SimParams", "sample_period", self.sample_period)
        _positive("SimParams", "max_torque", self.max_torque)
        _positive("SimParams", "divergence_limit", self.divergence_limit)
        _positive("SimParams", "error_rtol", self.error_rtol)
        _positive("SimParams", "error_atol", self.error_atol)
        if int(self.unstable_steps) != self.unstable_steps or self.unstable_steps < 1:
            raise ValueError(f"SimParams.unstable_steps must be an integer >= 1, got {self.unstable_steps!r}")
        ratio = self.sample_period / self.dt
        if abs(ratio - round(ratio)) > 1e-9 * ratio or round(ratio) < 1:
            raise ValueError(
                f"SimParams.dt must divide sample_period={self.sample_period} s exactly "
                f"(e.g. 1e-4, 5e-5, 1e-3), got dt={self.dt}"
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
        e0 = _as_tuple("Scenario", "initial_error", self.initial_error)
        object.__setattr__(self, "initial_error", e0)
        n = self.arm.n_links
        if n != 3:
            raise ValueError(
                f"Scenario.arm must have 3 links: the paper's reference (a Cartesian circle with a "
                f"fixed orientation) is solved by 3-link inverse kinematics; got {n}"
            )
        if len(e0) != n:
            raise ValueError(f"Scenario.initial_error must have {n} entries, got {len(e0)}")
        b = self.bounds
        ka0 = b.upper_amplitude + b.upper_floor
        kb0 = b.lower_amplitude + b.lower_floor
        for i, e in enumerate(e0):
            if not (-kb0 < e < ka0):
                raise ValueError(
                    f"Scenario.initial_error[{i}]={e} must lie inside the bounds at t=0, "
                    f"the open interval ({-kb0}, {ka0}) rad"
                )
        _nonnegative("Scenario", "angle_noise_std", self.angle_noise_std)
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
        """Layout: ``arm.pack()`` (2n+1), then [viscous, coulomb, tanh_slope,
        slope_right, slope_left, break_right, break_left, f_x, f_y, moment, onset, max_torque,
        divergence_limit, error_rtol, error_atol, unstable_steps]."""
        f, d, w = self.friction, self.dead_zone, self.force
        tail = [
            f.viscous, f.coulomb, f.tanh_slope,
            d.slope_right, d.slope_left, d.break_right, d.break_left,
            *w.wrench, w.onset,
            self.sim.max_torque, self.sim.divergence_limit,
            self.sim.error_rtol, self.sim.error_atol, float(self.sim.unstable_steps),
        ]
        return np.concatenate([self.arm.pack(), np.asarray(tail, dtype=np.float64)])

    def pack_reference(self) -> np.ndarray:
        """Layout: [frequency, cx, cy, radius, orientation, branch (0 smooth, 1 standard),
        then derived constants: wrist-circle centre (wcx, wcy), k, cos, sin and value of
        beta = angle(c_w)]."""
        r = self.reference
        l3 = self.arm.lengths[2]
        wcx = r.center[0] - l3 * math.cos(r.orientation)
        wcy = r.center[1] - l3 * math.sin(r.orientation)
        dist = math.hypot(wcx, wcy)
        k = math.sqrt(r.radius * dist / (self.arm.lengths[0] * self.arm.lengths[1]))
        return np.array(
            [r.frequency, r.center[0], r.center[1], r.radius, r.orientation,
             0.0 if r.branch == "smooth" else 1.0, wcx, wcy, k, wcx / dist, wcy / dist,
             math.atan2(wcy, wcx)],
            dtype=np.float64,
        )

    def with_changes(self, **changes: Any) -> "Scenario":
        """A copy with top-level fields replaced (``dataclasses.replace``)."""
        valid = {f.name for f in fields(self)}
        unknown = set(changes) - valid
        if unknown:
            raise ValueError(f"Scenario has no field(s) {sorted(unknown)}; valid: {sorted(valid)}")
        return replace(self, **changes)


def _paper(frequency: float, name: str) -> Scenario:
    return Scenario(name=name, reference=ReferenceParams(frequency=frequency))


PRESETS: dict[str, Scenario] = {
    "paper-0.1hz": _paper(0.1, "paper-0.1hz"),
    "paper-0.5hz": _paper(0.5, "paper-0.5hz"),
}
"""The paper's two simulation cases (Section 4.2.1 and 4.2.2)."""


def preset(name: str, **sim_overrides: Any) -> Scenario:
    """The named paper preset, optionally with :class:`SimParams` fields replaced (e.g. ``dt``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; accepted values: {sorted(PRESETS)}")
    sc = PRESETS[name]
    if sim_overrides:
        sc = replace(sc, sim=replace(sc.sim, **sim_overrides))
    return sc
