"""Joint-space reference, with analytic first and second derivatives: the paper's Section 4.1
circle (kind "circle", 3 links) or one sinusoid per joint (kind "joint", any number of links).

The end effector follows x_d = cx + r cos(w t), y_d = cy + r sin(w t), phi_d constant, with
w = 2 pi f. Its wrist (end effector minus l3 along phi_d) runs on a circle of radius r around
c_w = (cx, cy) - l3 (cos phi_d, sin phi_d) that touches the inner workspace boundary |w| = l1 - l2.
From the law of cosines, |w|^2 = (l1 - l2)^2 + 4 l1 l2 cos^2(q2 / 2), and tangency gives

    cos(q2 / 2) = k cos(theta),  k = sqrt(r |c_w| / (l1 l2)),  theta = (w t - angle(c_w)) / 2,

(k = sqrt(0.1 / 0.21) = 0.690 for the paper) so the **smooth** branch q2 = 2 acos(k cos theta) is
analytic for all t and folds the elbow through q2 = pi at the instants theta = pi/2 + m pi. The
**standard** branch keeps q2 in [0, pi] (acos of |k cos theta|): continuous, but its velocity jumps
at every fold. Then q1 = atan2(w_y, w_x) - atan2(l2 sin q2, l1 + l2 cos q2) and
q3 = phi_d - q1 - q2.

Kind "joint": q_d,j = offset_j + a_j sin(w t + p_j). Its phase is packed with beta = 0, so the same
angle theta = w t / 2 gives cos and sin of w t by the double angle, and each joint's sin and cos of
w t + p_j follow from the packed cos p_j and sin p_j: one sincos per time, whatever n.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit import vmath

from blf_gym.jit.layout import ARM, REF, REFERENCE, REFERENCE_SIGNALS, at
from blf_gym.model.params import Scenario

__all__ = ["reference_into", "reference_angle", "reference_from", "joint_reference", "REFERENCE_SIGNALS"]

_FREQ, _RADIUS, _ORIENT, _BRANCH = (REFERENCE.index(k) for k in ("frequency", "radius", "orientation", "branch"))
_WX, _WY, _K, _CB, _SB, _BETA = (REFERENCE.index(k) for k in ("wrist_x", "wrist_y", "k", "cos_beta", "sin_beta", "beta"))
_KIND = REFERENCE.index("kind")
_JCOS, _JSIN, _JAMP, _JOFF = (REFERENCE.start(k) for k in ("cos_phase", "sin_phase", "amplitude", "offset"))
_Q, _QD, _QDD = (REF.start(k) for k in ("q_d", "qd_d", "qdd_d"))
_L1, _L2 = ARM.index("lengths"), ARM.index("lengths") + 1


@njit(cache=True, error_model="numpy", inline="always")
def reference_angle(t, rp):
    """theta(t) = (w t - angle(c_w)) / 2, the one angle whose cos and sin the reference needs."""
    om = 2.0 * np.pi * rp[_FREQ]
    return 0.5 * (om * t - rp[_BETA])


@njit(cache=True, error_model="numpy", inline="always")
def reference_into(t, rp, arm, out):
    """Write [q_d, qd_d, qdd_d] (3n entries) at time ``t`` into ``out``.

    ``rp`` is :meth:`Scenario.pack_reference`; ``arm`` the packed arm (lengths are read from it).
    """
    st, ct = vmath.sincos(reference_angle(t, rp))
    reference_from(st, ct, rp, arm, out)


@njit(cache=True, error_model="numpy", inline="always")
def reference_from(st, ct, rp, arm, out):
    """:func:`reference_into` given (sin, cos) of :func:`reference_angle` at t: the closed loop's
    kernel evaluates those with the plant's and the measurement's link angles in one loop."""
    f, rad, phi, standard = rp[_FREQ], rp[_RADIUS], rp[_ORIENT], rp[_BRANCH] > 0.5
    wcx, wcy, k, cb, sb = rp[_WX], rp[_WY], rp[_K], rp[_CB], rp[_SB]
    l1, l2 = arm[_L1], arm[_L2]
    om = 2.0 * np.pi * f
    nu = 0.5 * om
    # theta = (om t - beta) / 2 with beta = angle(c_w); om t = 2 theta + beta
    c2t = ct * ct - st * st
    s2t = 2.0 * st * ct
    c = c2t * cb - s2t * sb  # cos(om t)
    sn = s2t * cb + c2t * sb  # sin(om t)
    if rp[_KIND] > 0.5:  # kind "joint" (packed with beta = 0)
        _sinusoids_from(c, sn, om, rp, arm, out)
        return

    # s = cos(q2 / 2) and its derivatives
    s = k * ct
    sd = -k * nu * st
    sdd = -nu * nu * s
    if standard and s < 0.0:
        s, sd, sdd = -s, -sd, -sdd
    one_m = 1.0 - s * s
    den = np.sqrt(one_m)
    inv_den = 1.0 / den
    q2 = 2.0 * vmath.acos(s)
    q2d = -2.0 * sd * inv_den
    q2dd = -2.0 * (sdd * one_m + s * sd * sd) * (inv_den * inv_den * inv_den)

    # wrist position angle alpha = atan2(w_y, w_x)
    wx = wcx + rad * c
    wy = wcy + rad * sn
    wxd = -rad * om * sn
    wyd = rad * om * c
    wxdd = -om * om * rad * c
    wydd = -om * om * rad * sn
    dd = wx * wx + wy * wy
    cr = wx * wyd - wy * wxd
    crd = wx * wydd - wy * wxdd
    ddd = 2.0 * (wx * wxd + wy * wyd)
    inv_dd = 1.0 / dd
    ald = cr * inv_dd
    aldd = (crd * dd - cr * ddd) * (inv_dd * inv_dd)

    # elbow offset angle beta = atan2(l2 sin q2, l1 + l2 cos q2)
    c2 = 2.0 * s * s - 1.0  # cos(q2) = cos(2 acos s)
    s2 = 2.0 * s * den  # sin(q2)
    inv_d2 = 1.0 / (l1 * l1 + l2 * l2 + 2.0 * l1 * l2 * c2)
    nn = l2 * (l2 + l1 * c2) * inv_d2
    nq = l1 * l2 * s2 * (l2 * l2 - l1 * l1) * (inv_d2 * inv_d2)
    bed = nn * q2d
    bedd = nn * q2dd + nq * q2d * q2d

    # q1 = alpha - beta with alpha = angle(w). The wrist circle stays within +-90 deg of the
    # direction of its centre (it lies outside the inner boundary it touches) and beta is within
    # +-90 deg (l1 > l2), so one atan2 of w rotated by -angle(c_w), then by -beta, is
    # continuous: q1 = angle(c_w) + atan2(...).
    wrx = wx * cb + wy * sb
    wry = wy * cb - wx * sb
    ex = l1 + l2 * c2
    ey = l2 * s2
    q1 = rp[_BETA] + vmath.atan2(wry * ex - wrx * ey, wrx * ex + wry * ey)
    q1d = ald - bed
    q1dd = aldd - bedd
    n = 3  # the circle is the paper's 3-link inverse kinematics
    q, qd, qdd = at(_Q, n), at(_QD, n), at(_QDD, n)
    out[q] = q1
    out[q + 1] = q2
    out[q + 2] = phi - q1 - q2
    out[qd] = q1d
    out[qd + 1] = q2d
    out[qd + 2] = -q1d - q2d
    out[qdd] = q1dd
    out[qdd + 1] = q2dd
    out[qdd + 2] = -q1dd - q2dd


@njit(cache=True, error_model="numpy", inline="always")
def _sinusoids_from(c, s, om, rp, arm, out):
    """Kind "joint": q_d,j = offset_j + a_j sin(om t + p_j) and its derivatives, from c = cos(om t),
    s = sin(om t). ``out`` holds 3n entries (callers pass the packed plant or the arm as ``arm``, so
    n is read from ``out``)."""
    n = out.shape[0] // len(REFERENCE_SIGNALS)
    for j in range(n):
        cp = rp[at(_JCOS, n) + j]
        sp = rp[at(_JSIN, n) + j]
        a = rp[at(_JAMP, n) + j]
        sj = s * cp + c * sp  # sin(om t + p_j)
        cj = c * cp - s * sp  # cos(om t + p_j)
        out[at(_Q, n) + j] = rp[at(_JOFF, n) + j] + a * sj
        out[at(_QD, n) + j] = a * om * cj
        out[at(_QDD, n) + j] = -a * om * om * sj


@njit(cache=True, error_model="numpy")
def _reference_table(ts, rp, arm):
    out = np.empty((ts.shape[0], len(REFERENCE_SIGNALS) * ((arm.shape[0] - 1) // 2)))
    for i in range(ts.shape[0]):
        reference_into(ts[i], rp, arm, out[i])
    return out


def joint_reference(t: np.ndarray | float, scenario: Scenario = Scenario()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q_d, qd_d, qdd_d), each of shape ``t.shape + (n,)``, in rad, rad/s, rad/s^2."""
    n = scenario.arm.n_links
    t_arr = np.atleast_1d(np.asarray(t, dtype=np.float64)).ravel()
    table = _reference_table(t_arr, scenario.pack_reference(), scenario.arm.pack())
    shape = np.shape(t) + (n,)
    return tuple(table[:, REF.slice(k, n)].reshape(shape) for k in REFERENCE_SIGNALS)
