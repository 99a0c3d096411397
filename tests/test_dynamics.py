"""Tests of blf_gym.model.dynamics: the n-link planar arm with point masses (docs/model.md section 1).

Every check compares the library against something built independently here: structural
identities of Lagrangian mechanics (SPD inertia, skew-symmetry, Christoffel symbols from finite
differences of M), the paper's Appendix A typed in by hand with its typos and lost minus signs
repaired, Pinocchio's CRBA/RNEA, conservation of energy along a numerically integrated free
motion, and finite differences of the forward kinematics.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from blf_gym.model.dynamics import (
    coriolis_matrix,
    forward_kinematics,
    gravity,
    joint_positions,
    mass_matrix,
    pose_jacobian,
)
from blf_gym.model.params import ArmParams

PAPER = ArmParams()  # l = (0.35, 0.30, 0.15), m = (0.23, 0.20, 0.10), g = 9.81


def random_arm(rng: np.random.Generator, n: int) -> ArmParams:
    return ArmParams(
        lengths=tuple(rng.uniform(0.1, 0.6, n)),
        masses=tuple(rng.uniform(0.05, 1.0, n)),
        gravity=9.81,
    )


def random_state(rng: np.random.Generator, n: int, speed: float = 3.0):
    return rng.uniform(-np.pi, np.pi, n), rng.uniform(-speed, speed, n)


# Hypothesis strategy: a link count, an arm and a state, all drawn together.
@st.composite
def arm_and_state(draw, counts=(2, 3, 4)):
    n = draw(st.sampled_from(counts))
    floats = lambda lo, hi: st.floats(lo, hi, allow_nan=False, allow_infinity=False)  # noqa: E731
    lengths = draw(st.lists(floats(0.05, 1.0), min_size=n, max_size=n))
    masses = draw(st.lists(floats(0.01, 2.0), min_size=n, max_size=n))
    q = np.array(draw(st.lists(floats(-2 * np.pi, 2 * np.pi), min_size=n, max_size=n)))
    qd = np.array(draw(st.lists(floats(-10.0, 10.0), min_size=n, max_size=n)))
    return ArmParams(lengths=tuple(lengths), masses=tuple(masses), gravity=9.81), q, qd


# ---------------------------------------------------------------------------------------------
# Independent kinematics (used by several tests)


def fk_points(q: np.ndarray, arm: ArmParams) -> np.ndarray:
    """Distal-end positions of every link, (n, 2), straight from the definition."""
    pts = []
    x = y = th = 0.0
    for qi, li in zip(q, arm.lengths):
        th += qi
        x += li * np.cos(th)
        y += li * np.sin(th)
        pts.append((x, y))
    return np.array(pts)


def mass_matrix_from_jacobians(q: np.ndarray, arm: ArmParams) -> np.ndarray:
    """M = sum_i m_i Jv_i^T Jv_i, Jv_i the translational Jacobian of point mass i (by hand)."""
    n = len(q)
    th = np.cumsum(q)
    M = np.zeros((n, n))
    for i in range(n):
        Jv = np.zeros((2, n))
        for a in range(i + 1):  # joint a moves every link j >= a
            for j in range(a, i + 1):
                Jv[0, a] -= arm.lengths[j] * np.sin(th[j])
                Jv[1, a] += arm.lengths[j] * np.cos(th[j])
        M += arm.masses[i] * Jv.T @ Jv
    return M


def christoffel_coriolis(q: np.ndarray, qd: np.ndarray, arm: ArmParams, h: float = 1e-6) -> np.ndarray:
    """C_kj = sum_i Gamma_{ijk} qd_i, Gamma from central differences of M (Christoffel, 1st kind)."""
    n = len(q)
    dM = np.empty((n, n, n))  # dM[i] = dM/dq_i
    for i in range(n):
        e = np.zeros(n)
        e[i] = h
        dM[i] = (mass_matrix(q + e, arm) - mass_matrix(q - e, arm)) / (2 * h)
    C = np.zeros((n, n))
    for k in range(n):
        for j in range(n):
            for i in range(n):
                C[k, j] += 0.5 * (dM[i][k, j] + dM[j][k, i] - dM[k][i, j]) * qd[i]
    return C


# ---------------------------------------------------------------------------------------------
# Structure of M and C


@settings(max_examples=200, deadline=None)
@given(arm_and_state())
def test_mass_matrix_symmetric_positive_definite(case):
    arm, q, _ = case
    M = mass_matrix(q, arm)
    # Symmetry is exact in the construction (mirrored writes), so demand it to round-off.
    np.testing.assert_allclose(M, M.T, rtol=0, atol=1e-14 * np.abs(M).max())
    # Point masses on a serial chain: M is positive definite at every q (each joint moves at least
    # the last mass along a non-zero, independent direction). The eigenvalue can be small for
    # tiny links/masses, so the check is relative to the largest one, with slack for round-off.
    eig = np.linalg.eigvalsh(M)
    assert eig.min() > 1e-12 * eig.max()
    # Cholesky must succeed (the closed loop solves with it).
    np.linalg.cholesky(M)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_mass_matrix_equals_sum_of_point_mass_jacobians(n):
    rng = np.random.default_rng(10 + n)
    for _ in range(50):
        arm = random_arm(rng, n)
        q, _ = random_state(rng, n)
        # Both are exact closed forms of O(1) magnitude: agreement to round-off.
        np.testing.assert_allclose(mass_matrix(q, arm), mass_matrix_from_jacobians(q, arm), rtol=0, atol=1e-13)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_mdot_minus_2c_is_skew_symmetric(n):
    rng = np.random.default_rng(20 + n)
    h = 1e-6
    for _ in range(50):
        arm = random_arm(rng, n)
        q, qd = random_state(rng, n)
        # Mdot = dM/dt along the motion, by central differences along q + s qd.
        Mdot = (mass_matrix(q + h * qd, arm) - mass_matrix(q - h * qd, arm)) / (2 * h)
        C = coriolis_matrix(q, qd, arm)
        N = Mdot - 2 * C
        # Central-difference error is O(h^2 |M'''| |qd|^3) ~ 1e-11 plus round-off eps|M|/h ~ 1e-10
        # for entries of O(1); 1e-8 leaves a margin yet catches any sign or factor error (O(1)).
        np.testing.assert_allclose(N + N.T, 0.0, atol=1e-8)
        # The stronger identity of the Christoffel choice: Mdot = C + C^T.
        np.testing.assert_allclose(Mdot, C + C.T, atol=1e-8)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_coriolis_equals_christoffel_symbols_of_fd_mass_matrix(n):
    rng = np.random.default_rng(30 + n)
    for _ in range(30):
        arm = random_arm(rng, n)
        q, qd = random_state(rng, n)
        C_ref = christoffel_coriolis(q, qd, arm)
        # Same finite-difference error budget as above (first derivatives of M times |qd| <= 3).
        np.testing.assert_allclose(coriolis_matrix(q, qd, arm), C_ref, rtol=0, atol=1e-8)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_gravity_is_gradient_of_potential(n):
    rng = np.random.default_rng(40 + n)
    h = 1e-6

    def potential(q, arm):
        return arm.gravity * np.dot(arm.masses, fk_points(q, arm)[:, 1])

    for _ in range(30):
        arm = random_arm(rng, n)
        q, _ = random_state(rng, n)
        grad = np.array([(potential(q + h * e, arm) - potential(q - h * e, arm)) / (2 * h) for e in np.eye(n)])
        # V ~ 10 J at most; round-off 1e-15 * 10 / 1e-6 = 1e-8, truncation h^2 |V'''| ~ 1e-11.
        np.testing.assert_allclose(gravity(q, arm), grad, rtol=0, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# The paper's Appendix A, typed in with the typos corrected and minus signs restored


def appendix_a(q: np.ndarray, qd: np.ndarray, arm: ArmParams):
    """M, C, G of the paper's Appendix A for 3 links.

    The extracted text lost every minus sign; they were restored by hand so that M matches the
    standard planar form (e.g. M11 = m1 l1^2 + m2(l1^2 + l2^2 + 2 l1 l2 c2) + m3(l1^2 + l2^2 +
    l3^2 + 2 l1 l2 c2 + 2 l2 l3 c3 + 2 l1 l3 c23)) and C's entries equal the Christoffel-symbol
    entries derived term by term from that M. The printed structure is kept (not simplified) so
    that this is the Appendix itself, with docs/model.md section 1's typo fixes:
      * M12: ``c3 (l2 + l1 c2)`` where the paper prints ``c2 (l2 + l1 c2)``;
      * C11: first term ``qd2 l1 l3 m3 s23`` (printed ``l1 l2``), third ``qd2 l1 l2 (m2 + m3) s2``
        (printed ``m3`` only).
    Here s2 = sin q2, s3 = sin q3, s23 = sin(q2 + q3), c1 = cos q1, c12 = cos(q1 + q2), ...
    """
    l1, l2, l3 = arm.lengths
    m1, m2, m3 = arm.masses
    g = arm.gravity
    q1, q2, q3 = q
    x1, x2, x3 = qd
    s2, s3, c2, c3 = np.sin(q2), np.sin(q3), np.cos(q2), np.cos(q3)
    s23 = np.sin(q2 + q3)
    c1, c12, c123 = np.cos(q1), np.cos(q1 + q2), np.cos(q1 + q2 + q3)

    # Recurring groups in the printed M: A = l3 + c3(l2 + l1 c2) - l1 s2 s3 and
    # B = s3(l2 + l1 c2) + l1 c3 s2 (kept literally below).
    M11 = (
        l2 * (m3 * s3 * (s3 * (l2 + l1 * c2) + l1 * c3 * s2) + m3 * c3 * (l3 + c3 * (l2 + l1 * c2) - l1 * s2 * s3))
        + l1 * (
            s2 * (
                l1 * m2 * s2
                + m3 * c3 * (s3 * (l2 + l1 * c2) + l1 * c3 * s2)
                - m3 * s3 * (l3 + c3 * (l2 + l1 * c2) - l1 * s2 * s3)
            )
            + c2 * (
                m2 * (l2 + l1 * c2)
                + m3 * s3 * (s3 * (l2 + l1 * c2) + l1 * c3 * s2)
                + m3 * c3 * (l3 + c3 * (l2 + l1 * c2) - l1 * s2 * s3)
            )
        )
        + l1**2 * m1
        + l3 * m3 * (l3 + c3 * (l2 + l1 * c2) - l1 * s2 * s3)
        + l2 * m2 * (l2 + l1 * c2)
    )
    M12 = (
        l2 * (m3 * s3 * (s3 * (l2 + l1 * c2) + l1 * c3 * s2) + m3 * c3 * (l3 + c3 * (l2 + l1 * c2) - l1 * s2 * s3))
        + l3 * m3 * (l3 + c3 * (l2 + l1 * c2) - l1 * s2 * s3)
        + l2 * m2 * (l2 + l1 * c2)
    )
    M13 = l3 * m3 * (l3 + c3 * (l2 + l1 * c2) - l1 * s2 * s3)
    M22 = l2**2 * m2 + l2 * (l2 * m3 * s3**2 + m3 * c3 * (l3 + l2 * c3)) + l3 * m3 * (l3 + l2 * c3)
    M23 = l3 * m3 * (l3 + l2 * c3)
    M33 = l3**2 * m3
    M = np.array([[M11, M12, M13], [M12, M22, M23], [M13, M23, M33]])

    C11 = -x2 * l1 * l3 * m3 * s23 - x3 * l1 * l3 * m3 * s23 - x2 * l1 * l2 * (m2 + m3) * s2 - x3 * l2 * l3 * m3 * s3
    C12 = (
        -x1 * l1 * l3 * m3 * s23 - x2 * l1 * l3 * m3 * s23 - x3 * l1 * l3 * m3 * s23
        - x1 * l1 * l2 * (m2 + m3) * s2 - x2 * l1 * l2 * (m2 + m3) * s2 - x3 * l2 * l3 * m3 * s3
    )
    C13 = -l3 * m3 * (l1 * s23 + l2 * s3) * (x1 + x2 + x3)
    C21 = x1 * l1 * l3 * m3 * s23 + x1 * l1 * l2 * m2 * s2 + x1 * l1 * l2 * m3 * s2 - x3 * l2 * l3 * m3 * s3
    C22 = -x3 * l2 * l3 * m3 * s3
    C23 = -l2 * l3 * m3 * s3 * (x1 + x2 + x3)
    C31 = l3 * m3 * (x1 * l2 * s3 + x2 * l2 * s3 + x1 * l1 * s23)
    C32 = l2 * l3 * m3 * s3 * (x1 + x2)
    C33 = 0.0
    C = np.array([[C11, C12, C13], [C21, C22, C23], [C31, C32, C33]])

    G = np.array([
        g * (l1 * m1 * c1 + l1 * m2 * c1 + l1 * m3 * c1 + l3 * m3 * c123 + l2 * m2 * c12 + l2 * m3 * c12),
        g * (l3 * m3 * c123 + l2 * m2 * c12 + l2 * m3 * c12),
        g * l3 * m3 * c123,
    ])
    return M, C, G


def test_appendix_a_sanity_against_standard_form():
    """Guard the hand-typed Appendix itself: M11 against the textbook closed form."""
    rng = np.random.default_rng(50)
    l1, l2, l3 = PAPER.lengths
    m1, m2, m3 = PAPER.masses
    for _ in range(20):
        q, qd = random_state(rng, 3)
        c2, c3, c23 = np.cos(q[1]), np.cos(q[2]), np.cos(q[1] + q[2])
        M11 = (m1 * l1**2 + m2 * (l1**2 + l2**2 + 2 * l1 * l2 * c2)
               + m3 * (l1**2 + l2**2 + l3**2 + 2 * l1 * l2 * c2 + 2 * l2 * l3 * c3 + 2 * l1 * l3 * c23))
        assert abs(appendix_a(q, qd, PAPER)[0][0, 0] - M11) < 1e-14


@pytest.mark.parametrize("arm", [PAPER, ArmParams((0.5, 0.2, 0.4), (1.3, 0.7, 0.4), 3.7)], ids=["paper", "other"])
def test_matches_paper_appendix_a(arm):
    rng = np.random.default_rng(51)
    for _ in range(200):
        q, qd = random_state(rng, 3, speed=10.0)
        M_ref, C_ref, G_ref = appendix_a(q, qd, arm)
        # Closed forms on both sides; entries are O(1) (M <= 0.3 kg m^2, G <= 10 N m, C <= 10),
        # so only round-off separates them.
        np.testing.assert_allclose(mass_matrix(q, arm), M_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(gravity(q, arm), G_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(coriolis_matrix(q, qd, arm), C_ref, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Pinocchio as an independent rigid-body reference


def pinocchio_model(arm: ArmParams):
    pin = pytest.importorskip("pinocchio", reason="Pinocchio (pip package 'pin') is not importable")
    model = pin.Model()
    parent = 0
    offset = 0.0  # joint i sits at the distal end of link i-1
    for i, (li, mi) in enumerate(zip(arm.lengths, arm.masses)):
        placement = pin.SE3(np.eye(3), np.array([offset, 0.0, 0.0]))
        parent = model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{i + 1}")
        # A point mass m_i at the link's distal end: lever (l_i, 0, 0), no rotational inertia.
        inertia = pin.Inertia(mi, np.array([li, 0.0, 0.0]), np.zeros((3, 3)))
        model.appendBodyToJoint(parent, inertia, pin.SE3.Identity())
        offset = li
    model.gravity.linear = np.array([0.0, -arm.gravity, 0.0])
    return pin, model


@pytest.mark.parametrize("n,family", [(2, False), (3, False), (4, False), (2, True), (4, True), (5, True), (6, True),
                                      (7, True)], ids=lambda v: str(v))
def test_matches_pinocchio_crba_and_rnea(n, family):
    # random arms of 2-4 links and the paper's, and the task family's members (docs/family.md)
    from blf_gym.model.family import family_arm

    rng = np.random.default_rng(60 + n)
    arm = family_arm(n) if family else PAPER if n == 3 else random_arm(rng, n)
    pin, model = pinocchio_model(arm)
    data = model.createData()
    zero = np.zeros(n)
    for _ in range(100):
        q, qd = random_state(rng, n, speed=10.0)
        M_pin = pin.crba(model, data, q).copy()
        M_pin = np.triu(M_pin) + np.triu(M_pin, 1).T  # CRBA fills the upper triangle only
        G_pin = pin.rnea(model, data, q, zero, zero).copy()
        Cqd_pin = pin.rnea(model, data, q, qd, zero).copy() - G_pin
        # Two exact algorithms in double precision; magnitudes O(1-10): 1e-10 is round-off slack.
        np.testing.assert_allclose(mass_matrix(q, arm), M_pin, rtol=0, atol=1e-10)
        np.testing.assert_allclose(gravity(q, arm), G_pin, rtol=0, atol=1e-10)
        np.testing.assert_allclose(coriolis_matrix(q, qd, arm) @ qd, Cqd_pin, rtol=0, atol=1e-10)


# ---------------------------------------------------------------------------------------------
# Energy conservation of the free, frictionless arm


def integrate_free_arm(arm, x0, h, steps, c_sign=1.0, g_sign=1.0, every=100):
    """ODE3 (Bogacki-Shampine, fixed step) on M qdd = -C qd - G; energies every ``every`` steps.

    ``c_sign``/``g_sign`` = -1 deliberately corrupt the model (to show the check can fail).
    """
    masses = np.asarray(arm.masses)
    n = len(masses)

    def f(x):
        q, qd = x[:n], x[n:]
        rhs = -c_sign * coriolis_matrix(q, qd, arm) @ qd - g_sign * gravity(q, arm)
        return np.concatenate([qd, np.linalg.solve(mass_matrix(q, arm), rhs)])

    def energy(x):
        q, qd = x[:n], x[n:]
        y = joint_positions(q, arm)[1:, 1]
        return 0.5 * qd @ mass_matrix(q, arm) @ qd + arm.gravity * masses @ y

    x = np.array(x0, dtype=float)
    energies = [energy(x)]
    for step in range(steps):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.75 * h * k2)
        x = x + h * (2 / 9 * k1 + 1 / 3 * k2 + 4 / 9 * k3)
        if step % every == every - 1:
            energies.append(energy(x))
    return x, np.array(energies)


def energy_scale(arm, x0):
    """The potential passes through zero, so drift is measured against the energy's natural size:
    g sum m_i (l_1 + .. + l_i) (the largest |potential|, 3.5 J for the paper's arm) plus the
    initial kinetic energy."""
    n = arm.n_links
    q0, qd0 = x0[:n], x0[n:]
    return arm.gravity * np.dot(arm.masses, np.cumsum(arm.lengths)) + 0.5 * qd0 @ mass_matrix(q0, arm) @ qd0


def test_energy_conserved_by_free_motion():
    arm = PAPER
    rng = np.random.default_rng(70)
    x0 = np.concatenate(random_state(rng, 3, speed=2.0))
    x, energies = integrate_free_arm(arm, x0, h=1e-4, steps=20_000)  # 2 s
    drift = np.max(np.abs(energies - energies[0])) / energy_scale(arm, x0)
    # Bound 1e-6: ODE3's global error is O(h^3). From this state the light third link whips up to
    # ~50 rad/s; with the test's own integrator the drift was 2.6e-9 at h = 1e-4 and 2.1e-8 at
    # 2e-4 (the 8x of a third-order method), so 1e-6 is a ~400x margin for platform round-off,
    # while a wrong sign in C or G drifts by > 1e-3 within 0.2 s (next test).
    assert drift < 1e-6, f"relative energy drift {drift:.3e}"
    # The motion must actually have exercised the dynamics (not a near-rest state).
    assert np.linalg.norm(x[3:] - x0[3:]) > 0.1


@pytest.mark.parametrize("c_sign, g_sign", [(-1.0, 1.0), (1.0, -1.0)], ids=["C-flipped", "G-flipped"])
def test_energy_check_detects_a_corrupted_model(c_sign, g_sign):
    """The energy criterion is sensitive: corrupting C or G breaks conservation by >> 1e-6."""
    arm = PAPER
    rng = np.random.default_rng(70)
    x0 = np.concatenate(random_state(rng, 3, speed=2.0))
    _, energies = integrate_free_arm(arm, x0, h=1e-4, steps=2_000, c_sign=c_sign, g_sign=g_sign)
    assert np.max(np.abs(energies - energies[0])) / energy_scale(arm, x0) > 1e-4


# ---------------------------------------------------------------------------------------------
# Kinematics


@pytest.mark.parametrize("n", [2, 3, 4])
def test_joint_positions_and_forward_kinematics(n):
    rng = np.random.default_rng(80 + n)
    for _ in range(30):
        arm = random_arm(rng, n)
        q, _ = random_state(rng, n)
        pts = joint_positions(q, arm)
        assert pts.shape == (n + 1, 2)
        np.testing.assert_array_equal(pts[0], 0.0)
        np.testing.assert_allclose(pts[1:], fk_points(q, arm), rtol=0, atol=1e-14)
        # Link lengths are preserved.
        np.testing.assert_allclose(np.linalg.norm(np.diff(pts, axis=0), axis=1), arm.lengths, atol=1e-14)
        pose = forward_kinematics(q, arm)
        np.testing.assert_allclose(pose[:2], fk_points(q, arm)[-1], rtol=0, atol=1e-14)
        assert abs(pose[2] - np.sum(q)) < 1e-14


def test_forward_kinematics_known_configurations():
    l1, l2, l3 = PAPER.lengths
    np.testing.assert_allclose(forward_kinematics(np.zeros(3)), [l1 + l2 + l3, 0.0, 0.0], atol=1e-15)
    # Straight up: every link along +y.
    np.testing.assert_allclose(forward_kinematics(np.array([np.pi / 2, 0, 0])), [0.0, l1 + l2 + l3, np.pi / 2], atol=1e-15)
    # Elbow folded back: the second link returns along -x.
    np.testing.assert_allclose(forward_kinematics(np.array([0, np.pi, 0])), [l1 - l2 - l3, 0.0, np.pi], atol=1e-15)


@pytest.mark.parametrize("n", [2, 3, 4])
def test_pose_jacobian_matches_finite_differences(n):
    rng = np.random.default_rng(90 + n)
    h = 1e-6
    for _ in range(30):
        arm = random_arm(rng, n)
        q, _ = random_state(rng, n)
        J_fd = np.column_stack([
            (forward_kinematics(q + h * e, arm) - forward_kinematics(q - h * e, arm)) / (2 * h) for e in np.eye(n)
        ])
        # Positions ~1 m: round-off 1e-16/1e-6 = 1e-10, truncation h^2 |x'''|/6 ~ 1e-12.
        np.testing.assert_allclose(pose_jacobian(q, arm), J_fd, rtol=0, atol=1e-8)


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_ldl_factor_and_solve_against_numpy(n):
    """The closed loop solves M x = b with a square-root-free LDL^T factor: the factor must
    rebuild M (unit lower L, 1/D on its diagonal) and the solve must match numpy.linalg.solve."""
    from blf_gym.model.dynamics import ldl_factor_into, ldl_solve_factored

    rng = np.random.default_rng(n)
    mats = [mass_matrix(rng.uniform(-np.pi, np.pi, n), random_arm(rng, n)) for _ in range(3)]
    for _ in range(3):
        A = rng.normal(size=(n, n))
        mats.append(A @ A.T + 0.1 * np.eye(n))
    for M in mats:
        F = np.full(n * n, np.nan)
        ldl_factor_into(np.ascontiguousarray(M).ravel(), F)
        F = F.reshape(n, n)
        L = np.tril(F, -1) + np.eye(n)
        D = np.diag(1.0 / np.diag(F))
        np.testing.assert_allclose(L @ D @ L.T, M, rtol=1e-12, atol=1e-12 * np.abs(M).max())
        b = rng.normal(size=n)
        x = np.empty(n)
        ldl_solve_factored(F.ravel().copy(), b, x)
        np.testing.assert_allclose(x, np.linalg.solve(M, b), rtol=1e-10, atol=1e-12)
