"""The task family: the paper's problem on planar arms of 2 to 7 links (docs/family.md).

The paper designs its law for an n-link arm and tests it on one 3-link arm. Every member of the
family keeps the paper's plant apart from the arm itself: the same friction, dead zone and external
force on every joint (they are per-joint models in the paper, eqs. 2-3), the same bounds on every
joint (Table 2's family), the same actuator limit and step. What changes with n:

* **The arm** (:func:`family_arm`): at n = 3 the paper's (Table 1). At other n, a chain of n
  identical modules, each the paper's average link (a third of its reach and of its mass:
  :data:`MODULE_LENGTH`, :data:`MODULE_MASS`), as a modular arm is built. Why modules rather than
  the paper's 0.80 m and 0.53 kg cut into n ever smaller pieces: the lightest mode of the arm (the
  smallest eigenvalue of M(q)) then stays near the paper's (8.6e-4 to 2.2e-3 kg m^2 against its
  9.3e-4) at every n, so the paper's friction and dead zone weigh on each joint as they do on the
  paper's, and the 0.1 ms step that integrates the paper's arm integrates every member. Cut into
  pieces, the 7-link arm's lightest mode is 40 times lighter (2.5e-5 kg m^2): the paper's friction
  alone then puts a pole near -1e5 1/s, outside ODE3's stability region at 0.1 ms, and its
  distal joints carry a gravity load of 0.03 N m under a dead zone of 0.2 N m. The price is
  reach: the modular arm reaches 0.27 n m, and the largest gravity torque at the base grows from
  1.4 N m (n = 2) to 12.9 N m (n = 7), and the 40 N force's from 21 to 75 N m, all inside the
  same 150 N m actuator limit (docs/family.md tabulates them).
* **The reference** (:func:`family_reference`): the paper's Cartesian circle is solved by 3-link
  inverse kinematics, so at n = 3 the family's presets *are* the paper's (``paper-0.1hz``,
  ``paper-0.5hz``). At other n each joint follows a sinusoid at the preset's frequency,
  :data:`FAMILY_AMPLITUDE` rad about the horizontal (no offset: the pose of largest gravity load),
  the joints' phases spread evenly over half a period so that the joints never all swing together.
  The paper's circle moves its first joint by 0.73 rad and the others by about 1.5 and 2.3 rad, at
  up to 0.52 rad/s at 0.1 Hz; 0.5 rad on every joint asks up to 0.31 rad/s at 0.1 Hz and 1.6 rad/s
  at 0.5 Hz.

Presets are named ``n{n}-{f}hz`` (``n5-0.1hz``) at n != 3; :func:`family_presets` lists them per n
and :func:`family_preset` builds one. The training and held-out suites of n are drawn by the same
rules around the member's 0.1 Hz preset (:func:`blf_gym.envs.scenarios.sample_suite` with that
base).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from blf_gym.model.params import PRESETS, ArmParams, ReferenceParams, Scenario, check_int, preset, with_sim

__all__ = ["PAPER_LINKS", "FAMILY_LINKS", "MODULE_LENGTH", "MODULE_MASS", "FAMILY_AMPLITUDE", "FAMILY_FREQUENCIES", "family_arm", "family_reference",
           "family_preset", "family_presets", "family_base", "preset_links", "member_arm", "check_n_links", "family_table"]

FAMILY_LINKS = (2, 3, 4, 5, 6, 7)
"""The family's numbers of links: the 2-link arm of most barrier-Lyapunov papers up to the 7 joints
of an industrial arm."""

MODULE_LENGTH = 0.2667
"""Each module's length at n != 3, m: the paper's reach (0.80 m) over its 3 links, to 0.1 mm."""

MODULE_MASS = 0.1767
"""Each module's point mass at n != 3, kg: the paper's mass (0.53 kg) over its 3 links, to 0.1 g."""

FAMILY_AMPLITUDE = 0.5
"""Amplitude of every joint's sinusoid at n != 3, rad."""

FAMILY_FREQUENCIES = (0.1, 0.5)
"""The reference frequencies of each member's two presets, Hz: the paper's two cases."""

_PAPER = ArmParams()

PAPER_LINKS = _PAPER.n_links
"""The paper's arm's links (3): the member whose presets are the paper's own."""


def check_n_links(owner: str, value: Any) -> int:
    """``value`` as a member of :data:`FAMILY_LINKS`, or ValueError naming ``n_links``."""
    return check_int(owner, "n_links", value, lo=FAMILY_LINKS[0], hi=FAMILY_LINKS[-1],
                     hint=" (the task family's arms; docs/family.md)")


def family_arm(n: int) -> ArmParams:
    """The family's arm of ``n`` links: the paper's own :class:`ArmParams` at n = 3, else n
    identical modules of :data:`MODULE_LENGTH` and :data:`MODULE_MASS` (module docstring)."""
    n = check_n_links("family_arm:", n)
    if n == _PAPER.n_links:
        return _PAPER
    return ArmParams(lengths=(MODULE_LENGTH,) * n, masses=(MODULE_MASS,) * n, gravity=_PAPER.gravity)


def member_arm(arm: ArmParams) -> ArmParams | None:
    """The family's arm that ``arm`` is a draw of (the same number of links and link lengths; its
    masses may carry a payload), or None for an arm outside the family."""
    n = arm.n_links
    if n not in FAMILY_LINKS:
        return None
    own = family_arm(n)
    return own if arm.lengths == own.lengths else None


def family_reference(n: int, frequency: float = 0.1) -> ReferenceParams:
    """The joint-space reference of the family's n-link arm (n != 3; the module docstring)."""
    n = check_n_links("family_reference:", n)
    return ReferenceParams(frequency=frequency, kind="joint", amplitudes=(FAMILY_AMPLITUDE,) * n,
                           phases=tuple(math.pi * j / n for j in range(n)), offsets=(0.0,) * n)


def family_presets(n: int) -> tuple[str, ...]:
    """The names of the presets of the n-link member, one per :data:`FAMILY_FREQUENCIES`: the
    paper's two at n = 3."""
    n = check_n_links("family_presets:", n)
    if n == _PAPER.n_links:
        return tuple(PRESETS)
    return tuple(f"n{n}-{f:g}hz" for f in FAMILY_FREQUENCIES)


def preset_links(name: str) -> int | None:
    """The number of links of a preset's name (3 for the paper's), None for a name that is no
    preset of the family."""
    if name in PRESETS:
        return _PAPER.n_links
    for n in FAMILY_LINKS:
        if n != _PAPER.n_links and name in family_presets(n):
            return n
    return None


def family_preset(name: str, **sim_overrides: Any) -> Scenario:
    """A preset of the family by name (``"n5-0.5hz"``, or the paper's ``"paper-0.1hz"``), with
    :class:`~blf_gym.model.params.SimParams` fields replaced as :func:`~blf_gym.model.params.preset`
    does."""
    n = preset_links(name) if isinstance(name, str) else None
    if n is None:
        names = [p for m in FAMILY_LINKS for p in family_presets(m)]
        raise ValueError(f"unknown preset {name!r}; accepted values: {names}")
    if n == _PAPER.n_links:
        return preset(name, **sim_overrides)
    frequency = FAMILY_FREQUENCIES[family_presets(n).index(name)]
    base = Scenario(name=name, arm=family_arm(n), reference=family_reference(n, frequency))
    return with_sim("family_preset", base, sim_overrides)


def family_base(n: int) -> Scenario:
    """The n-link member's base scenario, around which its suites are drawn: its 0.1 Hz preset."""
    return family_preset(family_presets(n)[0])


def family_table() -> list[dict[str, Any]]:
    """One row per member: links, lengths (m), masses (kg), reach (m), mass (kg), the largest
    gravity torque at joint 1 (arm horizontal, N m), the largest torque of the 40 N force at joint
    1 (arm vertical, N m), and the diagonal of the mass matrix at q = 0 (kg m^2): what docs/family.md
    tabulates."""
    rows = []
    for n in FAMILY_LINKS:
        arm = family_arm(n)
        ls, ms = np.asarray(arm.lengths), np.asarray(arm.masses)
        reach = np.cumsum(ls)  # distance of each mass from the base with the arm straight
        inertia = [float(np.sum(ms[j:] * (reach[j:] - (reach[j - 1] if j else 0.0)) ** 2)) for j in range(n)]
        rows.append({"n": n, "lengths": arm.lengths, "masses": arm.masses, "reach": float(ls.sum()),
                     "mass": float(ms.sum()), "gravity_torque": float(arm.gravity * np.sum(ms * reach)),
                     "force_torque": float(40.0 * ls.sum()), "inertia_q0": tuple(inertia)})
    return rows
