"""The CBF-QP filter (docs/model.md section 14): its closed form against OSQP on the same QP, the
second-order condition it enforces, the infeasible cases it counts, and its use through the env in
residual and plain mode."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401
from baselines.cbf import CBFFilterParams, cbf_apply, cbf_filter
from blf_gym.plugins.blocks import model_length, nominal_length, nominal_model_into, work_length
from blf_gym.model.dynamics import coriolis_matrix, gravity as gravity_vector, mass_matrix
from blf_gym.model.params import ArmParams


def _nominal(y, arm=ArmParams()):
    nom = np.zeros(nominal_length(3))
    nominal_model_into(y, arm.pack(), nom, np.zeros(work_length(3)))
    nom[model_length(3) : model_length(3) + 7] = arm.pack()
    return nom


def _case(rng, u_max=1e6, k_a_dot=None):
    """Random signals near the paper's ranges: angles, estimates, a reference, bounds, a law torque
    and a residual large enough that the condition is often active."""
    y = rng.uniform(-2.5, 2.5, 3)
    ka, kb = rng.uniform(0.02, 0.5), rng.uniform(0.04, 0.6)
    e = rng.uniform(-0.9, 0.9, 3) * np.where(rng.random(3) < 0.5, ka, kb)
    s = dict(y=y, x2_hat=rng.normal(0, 2, 3), x3_hat=rng.normal(0, 20, 3), q_d=y - e, qd_d=rng.normal(0, 2, 3),
             qdd_d=rng.normal(0, 10, 3), k_a=ka, k_a_dot=-0.6 * (ka - 0.02) if k_a_dot is None else k_a_dot,
             k_a_ddot=0.36 * (ka - 0.02), k_b=kb, k_b_dot=-0.6 * (kb - 0.04), k_b_ddot=0.36 * (kb - 0.04))
    return s, rng.normal(0, 10, 3), rng.normal(0, 30, 3), u_max


def _run(s, u_law, residual, u_max, p=CBFFilterParams(), x1_hat=None):
    out = [np.zeros(3), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1)]
    # the monitors' true state is the measured one here (q_true = y, qd_true = x2_hat); the observer's
    # x1_hat is y (no innovation) unless given
    x1_hat = s["y"] if x1_hat is None else x1_hat
    cbf_apply.py_func(residual, u_law, s["y"], s["x2_hat"], s["x3_hat"], s["q_d"], s["qd_d"], s["qdd_d"], s["k_a"],
                      s["k_a_dot"], s["k_a_ddot"], s["k_b"], s["k_b_dot"], s["k_b_ddot"], u_max, p.gamma1, p.gamma2,
                      p.e2_max, p.noise_fraction, p.handback, s["y"], s["x2_hat"], x1_hat, _nominal(s["y"]),
                      np.zeros(64), *out)
    return out


def _bounds(s, p=CBFFilterParams()):
    """The acceleration bounds of the two second-order conditions, written from h_a = k_a - e and
    h_b = k_b + e directly (h'' + c1 h' + c0 h >= 0 with e'' = qdd - qdd_d)."""
    c1, c0 = p.gamma1 + p.gamma2, p.gamma1 * p.gamma2
    e, ed = s["y"] - s["q_d"], s["x2_hat"] - s["qd_d"]
    ha, hb = s["k_a"] - e, s["k_b"] + e
    hi = s["qdd_d"] + s["k_a_ddot"] + c1 * (s["k_a_dot"] - ed) + c0 * ha
    lo = s["qdd_d"] - s["k_b_ddot"] - c1 * (s["k_b_dot"] + ed) - c0 * hb
    return lo, hi


def _accel(s, u):
    """The acceleration a torque asks for, from the model of blf_gym.model.dynamics (not the filter's
    LDL^T operators) and the observer's disturbance estimate."""
    M = mass_matrix(s["y"])
    return np.linalg.solve(M, u - coriolis_matrix(s["y"], s["x2_hat"]) @ s["x2_hat"] - gravity_vector(s["y"])) + s["x3_hat"]


def test_the_closed_form_is_the_qp_solution_osqp_finds():
    osqp = pytest.importorskip("osqp")
    import scipy.sparse as sp

    rng = np.random.default_rng(0)
    p = CBFFilterParams(gamma1=400.0, gamma2=400.0)  # the default rates: the condition is active in part of the draws
    active = 0
    for _ in range(40):
        s, u_law, r, u_max = _case(rng)
        r_f, act, infeasible, breach, _, _ = _run(s, u_law, r, u_max, p)
        lo, hi = _bounds(s, p)
        assert infeasible[0] == 0 and breach[0] == 0
        Minv = np.linalg.inv(mass_matrix(s["y"]))
        a_law = _accel(s, u_law)
        # the QP: min |M^-1 (x - r)|^2 s.t. lo - a_law <= M^-1 x <= hi - a_law
        P = Minv.T @ Minv
        solver = osqp.OSQP()
        solver.setup(sp.csc_matrix(2 * P), -2 * P @ r, sp.csc_matrix(Minv), lo - a_law, hi - a_law,
                     eps_abs=1e-11, eps_rel=1e-11, max_iter=200000, polishing=True, verbose=False)
        sol = solver.solve(raise_error=True)
        assert sol.info.status == "solved"
        np.testing.assert_allclose(r_f, sol.x, rtol=1e-5, atol=1e-5 * max(1.0, np.abs(sol.x).max()))
        a = _accel(s, u_law + r_f)
        tol = 1e-8 * np.maximum(1.0, np.abs(np.r_[lo, hi])).max()
        assert np.all(a <= hi + tol) and np.all(a >= lo - tol)  # the condition holds
        active += act[0] > 0
    assert 5 <= active <= 35  # both cases were exercised


def test_inactive_it_is_the_identity():
    rng = np.random.default_rng(1)
    s, u_law, _, u_max = _case(rng)
    lo, hi = _bounds(s)
    a = _accel(s, u_law)
    assert np.all((a > lo) & (a < hi))
    r_f, act, *_ = _run(s, u_law, np.zeros(3), u_max)
    assert act[0] == 0 and np.array_equal(r_f, np.zeros(3))


def test_the_hand_back_passes_the_laws_command_while_the_innovation_is_above_its_limit():
    """A case where the condition is active: with the monitor at 3e-3 rad an innovation of 2e-3
    changes nothing (bit for bit against the monitor off); 4e-3 on one joint gives r_f = 0, no
    activity and no breach counted, and says so."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        s, u_law, r, u_max = _case(rng)
        if _run(s, u_law, r, u_max)[1][0] > 0:
            break
    on = CBFFilterParams(handback=3e-3)
    off = _run(s, u_law, r, u_max)
    assert off[1][0] > 0  # the condition is active here
    below = _run(s, u_law, r, u_max, on, x1_hat=s["y"] - 2e-3)
    for a, b in zip(below, off):
        np.testing.assert_array_equal(a, b)
    r_f, act, infeasible, breach, _, handed_back = _run(s, u_law, r, u_max, on, x1_hat=s["y"] + [0.0, 4e-3, 0.0])
    np.testing.assert_array_equal(r_f, np.zeros(3))
    assert act[0] == 0 and infeasible[0] == 0 and breach[0] == 0 and handed_back[0] == 1


def test_the_infeasible_cases_are_handled_and_counted():
    rng = np.random.default_rng(2)
    # a torque limit that stops the filter: the limit wins, the stage is counted, the guarantee's
    # assumption monitor reads 0 (so the kernel counts it), and it is not called a breach
    hits = 0
    for _ in range(40):
        s, u_law, r, _ = _case(rng)
        r = 50 * r
        out = _run(s, u_law, r, 1e6, CBFFilterParams(gamma1=20.0, gamma2=20.0))
        if out[1][0] == 0:
            continue
        u_max = float(np.abs(u_law).max()) + 1e-3  # barely any room left beyond the law
        r_f, act, infeasible, breach, assumptions, _ = _run(s, u_law, r, u_max, CBFFilterParams(gamma1=20.0, gamma2=20.0))
        assert np.all(np.abs(u_law + r_f) <= u_max + 1e-9)
        lo, hi = _bounds(s, CBFFilterParams(gamma1=20.0, gamma2=20.0))
        a = _accel(s, u_law + r_f)
        if np.any(a > hi + 1e-6) or np.any(a < lo - 1e-6):
            assert infeasible[0] == 1 and assumptions[0] == 0 and breach[0] == 0
            hits += 1
    assert hits >= 3
    # bounds closing faster than the rates allow: lower above upper on every joint; the joint's
    # acceleration goes to the middle and the stage is counted
    s, u_law, r, u_max = _case(rng, u_max=1e12, k_a_dot=-1e5)
    lo, hi = _bounds(s)
    assert np.all(lo > hi)
    r_f, act, infeasible, breach, assumptions, _ = _run(s, u_law, r, u_max)
    assert infeasible[0] == 1 and assumptions[0] == 0 and breach[0] == 0
    np.testing.assert_allclose(_accel(s, u_law + r_f), 0.5 * (lo + hi), rtol=1e-7)


def test_it_is_offered_beside_the_barrier_filter_in_residual_and_plain_mode():
    env = gym.make("PlanarBLFResidual-v0", residual_filter="cbf", duration=0.3)
    env.reset(seed=0)
    for _ in range(30):
        _, _, _, trunc, info = env.step(np.ones(3, dtype=np.float32))
    assert set(info["filter_outputs"]) == {"r_f", "active", "infeasible", "breach", "assumptions", "handed_back"}
    np.testing.assert_allclose(info["u"], np.clip(info["u_law"] + info["filter_outputs"]["r_f"], -150, 150),
                               rtol=0, atol=1e-12)
    assert trunc and info["episode_metrics"]["filter_breaches"] == 0
    # plain mode: a policy that commands no torque lets the arm fall out of the bounds at once.
    # Through the filter, the condition is met on the estimated state; the arm still leaves the
    # bounds once the observer's velocity error outgrows the monitor's e2_max in the fall, and the
    # monitor says so before the first violation (the guarantee's assumption failed first).
    kw = dict(duration=2.0, terminate_on_violation=False)
    raw = gym.make("PlanarBLF-v0", **kw)
    raw.reset(seed=0)
    raw_cost = sum(raw.step(np.zeros(3, dtype=np.float32))[4]["cost"] for _ in range(200))
    env = gym.make("PlanarBLF-v0", residual_filter="cbf", **kw)
    env.reset(seed=0)
    first_violation = first_failure = None
    cost = 0.0
    for k in range(200):
        info = env.step(np.zeros(3, dtype=np.float32))[4]
        cost += info["cost"]
        if first_failure is None and info["filter_outputs"]["assumptions"][0] == 0:
            first_failure = k
        if first_violation is None and info["cost"] > 0:
            first_violation = k
    assert raw_cost > 100 and cost < raw_cost
    assert first_violation is None or (first_failure is not None and first_failure <= first_violation)


@pytest.mark.parametrize("kwargs, field", [({"gamma1": 0.0}, "gamma1"), ({"gamma2": float("inf")}, "gamma2"),
                                           ({"e2_max": -1.0}, "e2_max"), ({"noise_fraction": 1.0}, "noise_fraction"),
                                           ({"handback": -1e-3}, "handback"),
                                           ({"gamma": 1.0}, "gamma")])
def test_bad_parameters_are_refused_by_name(kwargs, field):
    with pytest.raises(ValueError, match=field):
        cbf_filter(**kwargs)
