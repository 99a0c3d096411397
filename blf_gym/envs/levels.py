"""Difficulty levels: the benchmark's scenarios with parts of their difficulty taken away.

A learner that fails the full task says little about why. The levels give a ladder, each a fixed
bundle of existing scenario knobs applied after a scenario is drawn, so that level ``L`` of a
preset, of training-suite episode ``k`` or of stress episode ``k`` is the same draw as at the full
benchmark with less taken from it:

====== ================================================================================
level  contents
====== ================================================================================
0      the nominal plant (no friction, no dead zone, no external force, no angle noise,
       the paper's payload, no initial error) inside bounds ``WIDE_BOUNDS`` times as wide
1      the scenario's plant and disturbances (friction, dead zone, payload, force, noise,
       initial error) inside bounds ``WIDE_BOUNDS`` times as wide
2      the scenario's bounds and plant without the external force
3      the full benchmark, the scenario as it is (the default; nothing is changed)
====== ================================================================================

The table in docs/levels.md is written from :data:`LEVELS` by ``python docs/tables.py``. The
reference trajectory, the period, the duration and the torque limit are never changed.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

from blf_gym.model.family import member_arm
from blf_gym.model.params import ArmParams, DeadZoneParams, Scenario, check_int
from blf_gym.envs.scenarios import widen_bounds

__all__ = ["DEFAULT_LEVEL", "LEVELS", "WIDE_BOUNDS", "Level", "apply_level", "check_level", "level_name"]

WIDE_BOUNDS = 10.0
"""The funnel's widening at levels 0 and 1: the paper's floors of 0.02 and 0.04 rad (1.1 and 2.3
degrees) become 0.2 and 0.4 rad (11 and 23 degrees), the width of the loose training funnel in
which plain PPO first tracked the 0.1 Hz preset's first 10 s (the issue's audit), and within
``blf_gym.envs.envcore.MAX_BOUND_SCALE`` (15)."""


def _widen(sc: Scenario) -> Scenario:
    return widen_bounds(sc, WIDE_BOUNDS)


def _no_force(sc: Scenario) -> Scenario:
    return replace(sc, force=replace(sc.force, wrench=(0.0, 0.0, 0.0)))


def _nominal(sc: Scenario) -> Scenario:
    """The plant the controllers' nominal model describes: no friction, an identity dead zone (unit
    slopes, no break points), the paper's masses (payload included; on another member of the task
    family, the member's), no force, no noise, starting on the reference."""
    member = member_arm(sc.arm)
    if sc.arm.n_links == len(ArmParams().masses):
        arm = replace(sc.arm, masses=ArmParams().masses)
    elif member is not None:  # a member of the task family, its payload drawn
        arm = replace(sc.arm, masses=member.masses)
    else:
        arm = sc.arm
    return replace(_no_force(sc), arm=arm, friction=replace(sc.friction, viscous=0.0, coulomb=0.0),
                   dead_zone=DeadZoneParams(slope_right=1.0, slope_left=1.0, break_right=0.0, break_left=0.0),
                   angle_noise_std=0.0, initial_error=(0.0,) * sc.arm.n_links)


@dataclass(frozen=True)
class Level:
    """One rung of the ladder: its number, a short name, what it keeps and what it changes, and the
    map from a drawn scenario to this level's."""

    number: int
    name: str
    plant: str
    bounds: str
    force: str
    apply: Callable[[Scenario], Scenario]


LEVELS: tuple[Level, ...] = (
    Level(0, "nominal", "nominal model (no friction, dead zone or noise; paper payload; e1(0) = 0)",
          f"{WIDE_BOUNDS:g}x wider", "off", lambda sc: _widen(_nominal(sc))),
    Level(1, "uncertain-wide", "the scenario's (friction, dead zone, payload, noise, e1(0))",
          f"{WIDE_BOUNDS:g}x wider", "the scenario's", _widen),
    Level(2, "no-force", "the scenario's", "the scenario's", "off", _no_force),
    Level(3, "full", "the scenario's", "the scenario's", "the scenario's", lambda sc: sc),
)
"""The levels, by number (see the module docstring)."""

DEFAULT_LEVEL = 3
"""The full benchmark: a scenario at this level is the scenario itself."""


def check_level(owner: str, value: object) -> int:
    """``value`` as a level number, or ValueError naming ``owner``'s ``level`` and the accepted range."""
    return check_int(owner, "level", value, lo=0, hi=len(LEVELS) - 1)


def apply_level(sc: Scenario, level: int) -> Scenario:
    """``sc`` at difficulty ``level`` (0 to 3; 3 returns ``sc`` itself), named with a ``@L<level>``
    suffix below level 3 so that records, titles and caches tell the levels apart."""
    level = check_level("apply_level", level)
    if level == DEFAULT_LEVEL:
        return sc
    out = LEVELS[level].apply(sc)
    return replace(out, name=f"{sc.name}@L{level}")


def level_name(level: int) -> str:
    """``"L<n> (<name>)"``, for tables and titles."""
    lv = LEVELS[check_level("level_name", level)]
    return f"L{lv.number} ({lv.name})"
