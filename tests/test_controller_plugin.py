"""The controller plug-in protocol of blf_gym.controller, as a user would use it.

A user's own law is written below at module level with ``@numba.njit(cache=True)`` and the
documented signature, wrapped as an ``InnerController`` and run in the compiled closed loop.
This file is the example the blf_gym.controller docstring points to.
"""

from __future__ import annotations

import subprocess
import sys

import numba
import numpy as np
import pytest

from blf_gym.controller import InnerController, available_controllers, make_controller
from blf_gym.params import ArmParams, preset
from blf_gym.simulate import simulate

KP, KD = 50.0, 1.0  # N m/rad, N m s/rad


@numba.njit(cache=True)
def pd_gravity_law(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u_out, work):
    """u = -Kp (y - q_d) - Kd (x2_hat - qd_d) + G(y), with G(y) read from the shared model array.

    Output feedback only: the angles y and the observer's velocity estimate, never qd_true.
    """
    n = y.shape[0]
    nn = n * n
    for i in range(n):
        # model = [M(y) (n*n), G(y) (n), cos (n), sin (n), LDL^T factor of M (n*n)]
        u_out[i] = -gains[0] * (y[i] - ref[i]) - gains[1] * (xhat[n + i] - ref[n + i]) + model[nn + i]


def _gravity_by_hand(q: np.ndarray, arm: ArmParams = ArmParams()) -> np.ndarray:
    """G(q) = dV/dq for point masses at the distal link ends (docs/model.md section 1), one config per row.

    V = g sum_i m_i y_i with y_i = sum_{j<=i} l_j sin(theta_j), theta_j = q_1 + ... + q_j, so
    dV/dq_k = g sum_{j>=k} l_j cos(theta_j) sum_{i>=j} m_i.
    """
    l, m, g = np.array(arm.lengths), np.array(arm.masses), arm.gravity
    theta = np.cumsum(q, axis=-1)
    mass_beyond = np.cumsum(m[::-1])[::-1]
    terms = g * l * mass_beyond * np.cos(theta)
    return np.cumsum(terms[..., ::-1], axis=-1)[..., ::-1]


@pytest.fixture(scope="module")
def runs():
    sc = preset("paper-0.1hz", duration=2.0)
    mine = InnerController("mypd", pd_gravity_law, np.array([KP, KD]))
    return simulate(sc, controller=mine), simulate(sc, controller="proposed")


def test_gravity_by_hand_matches_a_two_link_textbook_formula():
    # n = 2: G1 = (m1 + m2) g l1 c1 + m2 g l2 c12, G2 = m2 g l2 c12
    arm = ArmParams(lengths=(0.7, 0.4), masses=(1.5, 0.8), gravity=9.81)
    q = np.array([0.3, -1.1])
    c1, c12 = np.cos(0.3), np.cos(0.3 - 1.1)
    want = [(1.5 + 0.8) * 9.81 * 0.7 * c1 + 0.8 * 9.81 * 0.4 * c12, 0.8 * 9.81 * 0.4 * c12]
    np.testing.assert_allclose(_gravity_by_hand(q, arm), want, rtol=1e-14)


def test_user_law_runs_in_the_closed_loop(runs):
    mine, _ = runs
    assert not mine.diverged, mine.message
    assert mine.controller == "mypd"
    assert mine.t.shape == (2000,)
    assert np.all(np.isfinite(mine.u))
    assert not np.any(mine.saturated)


def test_recorded_torque_is_the_users_formula(runs):
    mine, _ = runs
    k = np.array([0, 1, 7, 250, 999, 1500, 1999])
    y, q_ref, qd_ref, x2_hat = mine.y[k], mine.q_ref[k], mine.qd_ref[k], mine.x2_hat[k]
    want = -KP * (y - q_ref) - KD * (x2_hat - qd_ref) + _gravity_by_hand(y)
    np.testing.assert_allclose(mine.u_law[k], want, rtol=0, atol=1e-9)
    # no residual and no clipping: the commanded torque is the law's
    np.testing.assert_array_equal(mine.u[k], mine.u_law[k])
    # at t = 0 the arm starts on the reference at rest and the observer at [q(0), 0, 0], so the
    # law's output is -Kd * (0 - qd_d(0)) + G(q(0))
    assert mine.t[0] == 0.0
    np.testing.assert_allclose(mine.x2_hat[0], 0.0, atol=0)
    np.testing.assert_allclose(mine.u_law[0], KD * mine.qd_ref[0] + _gravity_by_hand(mine.q[0]), atol=1e-9)


def test_user_pd_tracks_worse_than_the_proposed_law(runs):
    mine, proposed = runs
    rmse_mine = np.sqrt(np.mean(mine.e1 ** 2, axis=0))
    rmse_prop = np.sqrt(np.mean(proposed.e1 ** 2, axis=0))
    assert np.all(rmse_mine > rmse_prop), (np.degrees(rmse_mine), np.degrees(rmse_prop))
    assert rmse_mine.mean() > 2.0 * rmse_prop.mean()


def test_make_controller_passes_an_object_through_and_rejects_unknown_names():
    mine = InnerController("mypd", pd_gravity_law, [KP, KD])
    assert make_controller(mine) is mine
    assert mine.gains.dtype == np.float64 and mine.gains.tolist() == [KP, KD]
    with pytest.raises(ValueError) as exc:
        make_controller("nonexistent")
    msg = str(exc.value)
    assert "nonexistent" in msg
    for name in ("bc", "lesobc", "proposed", "none"):
        assert repr(name) in msg, name


def test_registered_controllers_are_available():
    names = available_controllers()
    for name in ("bc", "lesobc", "proposed", "none"):
        assert name in names
        assert isinstance(make_controller(name), InnerController)
    assert make_controller("bc").full_state is True
    assert make_controller("proposed").full_state is False


def test_inner_controller_requires_a_compiled_law():
    def plain(t, y, qd_true, xhat, ref, bnd, nominal, model, gains, u_out, work):
        u_out[:] = 0.0

    with pytest.raises(ValueError, match="njit"):
        InnerController("plain", plain, [1.0])
    with pytest.raises(ValueError, match="njit"):
        InnerController("lam", lambda *a: None, [1.0])
    with pytest.raises(ValueError, match="finite"):
        InnerController("nan", pd_gravity_law, [np.nan, 1.0])


def test_blf_gym_does_not_import_controllers_or_learning_libraries():
    code = ("import blf_gym, blf_gym.simulate, blf_gym.metrics, blf_gym.controller, sys; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
            "('baselines', 'agents', 'torch', 'stable_baselines3')); "
            "assert not bad, bad")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr


def test_blf_reproduce_module_does_not_import_torch():
    # baselines.reproduce's docstring: torch and stable-baselines3 are never imported on this path
    code = ("import baselines.reproduce, sys; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('agents', 'torch', 'stable_baselines3')); "
            "assert not bad, bad")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
