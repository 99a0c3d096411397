"""Scenario variations and the randomized suite.

A *variation* changes the paper's plant or task through a few named knobs, each with a unit and
a documented safe range (inside which the default 0.1 ms step stays stable with the paper's
gains; outside it the run may be reported as diverged, never silently wrong):

============================  ======  ================  ==========================================
knob                          unit    safe range        meaning
============================  ======  ================  ==========================================
``frequency``                 Hz      [0.05, 0.5]       reference circle frequency f
``force``                     N       [0, 60]           magnitude of f_ext along +x (paper: 40)
``force_onset``               s       [0, 30]           switch-on time of f_ext (paper: 20)
``friction_scale``            -       [0.5, 2.0]        multiplies viscous b and Coulomb c
``dead_zone_scale``           -       [0.5, 2.0]        multiplies both break points tau_r, tau_l
``payload``                   kg      [0.08, 0.3]       point mass m3 at the end effector (0.10)
``initial_error``             rad     |e| <= 0.1        e1(0) per joint (3 values or one for all)
``angle_noise_std``           rad     [0, 2e-4]         measurement noise on the angles
============================  ======  ================  ==========================================

Payloads lighter than about 0.08 kg make the true M33 so small that the closed loop's fastest mode
leaves ODE3's stability region at h = 0.1 ms: such runs are reported as diverged. The ranges are
safe for the paper's controllers; in plain mode with termination off, large actions can spin the
arm up until the run diverges, which is reported the same way.

The **randomized suite** (``"randomized"``) draws each knob uniformly from :data:`SUITE_RANGES`
with a caller-supplied ``numpy.random.Generator``; the controller's nominal model stays the
paper's, and that mismatch is the point.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Mapping

import numpy as np

from .params import PRESETS, ArmParams, Scenario, preset

__all__ = ["VARIATIONS", "SAFE_RANGES", "SUITE_RANGES", "apply_variations", "sample_suite",
           "resolve_scenario", "SUITES"]

VARIATIONS = ("frequency", "force", "force_onset", "friction_scale", "dead_zone_scale", "payload",
              "initial_error", "angle_noise_std")

SAFE_RANGES: dict[str, tuple[float, float]] = {
    "frequency": (0.05, 0.5),
    "force": (0.0, 60.0),
    "force_onset": (0.0, 30.0),
    "friction_scale": (0.5, 2.0),
    "dead_zone_scale": (0.5, 2.0),
    "payload": (0.08, 0.3),
    "initial_error": (-0.1, 0.1),
    "angle_noise_std": (0.0, 2e-4),
}
"""Documented ranges; values outside raise ValueError (pass ``strict=False`` to allow them)."""

SUITE_RANGES: dict[str, tuple[float, float]] = {
    "frequency": (0.1, 0.5),
    "force": (0.0, 60.0),
    "force_onset": (5.0, 25.0),
    "friction_scale": (0.5, 1.5),
    "dead_zone_scale": (0.5, 1.5),
    "payload": (0.08, 0.2),
    "initial_error": (-0.02, 0.02),
    "angle_noise_std": (0.0, 1e-4),
}
"""Uniform ranges of the randomized suite (a subset of :data:`SAFE_RANGES`)."""

SUITES = ("randomized",)


def _check(name: str, value: float, strict: bool) -> None:
    lo, hi = SAFE_RANGES[name]
    if not np.isfinite(value):
        raise ValueError(f"variation {name!r} must be finite, got {value!r}")
    if strict and not (lo <= value <= hi):
        raise ValueError(f"variation {name!r}={value!r} is outside its safe range [{lo}, {hi}] "
                         "(see blf_gym.scenarios). To run it anyway, build the Scenario with "
                         "blf_gym.scenarios.apply_variations(scenario, {...}, strict=False) and pass "
                         "it as scenario=")


def apply_variations(base: Scenario, variations: Mapping[str, Any], strict: bool = True) -> Scenario:
    """``base`` with the named knobs of :data:`VARIATIONS` applied."""
    unknown = set(variations) - set(VARIATIONS)
    if unknown:
        raise ValueError(f"unknown variation(s) {sorted(unknown)}; accepted: {list(VARIATIONS)}")
    sc = base
    v = dict(variations)
    if "frequency" in v:
        _check("frequency", float(v["frequency"]), strict)
        sc = replace(sc, reference=replace(sc.reference, frequency=float(v["frequency"])))
    if "force" in v or "force_onset" in v:
        wrench = sc.force.wrench
        onset = sc.force.onset
        if "force" in v:
            _check("force", float(v["force"]), strict)
            wrench = (float(v["force"]), 0.0, 0.0)
        if "force_onset" in v:
            _check("force_onset", float(v["force_onset"]), strict)
            onset = float(v["force_onset"])
        sc = replace(sc, force=replace(sc.force, wrench=wrench, onset=onset))
    if "friction_scale" in v:
        s = float(v["friction_scale"])
        _check("friction_scale", s, strict)
        sc = replace(sc, friction=replace(sc.friction, viscous=sc.friction.viscous * s,
                                          coulomb=sc.friction.coulomb * s))
    if "dead_zone_scale" in v:
        s = float(v["dead_zone_scale"])
        _check("dead_zone_scale", s, strict)
        sc = replace(sc, dead_zone=replace(sc.dead_zone, break_right=sc.dead_zone.break_right * s,
                                           break_left=sc.dead_zone.break_left * s))
    if "payload" in v:
        m = float(v["payload"])
        _check("payload", m, strict)
        masses = list(sc.arm.masses)
        masses[-1] = m
        sc = replace(sc, arm=ArmParams(lengths=sc.arm.lengths, masses=tuple(masses), gravity=sc.arm.gravity))
    if "initial_error" in v:
        e = np.broadcast_to(np.asarray(v["initial_error"], dtype=float), (sc.arm.n_links,))
        for x in e:
            _check("initial_error", float(x), strict)
        sc = replace(sc, initial_error=tuple(float(x) for x in e))
    if "angle_noise_std" in v:
        _check("angle_noise_std", float(v["angle_noise_std"]), strict)
        sc = replace(sc, angle_noise_std=float(v["angle_noise_std"]))
    return sc


def sample_suite(rng: np.random.Generator, base: Scenario | None = None, name: str = "randomized") -> Scenario:
    """Draw one scenario of the randomized suite from ``rng`` (the only source of randomness)."""
    if name not in SUITES:
        raise ValueError(f"unknown suite {name!r}; accepted: {list(SUITES)}")
    base = base if base is not None else preset("paper-0.1hz")
    draws: dict[str, Any] = {}
    for knob in VARIATIONS:
        lo, hi = SUITE_RANGES[knob]
        if knob == "initial_error":
            draws[knob] = tuple(float(x) for x in rng.uniform(lo, hi, size=base.arm.n_links))
        else:
            draws[knob] = float(rng.uniform(lo, hi))
    sc = apply_variations(base, draws)
    return replace(sc, name=name)


def resolve_scenario(spec: "str | Scenario") -> tuple[Scenario, str | None]:
    """(base scenario, suite name or None) for a preset name, a suite name or a Scenario."""
    if isinstance(spec, Scenario):
        return spec, None
    if spec in SUITES:
        return preset("paper-0.1hz"), spec
    if spec in PRESETS:
        return preset(spec), None
    raise ValueError(f"unknown scenario {spec!r}; accepted: {sorted(PRESETS) + list(SUITES)} "
                     "or a blf_gym.params.Scenario")
