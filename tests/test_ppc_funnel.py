"""The prescribed-performance and funnel controllers (docs/model.md sections 12-13): the analytic
rate of PPC's virtual velocity against finite differences, and on the nominal plant (no friction,
dead-zone or force; the controller's model is the plant) the property each one claims: the error
stays inside its bounds (PPC) or inside its funnel (funnel control) from a start well off the
reference."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from baselines.funnel import FunnelGains, funnel
from baselines.ppc import ppc, ppc_output
from blf_gym.plugins.blocks import nominal_length
from blf_gym.model.params import DeadZoneParams, ForceParams, FrictionParams, preset
from blf_gym.kernel.simulate import simulate_batch


def _signals(t):
    """Smooth test signals at time t: a reference, bounds shaped like the paper's and an error that
    stays well inside them, with their exact derivatives (the error's from sympy-free algebra)."""
    ka, kad, kadd = 0.5 * np.exp(-0.6 * t) + 0.02, -0.3 * np.exp(-0.6 * t), 0.18 * np.exp(-0.6 * t)
    kb, kbd, kbdd = 0.6 * np.exp(-0.6 * t) + 0.04, -0.36 * np.exp(-0.6 * t), 0.216 * np.exp(-0.6 * t)
    w = np.array([1.0, 2.0, 3.0])
    q_d, qd_d, qdd_d = np.sin(w * t), w * np.cos(w * t), -w * w * np.sin(w * t)
    a = np.array([0.4, -0.5, 0.6])  # e = a * k(t) * cos(2t) with k the bound on the error's side
    c, cd = np.cos(2 * t), -2 * np.sin(2 * t)
    e = np.where(a * c >= 0, a * c * ka, a * c * kb)
    ed = np.where(a * c >= 0, a * (cd * ka + c * kad), a * (cd * kb + c * kbd))
    return q_d + e, qd_d + ed, q_d, qd_d, qdd_d, (ka, kad, kadd, kb, kbd, kbdd)


def _ppc_alpha(t, K1):
    y, v, q_d, qd_d, qdd_d, k = _signals(t)
    work = np.zeros(64)
    out = [np.zeros(3) for _ in range(4)]
    ppc_output.py_func(y, v, np.zeros(3), q_d, qd_d, qdd_d, *k, K1, np.ones(3), 0.95, np.zeros(nominal_length(3)),
                       work, *out)
    return work[:3].copy(), work[3:6].copy(), out[3].copy(), y - q_d, k


@pytest.mark.parametrize("t", [0.05, 0.7, 1.3, 4.0])
def test_ppc_virtual_velocity_rate_matches_finite_differences(t):
    K1 = np.array([20.0, 20.0, 15.0])
    a1, a1d, eps, e, (ka, _, _, kb, _, _) = _ppc_alpha(t, K1)
    h = 1e-6
    fd = (_ppc_alpha(t + h, K1)[0] - _ppc_alpha(t - h, K1)[0]) / (2 * h)
    np.testing.assert_allclose(a1d, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    # the transformed error is 0 on the reference, odd in the normalised error and grows without
    # bound at either bound: here as its definition, from the error and the bounds
    np.testing.assert_allclose(eps, np.log((e + kb) / (ka - e)) - np.log(kb / ka), rtol=1e-12)


def _nominal_plant(initial_error, duration=3.0):
    sc = preset("paper-0.1hz")
    return dataclasses.replace(
        sc, friction=FrictionParams(viscous=0.0, coulomb=0.0),
        dead_zone=DeadZoneParams(slope_right=1.0, slope_left=1.0, break_right=0.0, break_left=0.0),
        force=ForceParams(wrench=(0.0, 0.0, 0.0)), initial_error=tuple(initial_error),
        sim=dataclasses.replace(sc.sim, duration=duration))


def test_ppc_keeps_a_large_initial_error_inside_the_bounds_on_the_nominal_plant():
    ka0, kb0 = 0.52, 0.64
    starts = [(0.9 * ka0, -0.9 * kb0, 0.5 * ka0), (-0.8 * kb0, 0.8 * ka0, -0.9 * kb0)]
    trajs = simulate_batch([_nominal_plant(s) for s in starts], ppc())
    for tr in trajs:
        e, ka, kb = tr.signals["e1"], tr.signals["k_a"], tr.signals["k_b"]  # (samples, joints)
        assert not tr.diverged
        assert np.all((e < ka) & (e > -kb))
        # and the error converges: in the last second it is a small fraction of the bounds
        late = tr.signals["t"] > 2.0
        assert np.abs(e[late]).max() < 0.05 * ka[late].min()


def test_funnel_keeps_the_error_in_its_funnel_on_the_nominal_plant():
    # a start inside the funnel whose inner level is feasible too: |e0| = 0.49, a(|e0|^2) |e0| = 0.64 < 1
    psi0 = 0.52
    starts = [(0.3 * psi0, -0.3 * psi0, 0.25 * psi0), (-0.35 * psi0, 0.2 * psi0, -0.3 * psi0)]
    trajs = simulate_batch([_nominal_plant(s) for s in starts], funnel())
    for tr in trajs:
        e = tr.signals["e1"]
        psi = np.minimum(tr.signals["k_a"], tr.signals["k_b"])[:, 0]  # the same bounds on every joint
        assert not tr.diverged
        assert np.all(np.linalg.norm(e, axis=1) < psi)  # |e0| < 1: inside the funnel, so inside the bounds


@pytest.mark.parametrize("make, kwargs, field", [
    (ppc, {"K1": (1.0, 2.0)}, "K1"), (ppc, {"K2": (1.0, -2.0, 3.0)}, "K2"), (ppc, {"barrier_clip": 1.0}, "barrier_clip"),
    (funnel, {"k_u": 0.0}, "k_u"), (funnel, {"k_e": float("nan")}, "k_e"), (funnel, {"funnel_clip": 1.0}, "funnel_clip"),
    (funnel, {"feedforward": 2.0}, "feedforward"), (funnel, {"gain": 1.0}, "gain")])
def test_bad_gains_are_refused_by_name(make, kwargs, field):
    with pytest.raises(ValueError, match=field):
        make(**kwargs)


def test_funnel_gains_carry_units():
    assert {f.name: f.metadata.get("unit") for f in dataclasses.fields(FunnelGains) if f.name != "nominal"} == {
        "k_e": "1/s", "k_u": "rad/s^2", "funnel_clip": "-", "feedforward": "-"}
