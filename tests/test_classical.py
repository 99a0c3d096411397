"""The classical baselines (baselines/classical.py) against independent references: computed torque
is Pinocchio's inverse dynamics (RNEA) of the commanded acceleration on the nominal arm, PD with
gravity compensation is Pinocchio's gravity torque plus the PD terms; the LESO variants subtract the
disturbance estimate as an acceleration (M x3_hat as a torque); bad gains are refused by name; each
runs in the closed loop as a registered plug-in."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from baselines.classical import (CTCGains, PDGains, computed_torque_leso_output, computed_torque_output,
                                 pd_gravity_leso_output, pd_gravity_output)
from blf_gym.plugins.blocks import work_length
from blf_gym.model.params import ArmParams

from test_blocks import nominal_signal  # noqa: E402 (the shared helper of the operator tests)

pin = pytest.importorskip("pinocchio", reason="Pinocchio (pip package 'pin') is not importable")


def _pinocchio(arm: ArmParams):
    """The point-mass planar arm (docs/model.md section 2) as a Pinocchio model."""
    model = pin.Model()
    parent, offset = 0, 0.0
    for i, (li, mi) in enumerate(zip(arm.lengths, arm.masses)):
        parent = model.addJoint(parent, pin.JointModelRZ(), pin.SE3(np.eye(3), np.array([offset, 0.0, 0.0])),
                                f"j{i}")
        model.appendBodyToJoint(parent, pin.Inertia(mi, np.array([li, 0.0, 0.0]), np.zeros((3, 3))),
                                pin.SE3.Identity())
        offset = li
    model.gravity.linear = np.array([0.0, -arm.gravity, 0.0])
    return model, model.createData()


vec = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)
gains = st.lists(st.floats(1.0, 3000.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(vec, vec, vec, vec, vec, vec, gains, gains)
def test_computed_torque_is_inverse_dynamics_of_the_commanded_acceleration(y, v, q_d, qd_d, qdd_d, x3, Kp, Kd):
    arm = ArmParams()
    model, data = _pinocchio(arm)
    nom = nominal_signal(y, arm)
    a = qdd_d - Kd * (v - qd_d) - Kp * (y - q_d)
    u = np.zeros(3)
    computed_torque_output.py_func(y, v, q_d, qd_d, qdd_d, Kp, Kd, nom, np.zeros(work_length(3)), u)
    np.testing.assert_allclose(u, pin.rnea(model, data, y, v, a), rtol=1e-9, atol=1e-8)
    # on the LESO: the estimated disturbance leaves the commanded acceleration
    computed_torque_leso_output.py_func(y, v, x3, q_d, qd_d, qdd_d, Kp, Kd, nom, np.zeros(work_length(3)), u)
    np.testing.assert_allclose(u, pin.rnea(model, data, y, v, a - x3), rtol=1e-9, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(vec, vec, vec, vec, vec, gains, gains)
def test_pd_with_gravity_compensation(y, v, q_d, qd_d, x3, Kp, Kd):
    arm = ArmParams()
    model, data = _pinocchio(arm)
    nom = nominal_signal(y, arm)
    g = pin.computeGeneralizedGravity(model, data, y)
    u = np.zeros(3)
    pd_gravity_output.py_func(y, v, q_d, qd_d, Kp, Kd, nom, u)
    np.testing.assert_allclose(u, g - Kp * (y - q_d) - Kd * (v - qd_d), rtol=1e-9, atol=1e-8)
    pd_gravity_leso_output.py_func(y, v, x3, q_d, qd_d, Kp, Kd, nom, u)
    M = pin.crba(model, data, y)
    M = np.triu(M) + np.triu(M, 1).T
    np.testing.assert_allclose(u, g - Kp * (y - q_d) - Kd * (v - qd_d) - M @ x3, rtol=1e-9, atol=1e-8)


@pytest.mark.parametrize("cls,field,bad", [(PDGains, "Kp", 0.0), (PDGains, "Kd", -1.0), (CTCGains, "Kp", np.nan),
                                           (CTCGains, "Kd", (1.0, 2.0))])
def test_bad_gains_are_refused_by_name(cls, field, bad):
    with pytest.raises(ValueError, match=f"{cls.__name__}.{field}"):
        cls(**{field: bad})


@pytest.mark.parametrize("name", ["pd_gravity", "pd_gravity_leso", "computed_torque", "computed_torque_leso",
                                  "proposed_tuned"])
def test_each_runs_in_the_closed_loop_and_keeps_the_preset_in_bounds(name):
    """Registered through the entry points and compiled as any plug-in; with their chosen gains
    none breaks a bound on the first 2 s of the 0.1 Hz preset (the start is where a bad sign or a
    missing gravity term shows at once; docs/gains/*/gains.md list the selection episodes each keeps)."""
    from blf_gym.model.params import preset
    from blf_gym.kernel.simulate import simulate_batch

    # two arms: the batch build, the one blf-eval compiles for every registered controller anyway
    traj = simulate_batch([preset("paper-0.1hz", duration=2.0)] * 2, name, noise_seeds=[0, 0], threads=1)[0]
    assert not traj.diverged
    assert np.all(traj.e1 < traj.k_a) and np.all(traj.e1 > -traj.k_b)
