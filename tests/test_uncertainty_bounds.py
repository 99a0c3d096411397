"""Tests of the input dead-zone (paper eq. 3) and the time-varying error bounds (eq. 17).

docs/model.md section 1: H(tau) = 1.0 (tau - 0.2) for tau >= 0.2, 0 inside (-0.2, 0.2), 1.2 (tau + 0.2)
for tau <= -0.2. docs/model.md section 3: k_a = 0.5 e^{-0.6 t} + 0.02, k_b = 0.6 e^{-0.6 t} + 0.04.
"""

from __future__ import annotations

import numpy as np
import pytest

from blf_gym.model.bounds import BOUND_LEN, bounds_into, error_bounds
from blf_gym.model.params import BoundParams
from blf_gym.model.uncertainty import dead_zone, dead_zone_array

# ---------------------------------------------------------------------------------------------
# Dead-zone


def test_dead_zone_is_zero_inside_the_break_points():
    tau = np.linspace(-0.2, 0.2, 1001)  # the closed interval: H(+-0.2) = 0 from either formula
    np.testing.assert_array_equal(dead_zone_array(tau), 0.0)


def test_dead_zone_slopes_outside():
    right = np.linspace(0.2, 50.0, 1001)
    left = np.linspace(-50.0, -0.2, 1001)
    # Straight from docs/model.md's formula; one multiply and one subtract per value, so round-off only.
    np.testing.assert_allclose(dead_zone_array(right), 1.0 * (right - 0.2), rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(dead_zone_array(left), 1.2 * (left + 0.2), rtol=1e-15, atol=1e-15)
    # Slopes measured by differences well away from the break points.
    for a, b, slope in ((1.0, 3.0, 1.0), (-3.0, -1.0, 1.2)):
        ha, hb = dead_zone_array(np.array([a, b]))
        assert (hb - ha) / (b - a) == pytest.approx(slope, rel=1e-12)
    # Asymmetry: the same overshoot gives 20% more torque on the left.
    assert dead_zone_array(-1.2) == pytest.approx(-1.2 * dead_zone_array(1.2), rel=1e-12)


def test_dead_zone_is_continuous_and_monotone():
    for brk in (-0.2, 0.2):
        for eps in (1e-6, 1e-9, 1e-12):
            lo, hi = dead_zone_array(np.array([brk - eps, brk + eps]))
            # The largest slope is 1.2, so H changes by at most 1.2 * 2 eps across a break point.
            assert abs(hi - lo) <= 1.2 * 2 * eps * (1 + 1e-9) + 1e-17
    tau = np.linspace(-3, 3, 60001)
    assert np.all(np.diff(dead_zone_array(tau)) >= 0.0)


def test_dead_zone_array_shape_and_scalar_kernel_agree():
    tau = np.random.default_rng(0).uniform(-2, 2, (4, 5))
    out = dead_zone_array(tau)
    assert out.shape == tau.shape
    # The compiled scalar used by the closed loop gives the same numbers.
    scalar = np.vectorize(lambda x: dead_zone(x, 1.0, 1.2, 0.2, -0.2))(tau)
    np.testing.assert_array_equal(out, scalar)


# ---------------------------------------------------------------------------------------------
# Error bounds


def test_error_bounds_equal_paper_table_2():
    t = np.linspace(0.0, 30.0, 3001)
    ka, kb = error_bounds(t)
    np.testing.assert_allclose(ka, 0.5 * np.exp(-0.6 * t) + 0.02, rtol=1e-14, atol=0)
    np.testing.assert_allclose(kb, 0.6 * np.exp(-0.6 * t) + 0.04, rtol=1e-14, atol=0)
    # Spot values: t = 0 is the sum of amplitude and floor; t -> inf the floor.
    ka0, kb0 = error_bounds(0.0)
    assert (float(ka0), float(kb0)) == pytest.approx((0.52, 0.64), abs=1e-15)
    kaI, kbI = error_bounds(1e4)
    assert (float(kaI), float(kbI)) == pytest.approx((0.02, 0.04), abs=1e-15)


def _bounds(t, bp):
    out = np.empty(BOUND_LEN)
    bounds_into(t, bp, out)
    return out


@pytest.mark.parametrize(
    "params",
    [BoundParams(), BoundParams(upper_amplitude=0.3, upper_floor=0.05, lower_amplitude=1.1,
                                lower_floor=0.01, decay_rate=2.0)],
    ids=["paper", "other"],
)
def test_compiled_bounds_values_and_derivatives(params):
    bp = params.pack()
    h = 1e-5
    for t in np.linspace(0.0, 10.0, 41):
        ka, dka, ddka, kb, dkb, ddkb = _bounds(t, bp)
        # Values equal the NumPy helper (and hence the closed form tested above).
        ref_a, ref_b = error_bounds(t, params)
        assert ka == pytest.approx(float(ref_a), rel=1e-14)
        assert kb == pytest.approx(float(ref_b), rel=1e-14)
        # First derivatives from central differences of the values, second from central
        # differences of the first derivatives. Truncation h^2/6 |k'''| = h^2/6 r^3 A <= 2e-10
        # (r <= 2, A <= 1.1) and round-off eps / h ~ 1e-11: 1e-8 absolute is safe and far below any O(r) error.
        vp, vm = _bounds(t + h, bp), _bounds(t - h, bp)
        fd = (vp - vm) / (2 * h)
        assert dka == pytest.approx(fd[0], abs=1e-8)
        assert dkb == pytest.approx(fd[3], abs=1e-8)
        assert ddka == pytest.approx(fd[1], abs=1e-8)
        assert ddkb == pytest.approx(fd[4], abs=1e-8)
        # Second derivatives also directly from second differences of the values
        # (round-off eps / h^2 needs a larger h: H = 1e-3 gives truncation H^2/12 r^4 A <= 2e-6).
        H = 1e-3
        a3 = _bounds(t + H, bp), _bounds(t, bp), _bounds(t - H, bp)
        dd = (a3[0] - 2 * a3[1] + a3[2]) / H**2
        assert ddka == pytest.approx(dd[0], abs=1e-5)
        assert ddkb == pytest.approx(dd[3], abs=1e-5)


def test_bounds_strictly_positive_and_decreasing():
    bp = BoundParams().pack()
    vals = np.array([_bounds(t, bp) for t in np.linspace(0, 30, 301)])
    assert np.all(vals[:, 0] > 0.02) and np.all(vals[:, 3] > 0.04)
    assert np.all(vals[:, 1] < 0) and np.all(vals[:, 4] < 0)  # decreasing
    assert np.all(vals[:, 2] > 0) and np.all(vals[:, 5] > 0)  # convex
