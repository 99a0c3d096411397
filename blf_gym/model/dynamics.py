"""Rigid-body model of an n-link planar arm with point masses (paper eq. 1, Appendix A).

Joint angles q are relative; the absolute angle of link j is theta_j = q_1 + ... + q_j, measured
from +x, and gravity acts along -y. Link j has length l_j and a point mass m_j at its distal end.

Derivation used here (generic in n, O(n^2) per call). With T the lower-triangular matrix of ones
(theta = T q) and mu_j = m_j + ... + m_n the mass carried beyond joint j,

* kinetic energy is 1/2 omega^T W omega with omega = T qd and
  W_jk = l_j l_k mu_max(j,k) cos(theta_j - theta_k), so M(q) = T^T W T;
* the Christoffel symbols of W in theta-coordinates give C~_jk = S_jk omega_k with
  S_jk = l_j l_k mu_max(j,k) sin(theta_j - theta_k); a constant linear change of coordinates maps
  them to C(q, qd) = T^T C~ T, so Mdot - 2C is skew-symmetric;
* G_a = sum_{j>=a} g l_j mu_j cos(theta_j);
* the end-effector pose (x, y, phi) has Jacobian rows -sum_{j>=a} l_j sin theta_j,
  sum_{j>=a} l_j cos theta_j and 1.

For 3 links this equals the paper's Appendix A once its typos are fixed (see docs/model.md section 1 and
``tests/test_dynamics.py``), and it matches Pinocchio's CRBA and RNEA.

The ``*_into`` functions are compiled (numba, cached to disk) and write into caller-provided
arrays so the closed-loop kernel allocates nothing per step; matrices are flat row-major
(n*n) arrays, which keeps the compiled code free of reshapes. ``arm`` is the packed layout of
:meth:`blf_gym.model.params.ArmParams.pack`: ``[l_1..l_n, m_1..m_n, g]``. The functions without
``_into`` are NumPy-facing conveniences built on the same compiled code.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit import vmath

from blf_gym.jit.layout import ARM, DYN_WORK, TRIG, WORK_PER_LINK, at, links_of, part
from blf_gym.model.params import ArmParams

__all__ = [
    "WORK_PER_LINK",
    "abs_trig_into",
    "mass_matrix_into",
    "coriolis_times_into",
    "gravity_into",
    "wrench_torque_into",
    "ldl_factor_into",
    "ldl_solve_factored",
    "ldl_solve_into",
    "mass_matrix",
    "coriolis_matrix",
    "gravity",
    "pose_jacobian",
    "forward_kinematics",
    "joint_positions",
]

_COS, _SIN = TRIG.start("cos"), TRIG.start("sin")
_LEN, _MASS, _GRAV = ARM.start("lengths"), ARM.start("masses"), ARM.start("gravity")
_MU, _OMEGA, _PSI = DYN_WORK.start("mu"), DYN_WORK.start("omega"), DYN_WORK.start("psi")
_PER_LINK = DYN_WORK.size("mu")  # each part of the work is n long
_TRIG_SIZE = TRIG.total


@njit(cache=True, error_model="numpy", inline="always")
def abs_trig_into(q, trig):
    """[cos theta_1..n, sin theta_1..n] of the absolute link angles into ``trig`` (2n).

    Every other ``*_into`` function takes this instead of q, so one configuration costs 2n
    transcendental calls however many model terms are evaluated at it.
    """
    n = q.shape[0]
    c0, s0 = at(_COS, n), at(_SIN, n)
    th = 0.0
    for j in range(n):
        th += q[j]
        sn, cs = vmath.sincos(th)
        trig[c0 + j] = cs
        trig[s0 + j] = sn


@njit(cache=True, error_model="numpy", inline="always")
def _mass_beyond(arm, n, mu):
    m0 = at(_MASS, n)
    acc = 0.0
    for j in range(n - 1, -1, -1):
        acc += arm[m0 + j]
        mu[j] = acc


@njit(cache=True, error_model="numpy", inline="always")
def mass_matrix_into(trig, arm, M, work):
    """M(q) into the flat row-major ``M`` (n*n). ``work`` needs ``n`` entries."""
    n = links_of(trig.shape[0], _TRIG_SIZE)
    l0, c0, s0 = at(_LEN, n), at(_COS, n), at(_SIN, n)
    mu = part(work, _MU, _PER_LINK, n)
    _mass_beyond(arm, n, mu)
    for j in range(n):
        lj = arm[l0 + j]
        M[j * n + j] = lj * lj * mu[j]
        for k in range(j + 1, n):
            # cos(theta_j - theta_k)
            w = lj * arm[l0 + k] * mu[k] * (trig[c0 + j] * trig[c0 + k] + trig[s0 + j] * trig[s0 + k])
            M[j * n + k] = w
            M[k * n + j] = w
    # M = T^T W T: reverse cumulative sums along both axes.
    for j in range(n - 2, -1, -1):
        for k in range(n):
            M[j * n + k] += M[(j + 1) * n + k]
    for j in range(n):
        for k in range(n - 2, -1, -1):
            M[j * n + k] += M[j * n + k + 1]


@njit(cache=True, error_model="numpy", inline="always")
def coriolis_times_into(trig, v, w, arm, out, work):
    """C(q, v) w into ``out`` (n), with C the Christoffel-symbol Coriolis matrix at ``trig``.

    ``C(q, qd) qd`` is the Coriolis/centripetal torque; a law's ``C(q, x2_hat) alpha1`` uses
    ``v = x2_hat`` and ``w = alpha1``. ``work`` needs ``3 n`` entries.
    """
    n = v.shape[0]
    l0, c0, s0 = at(_LEN, n), at(_COS, n), at(_SIN, n)
    mu = part(work, _MU, _PER_LINK, n)
    om = part(work, _OMEGA, _PER_LINK, n)
    ps = part(work, _PSI, _PER_LINK, n)
    _mass_beyond(arm, n, mu)
    a = 0.0
    b = 0.0
    for j in range(n):
        a += v[j]
        b += w[j]
        om[j] = a
        ps[j] = b
    # r_j = sum_k S_jk omega_k psi_k; out = T^T r.
    for j in range(n):
        out[j] = 0.0
    for j in range(n):
        for k in range(j + 1, n):
            # sin(theta_j - theta_k)
            s = arm[l0 + j] * arm[l0 + k] * mu[k] * (trig[s0 + j] * trig[c0 + k] - trig[c0 + j] * trig[s0 + k])
            out[j] += s * om[k] * ps[k]
            out[k] -= s * om[j] * ps[j]
    for j in range(n - 2, -1, -1):
        out[j] += out[j + 1]


@njit(cache=True, error_model="numpy", inline="always")
def gravity_into(trig, arm, out, work):
    """G(q) = dV/dq into ``out`` (n). ``work`` needs ``n`` entries."""
    n = out.shape[0]
    l0, c0 = at(_LEN, n), at(_COS, n)
    mu = part(work, _MU, _PER_LINK, n)
    _mass_beyond(arm, n, mu)
    g = arm[at(_GRAV, n)]
    acc = 0.0
    for j in range(n - 1, -1, -1):
        acc += g * arm[l0 + j] * mu[j] * trig[c0 + j]
        out[j] = acc


@njit(cache=True, error_model="numpy", inline="always")
def wrench_torque_into(trig, arm, wrench, out):
    """J(q)^T f for an end-effector wrench f = (f_x, f_y, moment), into ``out`` (n)."""
    n = out.shape[0]
    l0, c0, s0 = at(_LEN, n), at(_COS, n), at(_SIN, n)
    sx = 0.0
    sy = 0.0
    for j in range(n - 1, -1, -1):
        sx += arm[l0 + j] * trig[s0 + j]
        sy += arm[l0 + j] * trig[c0 + j]
        out[j] = -wrench[0] * sx + wrench[1] * sy + wrench[2]


@njit(cache=True, error_model="numpy", inline="always")
def ldl_factor_into(M, L):
    """Square-root-free Cholesky (LDL^T) factor of the SPD matrix M (flat row-major n*n) into ``L``.

    ``L`` holds the unit lower-triangular factor below its diagonal and the *reciprocals* 1 / D_ii
    on it, so that solving (:func:`ldl_solve_factored`) needs neither a square root nor a
    division: those are the slowest operations in the closed loop's hot path.
    """
    n = int(np.sqrt(M.shape[0]) + 0.5)
    for j in range(n):
        # D_j = M_jj - sum_k L_jk^2 D_k, with L_jk D_k kept in the upper triangle's mirror
        d = M[j * n + j]
        for k in range(j):
            d -= L[j * n + k] * L[k * n + j]
        inv = 1.0 / d
        L[j * n + j] = inv
        for i in range(j + 1, n):
            s = M[i * n + j]
            for k in range(j):
                s -= L[i * n + k] * L[k * n + j]
            # s = L_ij D_j: kept in L's upper triangle for the next columns, then L_ij = s / D_j
            L[j * n + i] = s
            L[i * n + j] = s * inv


@njit(cache=True, error_model="numpy", inline="always")
def ldl_solve_factored(L, b, out):
    """Solve L D L^T x = b into ``out``, with ``L`` from :func:`ldl_factor_into`."""
    n = b.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i * n + k] * out[k]
        out[i] = s
    for i in range(n - 1, -1, -1):
        s = out[i] * L[i * n + i]
        for k in range(i + 1, n):
            s -= L[k * n + i] * out[k]
        out[i] = s


@njit(cache=True, error_model="numpy", inline="always")
def ldl_solve_into(M, b, out, L):
    """Solve M x = b for symmetric positive definite M (flat row-major n*n); ``L`` (n*n) is scratch."""
    ldl_factor_into(M, L)
    ldl_solve_factored(L, b, out)


# ---------------------------------------------------------------------------------------------
# NumPy-facing helpers (same compiled code)


def _packed(arm: ArmParams | np.ndarray, q: np.ndarray) -> np.ndarray:
    packed = arm.pack() if isinstance(arm, ArmParams) else np.ascontiguousarray(arm, dtype=np.float64)
    if packed.shape != (ARM.length(q.shape[-1]),):
        raise ValueError(
            f"arm must describe {q.shape[-1]} links (packed length {ARM.length(q.shape[-1])}), "
            f"got packed length {packed.shape}"
        )
    return packed


def _trig(q: np.ndarray) -> np.ndarray:
    trig = np.empty(TRIG.length(q.shape[0]))
    abs_trig_into(q, trig)
    return trig


def _vec(x: np.ndarray) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"expected a 1-D joint vector, got shape {x.shape}")
    return x


def mass_matrix(q: np.ndarray, arm: ArmParams | np.ndarray = ArmParams()) -> np.ndarray:
    """Inertia matrix M(q), shape (n, n)."""
    q = _vec(q)
    n = q.shape[0]
    M = np.empty(n * n)
    mass_matrix_into(_trig(q), _packed(arm, q), M, np.empty(DYN_WORK.length(n)))
    return M.reshape(n, n)


def coriolis_matrix(q: np.ndarray, qd: np.ndarray, arm: ArmParams | np.ndarray = ArmParams()) -> np.ndarray:
    """The Christoffel-symbol Coriolis matrix C(q, qd), shape (n, n)."""
    q, qd = _vec(q), _vec(qd)
    n = q.shape[0]
    packed = _packed(arm, q)
    C = np.empty((n, n))
    e = np.zeros(n)
    col = np.empty(n)
    work = np.empty(DYN_WORK.length(n))
    trig = _trig(q)
    for k in range(n):
        e[:] = 0.0
        e[k] = 1.0
        coriolis_times_into(trig, qd, e, packed, col, work)
        C[:, k] = col
    return C


def gravity(q: np.ndarray, arm: ArmParams | np.ndarray = ArmParams()) -> np.ndarray:
    """Gravity torque G(q), shape (n,)."""
    q = _vec(q)
    out = np.empty(q.shape[0])
    gravity_into(_trig(q), _packed(arm, q), out, np.empty(DYN_WORK.length(q.shape[0])))
    return out


def joint_positions(q: np.ndarray, arm: ArmParams | np.ndarray = ArmParams()) -> np.ndarray:
    """Positions of the base and of each link's distal end, shape (n + 1, 2), m."""
    q = _vec(q)
    packed = _packed(arm, q)
    n = q.shape[0]
    th = np.cumsum(q)
    steps = packed[ARM.slice("lengths", n), None] * np.stack([np.cos(th), np.sin(th)], axis=1)
    return np.vstack([np.zeros((1, 2)), np.cumsum(steps, axis=0)])


def forward_kinematics(q: np.ndarray, arm: ArmParams | np.ndarray = ArmParams()) -> np.ndarray:
    """End-effector pose (x m, y m, phi rad)."""
    q = _vec(q)
    tip = joint_positions(q, arm)[-1]
    return np.array([tip[0], tip[1], float(np.sum(q))])


def pose_jacobian(q: np.ndarray, arm: ArmParams | np.ndarray = ArmParams()) -> np.ndarray:
    """Jacobian of the pose (x, y, phi) with respect to q, shape (3, n)."""
    q = _vec(q)
    packed = _packed(arm, q)
    n = q.shape[0]
    J = np.empty((3, n))
    out = np.empty(n)
    trig = _trig(q)
    for row, wrench in enumerate(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))):
        wrench_torque_into(trig, packed, np.array(wrench), out)
        J[row] = out
    return J
