"""The block declarations and the nominal-model operators of blf_gym.plugins.blocks.

The operators are checked against blf_gym.model.dynamics' NumPy functions, which tests/test_dynamics.py
checks against Pinocchio; the published law outputs against the paper's definitions recomputed
from the loop's own state.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from blf_gym.plugins.blocks import (PLANT, coriolis_times, gravity, mass_solve, mass_times, model_length, nominal_length,
                            nominal_model_into, size_of, units, work_length)
from blf_gym.model.bounds import BOUND_SIGNALS, KA, KB
from blf_gym.plugins.registry import available_controllers, available_observers, make_controller, make_observer
from blf_gym.model.dynamics import coriolis_matrix, gravity as gravity_np, mass_matrix
from blf_gym.model.params import ArmParams, preset
from blf_gym.model.reference import joint_reference
from blf_gym.kernel.simulate import ClosedLoop


def test_every_block_declares_states_and_unit_carrying_parameters():
    assert dict(PLANT.states) == {"q": "n", "qd": "n"} and PLANT.inputs == ("u",)
    for cls in PLANT.params:
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen
        for f in dataclasses.fields(cls):
            assert f.metadata.get("unit"), f"{cls.__name__}.{f.name} carries no unit"
    for name in available_controllers():
        c = make_controller(name)
        assert "u_law" in c.outputs
        if c.params is not None:
            assert all(units(c.params).values()), name
    for name in available_observers():
        o = make_observer(name)
        assert o.states and all(units(o.params).values()), name
    assert units(make_controller("proposed").params) == {"K1": "1/s", "K2": "N m s/rad", "barrier_clip": "-"}


def test_sizes():
    assert [size_of(s, 3, "x") for s in (0, 4, "n", "2n", "3*n", " 4 n ")] == [0, 4, 3, 6, 9, 12]
    for bad in (-1, "m", "n2", 1.5, True, None):
        with pytest.raises(ValueError, match="size"):
            size_of(bad, 3, "x")


def nominal_signal(y, arm=ArmParams()):
    """The ``nominal`` signal a plug-in reads at the measured angles ``y`` (also tests/test_classical.py's)."""
    n = y.shape[0]
    nom = np.zeros(nominal_length(n))
    nominal_model_into(y, arm.pack(), nom, np.zeros(work_length(n)))
    nom[model_length(n) : model_length(n) + 2 * n + 1] = arm.pack()
    return nom


angles = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)
vectors = st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(angles, vectors, vectors)
def test_operators_match_the_model_at_the_measured_angles(y, v, w):
    nom = nominal_signal(y)
    out = np.zeros(3)
    M = mass_matrix(y)
    mass_times(nom, w, out)
    np.testing.assert_allclose(out, M @ w, rtol=1e-12, atol=1e-12)
    mass_solve(nom, w, out)
    np.testing.assert_allclose(M @ out, w, rtol=1e-9, atol=1e-9)
    coriolis_times(nom, v, w, out)
    np.testing.assert_allclose(out, coriolis_matrix(y, v) @ w, rtol=1e-10, atol=1e-10)
    gravity(nom, out)
    np.testing.assert_allclose(out, gravity_np(y), rtol=1e-12, atol=1e-12)


def test_the_proposed_law_publishes_its_signals():
    sc = preset("paper-0.1hz", duration=1.0)
    loop = ClosedLoop([sc], "proposed")
    loop.advance(1234, record_samples=0)
    # the outputs are those of the last step's first stage, at its start state
    steps = int(loop.ksteps[0]) - 1
    loop2 = ClosedLoop([sc], "proposed")
    loop2.advance(steps, record_samples=0)
    x = loop2.X[0].copy()
    t = steps * sc.sim.dt
    out = loop.outputs()
    n = 3
    q_d, qd_d, _ = (np.asarray(a) for a in joint_reference(t, sc))
    z1 = x[:n] - q_d
    np.testing.assert_allclose(out["z1"][0], z1, rtol=0, atol=1e-15)
    # z2_hat = x2_hat - alpha1, alpha1 = qd_d - (K1 + lambda1) z1 (paper eq. 18)
    bnd = np.zeros(len(BOUND_SIGNALS))
    from blf_gym.model.bounds import bounds_into

    bounds_into(t, sc.bounds.pack(), bnd)
    lam = np.hypot(bnd[1] / bnd[KA], bnd[4] / bnd[KB])
    alpha1 = qd_d - (np.array([20.0, 20.0, 15.0]) + lam) * z1
    x2_hat = x[2 * n + n : 2 * n + 2 * n]
    np.testing.assert_allclose(out["z2_hat"][0], x2_hat - alpha1, rtol=1e-12, atol=1e-12)
    k = np.where(z1 > 0, bnd[KA], bnd[KB])
    np.testing.assert_allclose(out["barrier"][0], z1 / (k ** 2 - z1 ** 2), rtol=1e-12)
