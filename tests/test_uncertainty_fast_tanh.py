"""The one-exp tanh used by the friction term (blf_gym.model.uncertainty._tanh).

It replaces libm's tanh inside the compiled kernel, so it must agree with numpy.tanh to a few
units of round-off in absolute terms (the friction term multiplies it by c = 0.2 N m) and be odd,
over the whole range the kernel can hand it: psi qd with psi = 10 and |qd| up to tens of rad/s.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from blf_gym.model.uncertainty import _tanh

ATOL = 3e-16


@njit(cache=True)
def _tanh_array(z, out):
    # _tanh is inline="always": this is how the kernel sees it (compiled, inlined into a loop)
    for i in range(z.shape[0]):
        out[i] = _tanh(z[i])


def _grid() -> np.ndarray:
    dense = np.linspace(-50.0, 50.0, 2_000_001)  # step 5e-5 through the whole transition region
    tiny = np.logspace(-12, -1, 2001)  # where 1 - exp(-2|z|) cancels
    mid = np.linspace(-3.0, 3.0, 600_001)  # where tanh bends: the largest rounding of the formula
    pos = np.concatenate([tiny, np.abs(mid), np.abs(dense), [1e-300, 5e-324, 18.0, 19.06, 20.0, 50.0]])
    return np.concatenate([pos, -pos, [0.0]])


def _compiled(z: np.ndarray) -> np.ndarray:
    out = np.empty_like(z)
    _tanh_array(np.ascontiguousarray(z), out)
    return out


def test_fast_tanh_matches_numpy_to_round_off():
    z = _grid()
    got = _compiled(z)
    err = np.abs(got - np.tanh(z))
    worst = int(np.argmax(err))
    assert err[worst] <= ATOL, f"|_tanh - tanh| = {err[worst]:.3e} at z = {z[worst]!r}"


def test_fast_tanh_tiny_arguments_are_absolutely_accurate():
    # For |z| << 1, tanh z = z - z^3/3 + ...; the cancelling formula loses relative accuracy but the
    # absolute error must still be round-off (the friction torque is absolute).
    z = np.array([1e-12, -1e-12, 3.7e-13, 1e-9, -1e-9, 1e-6, 2.5e-8])
    got = _compiled(z)
    np.testing.assert_allclose(got, z - z ** 3 / 3.0, rtol=0, atol=ATOL)


def test_fast_tanh_saturates_for_large_arguments():
    z = np.array([19.5, 25.0, 40.0, 50.0, 300.0, 800.0, 1e300, np.inf])
    # tanh(z) = 1 - 2 e^{-2z} + ...; already below half an ulp of 1 from z = 19.1 on
    np.testing.assert_array_equal(_compiled(z), 1.0)
    np.testing.assert_array_equal(_compiled(-z), -1.0)


def test_fast_tanh_is_odd():
    z = np.abs(_grid())
    np.testing.assert_array_equal(_compiled(-z), -_compiled(z))


def test_fast_tanh_called_from_python_agrees_with_the_compiled_loop():
    for v in (0.0, 1e-12, -0.3, 0.5493061443340549, 2.0, -7.5, 50.0):
        assert _tanh(v) == _compiled(np.array([v]))[0]
        assert abs(_tanh(v) - np.tanh(v)) <= ATOL
