"""The kernel's own elementary functions (blf_gym.jit.vmath) against NumPy's, which call the C library.

The bounds asserted are the ones the module's docstring and docs/model.md state: 1 ulp for sin,
cos, exp and acos, 2 ulp for atan2, and the special values (NaN, infinities, underflow to 0 and to
subnormals) as the C library gives them (tanh: tests/test_uncertainty_fast_tanh.py). A wrong coefficient, a reduction that drops a term or a
wrong quadrant breaks these by many ulp.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from blf_gym.jit import vmath


@njit(cache=True, error_model="numpy")
def _apply(kind, x, y, out):
    for i in range(x.shape[0]):
        if kind == 0:
            out[i] = vmath.sincos(x[i])[0]
        elif kind == 1:
            out[i] = vmath.sincos(x[i])[1]
        elif kind == 2:
            out[i] = vmath.exp(x[i])
        elif kind == 3:
            out[i] = vmath.acos(x[i])
        else:
            out[i] = vmath.atan2(x[i], y[i])


_KINDS = {"sin": (0, np.sin, 1), "cos": (1, np.cos, 1), "exp": (2, np.exp, 1), "acos": (3, np.arccos, 1),
          "atan2": (4, np.arctan2, 2)}


def _ours(name, x, y=None):
    x = np.ascontiguousarray(x, dtype=float)
    out = np.empty_like(x)
    _apply(_KINDS[name][0], x, x if y is None else np.ascontiguousarray(y, float), out)
    return out


def _ulp_error(got, ref):
    fin = np.isfinite(ref)
    assert np.array_equal(np.isfinite(got), fin)
    np.testing.assert_array_equal(got[~fin], ref[~fin])
    return np.abs(got[fin] - ref[fin]) / np.spacing(np.abs(ref[fin]))


def _samples(name, rng):
    if name in ("sin", "cos"):
        return [rng.uniform(-4, 4, 100_000), rng.uniform(-200, 200, 100_000), rng.uniform(-1e6, 1e6, 20_000),
                np.arange(-200, 201) * (np.pi / 2), np.array([0.0, -0.0, 1e-300, 5e-324])]
    if name == "exp":
        return [rng.uniform(-2, 2, 100_000), rng.uniform(-746, 710, 100_000),
                np.array([0.0, -0.0, 1e-300, -708.4, -744.4, -745.1, 709.7])]
    if name == "acos":
        return [rng.uniform(-1, 1, 100_000), 1 - np.logspace(-16, 0, 2000), -1 + np.logspace(-16, 0, 2000),
                np.array([-1.0, -0.5, 0.0, 0.5, 1.0])]
    return []


@pytest.mark.parametrize("name", ["sin", "cos", "exp", "acos"])
def test_within_one_ulp_of_the_c_library(name):
    rng = np.random.default_rng(0)
    fn = _KINDS[name][1]
    for x in _samples(name, rng):
        with np.errstate(over="ignore"):
            ref = fn(x)
        err = _ulp_error(_ours(name, x), ref)
        assert err.max() <= 1.0, (name, err.max())


def test_atan2_within_two_ulp_in_every_octant():
    rng = np.random.default_rng(1)
    ang = rng.uniform(-np.pi, np.pi, 200_000)
    rad = np.exp(rng.uniform(-20, 20, ang.size))
    x, y = rad * np.cos(ang), rad * np.sin(ang)
    axes = np.array([1.0, -1.0, 0.0, 0.0, 1.0, -1.0, 2.0, -3.0])
    x = np.concatenate([x, axes, np.array([1.0, 1.0, -1.0, -1.0])])
    y = np.concatenate([y, axes[::-1], np.array([1.0, -1.0, 1.0, -1.0])])
    err = _ulp_error(_ours("atan2", y, x), np.arctan2(y, x))
    assert err.max() <= 2.0, err.max()


def test_special_values():
    inf, nan = np.inf, np.nan
    s = _ours("sin", [inf, -inf, nan])
    c = _ours("cos", [inf, -inf, nan])
    assert np.isnan(s).all() and np.isnan(c).all()
    np.testing.assert_array_equal(_ours("exp", [-inf, -800.0, 800.0, inf]), [0.0, 0.0, inf, inf])
    assert np.isnan(_ours("exp", [nan]))[0]
    sub = _ours("exp", [-740.0])[0]
    assert 0.0 < sub < np.finfo(float).tiny and sub == np.exp(-740.0)
    assert np.isnan(_ours("acos", [1.0 + 1e-15, -2.0, nan])).all()
    assert np.isnan(_ours("atan2", [nan, 1.0], [1.0, nan])).all()


def test_atan2_keeps_the_sign_of_a_zero_y():
    # C's atan2 reads y's sign bit: atan2(-0, -1) = -pi, atan2(-0, 1) = -0 (C99 Annex F.9.1.4)
    y = np.array([0.0, -0.0, 0.0, -0.0, 0.0, -0.0])
    x = np.array([-1.0, -1.0, 1.0, 1.0, -1e300, 1e-300])
    ours = _ours("atan2", y, x)
    np.testing.assert_array_equal(ours, np.arctan2(y, x))
    assert (np.signbit(ours) == np.signbit(y)).all()


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e5, 1e5))
def test_sin_cos_hypothesis(x):
    s, c = _ours("sin", [x])[0], _ours("cos", [x])[0]
    assert abs(s - np.sin(x)) <= np.spacing(abs(np.sin(x))) and abs(c - np.cos(x)) <= np.spacing(abs(np.cos(x)))


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6))
def test_atan2_hypothesis(y, x):
    if x == 0.0 and y == 0.0:
        return
    ref = np.arctan2(y, x)
    assert abs(_ours("atan2", [y], [x])[0] - ref) <= 2 * np.spacing(abs(ref))
