"""The barrier filter (baselines/filters.py, docs/model.md section 11): what can be guaranteed.

(a) Properties of the filter function alone, by Hypothesis: its output is finite and inside the
    actuator box, the condition z2_hat^T r_f <= beta(m) holds to 1e-12, it is the identity when
    inactive, and theta is in [0, 1].
(b) Along filtered closed-loop runs (the kernel counts its monitors at every integration step): the
    condition never breaks, and no episode in which the guarantee's assumptions held throughout
    violates a bound. Episodes where an assumption failed are counted, and the test prints them.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from baselines.filters import BarrierFilterParams, barrier_apply, barrier_filter
from blf_gym.model.params import preset
from blf_gym.envs.scenarios import sample_suite
from blf_gym.kernel.simulate import simulate_batch

P = BarrierFilterParams()
UMAX = 150.0
CLIP = 0.95

torque = st.floats(-200.0, 200.0, allow_nan=False)
vec3 = lambda s: st.lists(s, min_size=3, max_size=3).map(np.array)  # noqa: E731


def _apply(r, u_law, z1, z2, ka, kb, p=P, innovation=None):
    out = {k: np.zeros(3 if k == "r_f" else 1) for k in ("r_f", "theta", "beta", "breach", "assumptions",
                                                          "handed_back")}
    zeros = np.zeros(3)
    x1_hat = zeros if innovation is None else -np.asarray(innovation, dtype=float)  # y = 0, so y - x1_hat = innovation
    barrier_apply(r, u_law, z1, z2, ka, kb, UMAX, p.beta_max, p.m0, p.m1, p.gain_max, p.e2_max, p.noise_fraction,
                  p.handback, CLIP, zeros, zeros, zeros, zeros, x1_hat, zeros, out["r_f"], out["theta"], out["beta"],
                  out["breach"], out["assumptions"], out["handed_back"])
    return out


def _margin(z1, ka, kb):
    return min((ka - e) / ka if e >= 0 else (kb + e) / kb for e in z1)


@settings(max_examples=400, deadline=None)
@given(vec3(torque), vec3(st.floats(-160.0, 160.0)), vec3(st.floats(-0.3, 0.3)), vec3(st.floats(-50.0, 50.0)),
       st.floats(0.01, 0.3), st.floats(0.01, 0.3))
def test_the_filter_keeps_its_condition_inside_the_box(r, u_law, z1, z2, ka, kb):
    out = _apply(r, u_law, z1, z2, ka, kb)
    rf, th, beta = out["r_f"], out["theta"][0], out["beta"][0]
    assert np.all(np.isfinite(rf)) and 0.0 <= th <= 1.0 and beta >= 0.0
    # inside the actuator box, unless u_law alone is outside it (then r_f = 0)
    if np.all(np.abs(u_law) < UMAX):
        assert np.all(np.abs(u_law + rf) <= UMAX * (1 + 1e-12))
    else:
        assert np.all(rf == 0.0)
    # the condition, to 1e-12, and the kernel's monitor agrees
    assert z2 @ rf <= beta + 1e-12 * max(1.0, beta)
    assert out["breach"][0] == 0.0
    # beta follows its ramp in the smallest margin, and the residual may not raise V2 below m0
    m = _margin(z1, ka, kb)
    rc = np.clip(u_law + r, -UMAX, UMAX) - u_law  # the residual clipped to the actuator box
    want = min(max((m - P.m0) / (P.m1 - P.m0), 0.0), 1.0) * max(P.beta_max, rc @ rc / P.gain_max)
    assert beta == pytest.approx(want, rel=1e-9, abs=1e-12)
    if m <= P.m0:
        assert np.all(rf == 0.0)


@settings(max_examples=300, deadline=None)
@given(vec3(st.floats(-5.0, 5.0)), vec3(st.floats(-100.0, 100.0)), vec3(st.floats(-0.005, 0.005)),
       vec3(st.floats(-0.05, 0.05)))
def test_the_filter_is_the_identity_when_inactive(r, u_law, z1, z2):
    # far from the bounds (margin >= m1), inside the box, within the budget: r_f is r, bit for bit
    ka = kb = 0.1
    assume(_margin(z1, ka, kb) >= P.m1)
    assume(z2 @ r <= P.beta_max)  # within the budget (which is at least beta_max)
    out = _apply(r, u_law, z1, z2, ka, kb)
    np.testing.assert_array_equal(out["r_f"], r)
    assert out["theta"][0] == 1.0


def test_the_filter_scales_a_residual_that_would_raise_v2():
    z1, z2 = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    r = np.array([20.0, 3.0, -3.0])
    out = _apply(r, np.zeros(3), z1, z2, 0.1, 0.1)
    # far from the bounds the budget is max(beta_max, |r|^2 / gain_max) = 418 / 5 = 83.6
    budget = max(P.beta_max, r @ r / P.gain_max)
    assert budget == pytest.approx(418.0 / 5.0)
    np.testing.assert_array_equal(out["r_f"], r)  # 20 < 83.6: within the budget, untouched
    z2 = np.array([10.0, 0.0, 0.0])  # z2^T r = 200 > 83.6: scaled onto the budget
    out = _apply(r, np.zeros(3), z1, z2, 0.1, 0.1)
    assert out["theta"][0] == pytest.approx(budget / 200.0)
    assert z2 @ out["r_f"] == pytest.approx(budget)
    # a residual that lowers V2 passes untouched
    out = _apply(np.array([-20.0, 3.0, -3.0]), np.zeros(3), z1, z2, 0.1, 0.1)
    np.testing.assert_array_equal(out["r_f"], [-20.0, 3.0, -3.0])


def test_the_hand_back_gives_the_law_control_while_the_innovation_is_above_its_limit():
    """The scaled case above: with the monitor at 3e-3 rad, an innovation of 2e-3 on every joint leaves
    r_f as with the monitor off (bit for bit); 4e-3 on one joint zeroes it, and says so."""
    z1, z2, r = np.zeros(3), np.array([10.0, 0.0, 0.0]), np.array([20.0, 3.0, -3.0])
    on = BarrierFilterParams(handback=3e-3)
    off = _apply(r, np.zeros(3), z1, z2, 0.1, 0.1)
    below = _apply(r, np.zeros(3), z1, z2, 0.1, 0.1, on, innovation=[2e-3, -2e-3, 2e-3])
    np.testing.assert_array_equal(below["r_f"], off["r_f"])
    assert below["handed_back"][0] == 0.0 and off["handed_back"][0] == 0.0
    above = _apply(r, np.zeros(3), z1, z2, 0.1, 0.1, on, innovation=[0.0, -4e-3, 0.0])
    np.testing.assert_array_equal(above["r_f"], np.zeros(3))
    assert above["handed_back"][0] == 1.0 and above["theta"][0] == 0.0 and above["breach"][0] == 0.0
    # off (0) never hands back, whatever the innovation
    assert _apply(r, np.zeros(3), z1, z2, 0.1, 0.1, innovation=[1.0, 1.0, 1.0])["handed_back"][0] == 0.0


def test_bad_filter_parameters_are_refused():
    for kw, field in (({"m0": 0.6, "m1": 0.5}, "m0"), ({"beta_max": -1.0}, "beta_max"), ({"e2_max": 0.0}, "e2_max"),
                      ({"handback": -1e-3}, "handback"),
                      ({"m0": float("nan")}, "m0"), ({"bogus": 1}, "bogus")):
        with pytest.raises(ValueError, match=field):
            barrier_filter(**kw)


# ---------------------------------------------------------------------------------------------
# (b) along filtered runs


def _episodes():
    base = preset("paper-0.1hz", duration=10.0)
    scs = [preset("paper-0.1hz", duration=10.0), preset("paper-0.5hz", duration=10.0)]
    scs += [sample_suite(np.random.default_rng(s), base, "randomized") for s in range(3)]
    scs += [sample_suite(np.random.default_rng(s), base, "stress") for s in range(3)]
    return scs


def _residuals(k: int) -> list[np.ndarray]:
    """Hostile constant residuals: every sign pattern at the residual's full 8 N m, and zero."""
    signs = [np.array([(p >> j) & 1 for j in range(3)]) * 2.0 - 1.0 for p in range(8)]
    return [np.zeros(3)] + [8.0 * s for s in signs][:k]


@pytest.mark.parametrize("pattern", range(9))
def test_filtered_runs_never_break_the_condition_nor_a_bound_where_the_assumptions_held(pattern):
    scs = _episodes()
    r = _residuals(8)[pattern]
    res = np.tile(r, (len(scs), 1))
    trajs = simulate_batch(scs, "proposed", residual=res, residual_filter="barrier", threads=1)
    held = failed = 0
    for sc, tr in zip(scs, trajs):
        assert tr.residual_filter == "barrier"
        assert tr.filter_breaches == 0, (sc.name, tr.filter_breaches)
        violated = tr.step_violations > 0 or tr.diverged
        if tr.assumption_failures == 0:
            held += 1
            assert not violated, f"{sc.name}: a violation with every assumption holding (residual {r})"
        else:
            failed += 1
    print(f"residual {r}: assumptions held throughout in {held} of {len(scs)} episodes, failed in {failed}")
    assert held >= 1  # the test would be empty otherwise
