"""Elementary functions the closed loop's compiler can vectorise across arms.

The batched kernel (:mod:`blf_gym.kernel.simulate`) steps blocks of arms with the same entry of
neighbouring arms side by side in memory, so that one loop over the arms runs on vector registers.
A call into the C maths library (``np.sin``, ``np.exp``...) cannot be vectorised (llvmlite has no
vector maths library here), and it would keep the plant's trigonometry, the reference and the bounds
scalar. These functions are written as straight-line arithmetic with selects instead of branches,
which LLVM vectorises.

Every path of the closed loop uses them (the single env, the vector env, the reproduction, the
evaluation), through the plant's link angles (:func:`blf_gym.model.dynamics.abs_trig_into`), the reference
(:func:`blf_gym.model.reference.reference_into`), the bounds and the friction. A block of 4 arms
evaluates them on vector registers, and one arm alone evaluates its 2n + 1 sines and cosines and
its n + 1 exponentials of a stage in one vector loop each, so a batch and single arms compute the
same function of the same argument and agree bit for bit. Against the C library they differ in
last bits: below 1 ulp for ``sincos``, ``exp`` and ``acos`` and below 2 ulp for ``atan2``
(``tests/test_vmath.py`` checks them against NumPy), so a run differs from one with the C
library by round-off (docs/model.md gives the measured size).

The polynomial and rational coefficients and the split constants of pi/2 and ln 2 are the published
ones of Sun's fdlibm (``k_sin.c``, ``k_cos.c``, ``e_rem_pio2.c``, ``e_exp.c``, ``e_acos.c``,
``s_atan.c``); the code is ours, branch-free for vectorisation. The argument reduction of
``sincos`` is exact to about 1e-30 rad for |x| < 1.6e6 rad, far beyond any angle a healthy run
reaches (the divergence limit stops a run at 1e6).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)
from numba import types as nbtypes
from numba.extending import intrinsic

__all__ = ["sincos", "exp", "acos", "atan2"]


@intrinsic
def _as_int(typingctx, x):
    """The bits of a float64 as an int64."""
    if x != nbtypes.float64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], context.get_value_type(nbtypes.int64))

    return nbtypes.int64(nbtypes.float64), codegen


@intrinsic
def _as_float(typingctx, i):
    """The float64 whose bits are the int64 ``i``."""
    if i != nbtypes.int64:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], context.get_value_type(nbtypes.float64))

    return nbtypes.float64(nbtypes.int64), codegen


# --- sin and cos -------------------------------------------------------------------------------

_INV_PIO2 = 6.36619772367581382433e-01
# pi/2 as three 33-bit parts and a tail (the parts' products with |n| < 2^20 are exact)
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3, _PIO2_3T = 2.02226624871116645580e-21, 8.47842766036889956997e-32
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11


@njit(cache=True, error_model="numpy", inline="always")
def sincos(x):
    """(sin x, cos x), both within 1 ulp; NaN for a non-finite x."""
    fn = np.floor(x * _INV_PIO2 + 0.5)
    # x - fn pi/2 as hi + lo: the first product and difference are exact (|fn| < 2^20, and x is
    # within pi/4 of fn pi/2); the next two parts' differences keep their rounding errors
    r = x - fn * _PIO2_1
    w = fn * _PIO2_2
    t = r
    r = t - w
    e2 = (t - r) - w
    w = fn * _PIO2_3
    t = r
    r = t - w
    e3 = (t - r) - w
    w = fn * _PIO2_3T - e3 - e2
    hi = r - w
    lo = (r - hi) - w
    z = hi * hi
    # sin(hi + lo) and cos(hi + lo) on [-pi/4, pi/4]
    v = z * hi
    p = _S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))
    s = hi - ((z * (0.5 * lo - v * p) - lo) - v * _S1)
    q = z * (_C1 + z * (_C2 + z * (_C3 + z * (_C4 + z * (_C5 + z * _C6)))))
    hz = 0.5 * z
    wc = 1.0 - hz
    c = wc + (((1.0 - wc) - hz) + (z * q - hi * lo))
    quadrant = fn - 4.0 * np.floor(0.25 * fn)
    odd = quadrant == 1.0 or quadrant == 3.0
    sn = c if odd else s
    cs = s if odd else c
    sn = -sn if quadrant >= 2.0 else sn
    cs = -cs if (quadrant == 1.0 or quadrant == 2.0) else cs
    return sn, cs


# --- exp ---------------------------------------------------------------------------------------

_LN2_HI, _LN2_LO, _INV_LN2 = 6.93147180369123816490e-01, 1.90821492927058770002e-10, 1.44269504088896338700e+00
_P1, _P2, _P3 = 1.66666666666666019037e-01, -2.77777777770155933842e-03, 6.61375632143793436117e-05
_P4, _P5 = -1.65339022054652515390e-06, 4.13813679705723846039e-08
_EXP_MAX, _EXP_MIN = 709.782712893383973096, -745.13321910194110842


@njit(cache=True, error_model="numpy", inline="always")
def exp(x):
    """e^x within 1 ulp (subnormal results included); 0 below -745.13, inf above 709.78, NaN for NaN."""
    xc = min(max(x, -746.0), 710.0)  # keeps the scale's exponent in range; the ends are selected below
    k = np.floor(xc * _INV_LN2 + 0.5)
    hi = xc - k * _LN2_HI
    lo = k * _LN2_LO
    r = hi - lo
    t = r * r
    c = r - t * (_P1 + t * (_P2 + t * (_P3 + t * (_P4 + t * _P5))))
    y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
    # y 2^k as y 2^k1 2^k2, each factor a normal number, so a subnormal result is rounded once
    ki = np.int64(k)
    k1 = ki >> 1
    k2 = ki - k1
    out = y * _as_float((k1 + 1023) << 52) * _as_float((k2 + 1023) << 52)
    out = 0.0 if x < _EXP_MIN else out
    out = np.inf if x > _EXP_MAX else out
    return x if x != x else out


# --- acos --------------------------------------------------------------------------------------

_PIO2_HI, _PIO2_LO, _PI = 1.57079632679489655800e+00, 6.12323399573676603587e-17, 3.14159265358979311600e+00
_PS0, _PS1, _PS2 = 1.66666666666666657415e-01, -3.25565818622400915405e-01, 2.01212532134862925881e-01
_PS3, _PS4, _PS5 = -4.00555345006794114027e-02, 7.91534994289814532176e-04, 3.47933107596021167570e-05
_QS1, _QS2, _QS3, _QS4 = (-2.40339491173441421878e+00, 2.02094576023350569471e+00, -6.88283971605453293030e-01,
                          7.70381505559019352791e-02)


@njit(cache=True, error_model="numpy", inline="always")
def _asin_ratio(z):
    """(asin(sqrt z) - sqrt z) / sqrt(z)^3 as a rational function of z in [0, 0.25]."""
    p = z * (_PS0 + z * (_PS1 + z * (_PS2 + z * (_PS3 + z * (_PS4 + z * _PS5)))))
    q = 1.0 + z * (_QS1 + z * (_QS2 + z * (_QS3 + z * _QS4)))
    return p / q


@njit(cache=True, error_model="numpy", inline="always")
def acos(x):
    """arccos x in [0, pi] within 1 ulp for |x| <= 1; NaN outside."""
    ax = abs(x)
    # |x| <= 0.5: pi/2 - asin x
    zs = x * x
    small = _PIO2_HI - (x - (_PIO2_LO - x * _asin_ratio(zs)))
    # |x| > 0.5: through asin(sqrt((1 - |x|) / 2)), the square root split into a head with a short
    # mantissa and its correction
    z = (1.0 - ax) * 0.5
    s = np.sqrt(z)
    rz = _asin_ratio(z)
    neg = _PI - 2.0 * (s + (rz * s - _PIO2_LO))
    df = _as_float(_as_int(s) & np.int64(-4294967296))
    c = (z - df * df) / (s + df) if s > 0.0 else 0.0
    pos = 2.0 * (df + (rz * s + c))
    big = neg if x < 0.0 else pos
    out = small if ax <= 0.5 else big
    return out if ax <= 1.0 else np.nan


# --- atan2 -------------------------------------------------------------------------------------

_ATAN_HI = (4.63647609000806093515e-01, 7.85398163397448278999e-01)  # atan(0.5), atan(1)
_ATAN_LO = (2.26987774529616870924e-17, 3.06161699786838301793e-17)
_A0, _A1, _A2 = 3.33333333333329318027e-01, -1.99999999998764832476e-01, 1.42857142725034663711e-01
_A3, _A4, _A5 = -1.11111104054623557880e-01, 9.09088713343650656196e-02, -7.69187620504482999495e-02
_A6, _A7, _A8 = 6.66107313738753120669e-02, -5.83357013379057348645e-02, 4.97687799461593236017e-02
_A9, _A10 = -3.65315727442169155270e-02, 1.62858201153657823623e-02


@njit(cache=True, error_model="numpy", inline="always")
def _atan01(t):
    """(hi, lo) with hi + lo = atan t for t in [0, 1]."""
    # reduce around 0 (t < 7/16), 0.5 (t < 11/16) or 1
    mid = t >= 0.4375
    one = t >= 0.6875
    r0 = t
    r1 = (2.0 * t - 1.0) / (2.0 + t)
    r2 = (t - 1.0) / (t + 1.0)
    r = r2 if one else (r1 if mid else r0)
    base_hi = _ATAN_HI[1] if one else (_ATAN_HI[0] if mid else 0.0)
    base_lo = _ATAN_LO[1] if one else (_ATAN_LO[0] if mid else 0.0)
    z = r * r
    w = z * z
    s1 = z * (_A0 + w * (_A2 + w * (_A4 + w * (_A6 + w * (_A8 + w * _A10)))))
    s2 = w * (_A1 + w * (_A3 + w * (_A5 + w * (_A7 + w * _A9))))
    # atan t = base + r - r (s1 + s2), with base's tail folded into the correction
    return base_hi, (r - ((r * (s1 + s2) - base_lo)))


@njit(cache=True, error_model="numpy", inline="always")
def atan2(y, x):
    """The angle of (x, y) in [-pi, pi] within 2 ulp, for finite x and y not both 0 (NaN in, NaN out)."""
    ax = abs(x)
    ay = abs(y)
    swap = ay > ax
    num = ax if swap else ay
    den = ay if swap else ax
    hi, lo = _atan01(num / den)
    a = hi + lo  # atan(min / max) in [0, pi/4]
    # the octant: pi/2 - a when |y| > |x|, then pi - that when x < 0
    a = (_PIO2_HI - (a - _PIO2_LO)) if swap else a
    a = (_PI - (a - 2.0 * _PIO2_LO)) if x < 0.0 else a
    a = math.copysign(a, y)  # the sign bit of y, so that atan2(-0.0, -1.0) = -pi as in C
    return a if (x == x and y == y) else np.nan
