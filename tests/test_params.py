"""Parameter validation: invalid values raise ValueError naming the offending field."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from blf_gym.model.params import (
    ArmParams,
    BoundParams,
    DeadZoneParams,
    ForceParams,
    FrictionParams,
    ReferenceParams,
    Scenario,
    SimParams,
    preset,
)

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
    # 1 ms / dt must be a whole number >= 1 (metrics are sampled on a 1 ms grid, docs/model.md section 6).
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


# ---------------------------------------------------------------------------------------------
# Types: booleans are not numbers, strings are neither; numpy scalars are numbers

# (class, field, lower end, lower end excluded, upper end)
REAL_FIELDS = [
    (ArmParams, "gravity", 0.0, False, None),
    (FrictionParams, "viscous", 0.0, False, None),
    (FrictionParams, "coulomb", 0.0, False, None),
    (FrictionParams, "tanh_slope", 0.0, True, None),
    (DeadZoneParams, "slope_right", 0.0, True, None),
    (DeadZoneParams, "slope_left", 0.0, True, None),
    (DeadZoneParams, "break_right", 0.0, False, None),
    (DeadZoneParams, "break_left", None, False, 0.0),
    (ForceParams, "onset", 0.0, False, None),
    (ReferenceParams, "frequency", 0.0, True, None),
    (ReferenceParams, "radius", 0.0, True, None),
    (ReferenceParams, "orientation", None, False, None),
    (BoundParams, "upper_amplitude", 0.0, False, None),
    (BoundParams, "upper_floor", 0.0, True, None),
    (BoundParams, "lower_amplitude", 0.0, False, None),
    (BoundParams, "lower_floor", 0.0, True, None),
    (BoundParams, "decay_rate", 0.0, False, None),
    (SimParams, "dt", 1e-7, False, 1e-3),
    (SimParams, "duration", 0.0, True, None),
    (SimParams, "sample_period", 1e-7, False, None),
    (SimParams, "max_torque", 0.0, True, None),
    (SimParams, "divergence_limit", 0.0, True, None),
    (SimParams, "error_rtol", 0.0, True, None),
    (SimParams, "error_atol", 0.0, True, None),
    (Scenario, "angle_noise_std", 0.0, False, None),
]
# (class, field, length)
SEQUENCE_FIELDS = [
    (ArmParams, "masses", 3),
    (ForceParams, "wrench", 3),
    (ReferenceParams, "center", 2),
    (Scenario, "initial_error", 3),
]

NOT_A_NUMBER = (st.sampled_from([True, False, np.True_, None, "1", "0.1", "nan", 1j, np.complex128(1.0),
                                 [0.1], (0.1,), np.array([0.1]), {}])
                | st.text(max_size=4) | st.sampled_from([math.nan, math.inf, -math.inf, np.float64("nan")]))


def _bad_real(lo, lo_open, hi):
    s = NOT_A_NUMBER
    if lo is not None:
        s = s | st.floats(max_value=lo, exclude_max=not lo_open, allow_nan=False)
    if hi is not None:
        s = s | st.floats(min_value=hi, exclude_min=True, allow_nan=False)
    return s


@pytest.mark.parametrize("cls, name, lo, lo_open, hi", REAL_FIELDS,
                         ids=[f"{c.__name__}.{n}" for c, n, *_ in REAL_FIELDS])
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_property_every_real_field_refuses_bad_values_naming_it(cls, name, lo, lo_open, hi, data):
    value = data.draw(_bad_real(lo, lo_open, hi))
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.{name}\b.*must"):
        cls(**{name: value})


@pytest.mark.parametrize("cls, name, length", SEQUENCE_FIELDS,
                         ids=[f"{c.__name__}.{n}" for c, n, _ in SEQUENCE_FIELDS])
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_property_every_sequence_field_refuses_bad_values_naming_it(cls, name, length, data):
    good = st.floats(-1e-3, 1e-3) if name == "initial_error" else st.floats(0.01, 0.02)
    bad_entry = NOT_A_NUMBER.filter(lambda v: not isinstance(v, float) or math.isfinite(v) is False)
    value = data.draw(
        NOT_A_NUMBER | st.floats(allow_nan=False)  # a scalar is not a sequence
        | st.lists(good, max_size=6).filter(lambda v: len(v) != length)
        | st.tuples(st.integers(0, length - 1), bad_entry).map(
            lambda ib: [ib[1] if i == ib[0] else 0.01 for i in range(length)]))
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.{name}\b"):
        cls(**{name: value})


@pytest.mark.parametrize("value", [0, -1, 1.0, 100.0, True, "100", None, np.float64(5.0), 1j])
def test_unstable_steps_must_be_an_integer(value):
    with pytest.raises(ValueError, match=r"SimParams\.unstable_steps must be an integer >= 1"):
        SimParams(unstable_steps=value)


@pytest.mark.parametrize("name, value", [("name", 3), ("name", None), ("arm", "arm"), ("sim", None),
                                         ("bounds", {}), ("reference", 0.1)])
def test_scenario_fields_must_have_their_types(name, value):
    with pytest.raises(ValueError, match=rf"Scenario\.{name} must be"):
        Scenario(**{name: value})


def test_lengths_must_be_a_non_empty_sequence_of_positive_numbers():
    for bad in ((), "0.35", 0.35, (0.35, True, 0.15), (0.35, "0.3", 0.15)):
        with pytest.raises(ValueError, match=r"ArmParams\.lengths"):
            ArmParams(lengths=bad)


def test_numpy_scalars_and_arrays_are_numbers():
    sim = SimParams(dt=np.float64(1e-4), duration=np.int64(2), max_torque=np.float32(100.0),
                    unstable_steps=np.int64(50))
    assert (sim.dt, sim.duration, sim.max_torque, sim.unstable_steps) == (1e-4, 2.0, 100.0, 50)
    assert all(type(v) is float for v in (sim.dt, sim.duration, sim.max_torque))
    assert type(sim.unstable_steps) is int
    arm = ArmParams(lengths=np.array([0.35, 0.30, 0.15]), masses=[np.float64(0.23), 0.2, np.float32(0.1)],
                    gravity=10)
    assert arm.lengths == (0.35, 0.30, 0.15) and arm.gravity == 10.0
    sc = Scenario(initial_error=np.array([0.01, 0.0, -0.01]), angle_noise_std=np.float64(1e-4))
    assert sc.initial_error == (0.01, 0.0, -0.01)
    assert ForceParams(wrench=np.array([1, 2, 3])).wrench == (1.0, 2.0, 3.0)


def test_preset_refuses_unknown_sim_overrides_and_bad_names():
    with pytest.raises(ValueError, match="dtt"):
        preset("paper-0.1hz", dtt=1e-4)
    for bad in (["paper-0.1hz"], None, 1):
        with pytest.raises(ValueError, match="preset"):
            preset(bad)
