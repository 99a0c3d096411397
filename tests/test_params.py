"""Parameter validation: invalid values raise ValueError naming the offending field."""

from __future__ import annotations

import dataclasses
import math

import pytest

from blf_gym.params import ArmParams, BoundParams, ReferenceParams, Scenario, SimParams, preset

# ---------------------------------------------------------------------------------------------
# ArmParams


@pytest.mark.parametrize("bad", [0.0, -0.3, math.nan, math.inf])
@pytest.mark.parametrize("index", [0, 2])
def test_arm_rejects_non_positive_lengths(bad, index):
    lengths = [0.35, 0.30, 0.15]
    lengths[index] = bad
    with pytest.raises(ValueError, match=rf"ArmParams\.lengths\[{index}\]"):
        ArmParams(lengths=tuple(lengths))


@pytest.mark.parametrize("bad", [0.0, -0.1, math.nan])
@pytest.mark.parametrize("index", [0, 1])
def test_arm_rejects_non_positive_masses(bad, index):
    masses = [0.23, 0.20, 0.10]
    masses[index] = bad
    with pytest.raises(ValueError, match=rf"ArmParams\.masses\[{index}\]"):
        ArmParams(masses=tuple(masses))


@pytest.mark.parametrize("masses", [(0.23, 0.20), (0.23, 0.20, 0.10, 0.05)])
def test_arm_rejects_mismatched_masses_length(masses):
    with pytest.raises(ValueError, match=r"ArmParams\.masses"):
        ArmParams(lengths=(0.35, 0.30, 0.15), masses=masses)


def test_arm_rejects_negative_gravity():
    with pytest.raises(ValueError, match=r"ArmParams\.gravity"):
        ArmParams(gravity=-9.81)


def test_arm_accepts_other_link_counts():
    arm = ArmParams(lengths=(0.5, 0.4), masses=(1.0, 2.0))
    assert arm.n_links == 2 and arm.pack().shape == (5,)


# ---------------------------------------------------------------------------------------------
# SimParams


@pytest.mark.parametrize("dt", [0.0, -1e-4, math.nan])
def test_sim_rejects_non_positive_dt(dt):
    with pytest.raises(ValueError, match=r"SimParams\.dt"):
        SimParams(dt=dt)


@pytest.mark.parametrize("dt", [3e-4, 7e-5, 1.5e-3, 2e-3])
def test_sim_rejects_dt_not_dividing_1ms(dt):
    # 1 ms / dt must be a whole number >= 1 (metrics are sampled on a 1 ms grid, SPEC 6).
    with pytest.raises(ValueError, match=r"SimParams\.dt"):
        SimParams(dt=dt)


@pytest.mark.parametrize("dt", [1e-3, 5e-4, 2.5e-4, 1e-4, 5e-5, 1e-5])
def test_sim_accepts_divisors_of_1ms(dt):
    sim = SimParams(dt=dt)
    assert sim.steps_per_sample == round(1e-3 / dt)


# ---------------------------------------------------------------------------------------------
# Scenario


@pytest.mark.parametrize(
    "e0, index",
    [
        ((0.52, 0.0, 0.0), 0),  # k_a(0) = 0.5 + 0.02: the open interval excludes the bound
        ((0.0, -0.64, 0.0), 1),  # -k_b(0) = -(0.6 + 0.04)
        ((0.0, 0.0, 1.0), 2),
        ((0.0, 0.0, -2.0), 2),
    ],
)
def test_scenario_rejects_initial_error_outside_bounds(e0, index):
    with pytest.raises(ValueError, match=rf"Scenario\.initial_error\[{index}\]"):
        Scenario(initial_error=e0)


def test_scenario_accepts_initial_error_just_inside_bounds():
    sc = Scenario(initial_error=(0.519, -0.639, 0.0))
    assert sc.initial_error == (0.519, -0.639, 0.0)


def test_scenario_initial_error_follows_the_bound_parameters():
    # 0.3 is inside the paper's bounds but outside k_a(0) = 0.2 + 0.02.
    tight = BoundParams(upper_amplitude=0.2)
    with pytest.raises(ValueError, match=r"Scenario\.initial_error\[0\]"):
        Scenario(bounds=tight, initial_error=(0.3, 0.0, 0.0))


def test_scenario_rejects_wrong_initial_error_length():
    with pytest.raises(ValueError, match=r"Scenario\.initial_error"):
        Scenario(initial_error=(0.0, 0.0))


# ---------------------------------------------------------------------------------------------
# Presets and the reference branch


@pytest.mark.parametrize("name", ["paper-1hz", "paper", "", "PAPER-0.1HZ"])
def test_unknown_preset_name(name):
    with pytest.raises(ValueError, match="preset"):
        preset(name)


@pytest.mark.parametrize("name, f", [("paper-0.1hz", 0.1), ("paper-0.5hz", 0.5)])
def test_known_presets(name, f):
    sc = preset(name)
    assert sc.name == name and sc.reference.frequency == f and sc.reference.branch == "smooth"


def test_preset_sim_overrides_are_validated():
    assert preset("paper-0.1hz", dt=5e-5).sim.dt == 5e-5
    with pytest.raises(ValueError, match=r"SimParams\.dt"):
        preset("paper-0.1hz", dt=3e-4)


@pytest.mark.parametrize("branch", ["elbow-up", "Smooth", "", None])
def test_unknown_reference_branch(branch):
    with pytest.raises(ValueError, match=r"ReferenceParams\.branch"):
        ReferenceParams(branch=branch)
    # Also through dataclasses.replace, the way callers switch branches.
    sc = preset("paper-0.1hz")
    with pytest.raises(ValueError, match=r"ReferenceParams\.branch"):
        dataclasses.replace(sc.reference, branch=branch)
