"""Tests of blf_gym.model.reference.joint_reference: the paper's circle by inverse kinematics (docs/model.md section 2).

References used here are independent of the library: the Cartesian circle itself (through a
forward kinematics written in this file), docs/model.md section 2's closed form of the smooth branch,
finite differences of the returned angles and velocities, and docs/model.md's measured maxima.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from blf_gym.model.params import preset
from blf_gym.model.reference import joint_reference

PRESETS = ["paper-0.1hz", "paper-0.5hz"]
# k of docs/model.md section 2: cos(q2 / 2) = k cos(pi f t) on the smooth branch (law of cosines).
K_FOLD = np.sqrt(0.1 / 0.21)


def scenario(name: str, branch: str = "smooth"):
    sc = preset(name)
    return dataclasses.replace(sc, reference=dataclasses.replace(sc.reference, branch=branch))


def fk(q: np.ndarray, lengths) -> np.ndarray:
    """End-effector (x, y, phi) for relative angles q (..., 3), by the definition."""
    th = np.cumsum(q, axis=-1)
    x = np.sum(np.asarray(lengths) * np.cos(th), axis=-1)
    y = np.sum(np.asarray(lengths) * np.sin(th), axis=-1)
    return np.stack([x, y, th[..., -1]], axis=-1)


def folds(f: float, count: int = 4) -> np.ndarray:
    """Fold instants t = (2k + 1) / (2 f): the elbow is fully folded, J singular."""
    return (2 * np.arange(count) + 1) / (2 * f)


def dense_grid(f: float) -> np.ndarray:
    """Two periods of the smooth branch (period 2/f), plus points within 1e-3 s of every fold
    (including the fold instant itself and logarithmically close approaches from both sides)."""
    base = np.linspace(0.0, 4.0 / f, 8001)
    near = np.concatenate([-np.logspace(-9, -3, 13), [0.0], np.logspace(-9, -3, 13)])
    return np.sort(np.concatenate([base, (folds(f)[:, None] + near).ravel()]))


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("branch", ["smooth", "standard"])
@pytest.mark.parametrize("name", PRESETS)
def test_forward_kinematics_follows_the_circle(name, branch):
    sc = scenario(name, branch)
    f = sc.reference.frequency
    t = dense_grid(f)
    q, _, _ = joint_reference(t, sc)
    assert q.shape == t.shape + (3,)
    pose = fk(q, sc.arm.lengths)
    w = 2 * np.pi * f
    # Closed-form IK on O(1) quantities: only round-off remains.
    np.testing.assert_allclose(pose[:, 0], 0.4 + 0.2 * np.cos(w * t), rtol=0, atol=1e-12)
    np.testing.assert_allclose(pose[:, 1], 0.2 * np.sin(w * t), rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrap(pose[:, 2]), 0.0, rtol=0, atol=1e-12)


def test_output_shapes_follow_t():
    sc = scenario("paper-0.1hz")
    for t in (0.3, np.array(0.3), np.zeros(5), np.zeros((2, 4))):
        out = joint_reference(t, sc)
        assert len(out) == 3
        for a in out:
            assert a.shape == np.shape(t) + (3,)


@pytest.mark.parametrize("name", PRESETS)
def test_smooth_branch_matches_spec_closed_form(name):
    """docs/model.md section 2: q2 = 2 acos(k cos(pi f t)), q1 = atan2(w) - atan2(l2 s2, l1 + l2 c2), q3 = -q1 - q2."""
    sc = scenario(name)
    f = sc.reference.frequency
    l1, l2, l3 = sc.arm.lengths
    t = dense_grid(f)
    q, _, _ = joint_reference(t, sc)
    q2 = 2 * np.arccos(K_FOLD * np.cos(np.pi * f * t))
    wx = 0.4 + 0.2 * np.cos(2 * np.pi * f * t) - l3  # wrist = end effector - l3 along phi = 0
    wy = 0.2 * np.sin(2 * np.pi * f * t)
    q1 = np.arctan2(wy, wx) - np.arctan2(l2 * np.sin(q2), l1 + l2 * np.cos(q2))
    # acos loses precision near its ends (q2 near 0 never happens here, |k cos| <= 0.69), so
    # round-off stays ~1e-15; angles may differ by 2 pi, hence the wrap for q1 and q3.
    np.testing.assert_allclose(q[:, 1], q2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrap(q[:, 0] - q1), 0.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrap(q[:, 2] + q1 + q2), 0.0, rtol=0, atol=1e-12)
    # At the fold instants the elbow is exactly folded.
    qf, _, _ = joint_reference(folds(f), sc)
    np.testing.assert_allclose(qf[:, 1], np.pi, atol=1e-12)


@pytest.mark.parametrize("name", PRESETS)
def test_smooth_branch_derivatives_match_finite_differences(name):
    sc = scenario(name)
    f = sc.reference.frequency
    t = dense_grid(f)
    h = 1e-5
    qp, qdp, _ = joint_reference(t + h, sc)
    qm, qdm, _ = joint_reference(t - h, sc)
    _, qd, qdd = joint_reference(t, sc)
    fd_qd = (qp - qm) / (2 * h)
    fd_qdd = (qdp - qdm) / (2 * h)
    # Central-difference truncation is h^2/6 |x'''|. Each derivative multiplies by ~ (2 pi f) x
    # (a few, near the folds), so at 0.5 Hz |q'''| ~ 1e4 and |q''''| ~ 4e5: errors ~ 2e-7 and 7e-6,
    # i.e. < 3e-8 of the peaks (27.7 rad/s, 258 rad/s^2); round-off eps |q| / h ~ 1e-10.
    # 1e-6 of the peak leaves > 30x margin; a missing or wrong term would be O(1) of the peak.
    np.testing.assert_allclose(qd, fd_qd, rtol=0, atol=1e-6 * np.abs(qd).max())
    np.testing.assert_allclose(qdd, fd_qdd, rtol=0, atol=1e-6 * np.abs(qdd).max())
    # The analytic relations of the IK: q3 = phi_d - q1 - q2 with phi_d constant.
    np.testing.assert_allclose(qd.sum(axis=1), 0.0, atol=1e-12 * np.abs(qd).max())
    np.testing.assert_allclose(qdd.sum(axis=1), 0.0, atol=1e-12 * np.abs(qdd).max())


@pytest.mark.parametrize("name", PRESETS)
def test_smooth_branch_is_continuous_across_folds(name):
    sc = scenario(name)
    f = sc.reference.frequency
    eps = 1e-8
    tf = folds(f)
    before = joint_reference(tf - eps, sc)
    after = joint_reference(tf + eps, sc)
    # Peaks of the next derivative bound the change over 2 eps: docs/model.md section 2 for qd and qdd; |q'''| is
    # ~1e4 at 0.5 Hz (from the FD error budget below) and scales as f^3, so ~90 at 0.1 Hz.
    peak_qd, peak_qdd, peak_qddd = (5.6, 10.5, 200.0) if f < 0.3 else (28.0, 260.0, 2e4)
    for a, b, bound in zip(before, after, (peak_qd, peak_qdd, peak_qddd)):
        assert np.all(np.abs(a - b) <= 2 * eps * bound + 1e-12)
    # No 2 pi wrap anywhere on the dense grid either (q1 comes from an atan2).
    t = dense_grid(f)
    q, _, _ = joint_reference(t, sc)
    assert np.all(np.abs(np.diff(q, axis=0)) < 1.01 * np.diff(t)[:, None] * peak_qd + 1e-12)


@pytest.mark.parametrize("name", PRESETS)
def test_smooth_branch_has_period_two_over_f(name):
    """One lap of the circle mirrors the elbow (q2 -> 2 pi - q2); two laps return to the start."""
    sc = scenario(name)
    f = sc.reference.frequency
    t = np.linspace(0.0, 2.0 / f, 1001)
    q0, qd0, qdd0 = joint_reference(t, sc)
    q1, qd1, qdd1 = joint_reference(t + 2.0 / f, sc)
    # Argument reduction of cos/sin at t + 2/f costs ~eps * w t of phase; 1e-9 is ample.
    np.testing.assert_allclose(q1, q0, atol=1e-9)
    np.testing.assert_allclose(qd1, qd0, atol=1e-9 * 30)
    np.testing.assert_allclose(qdd1, qdd0, atol=1e-9 * 300)
    qh, _, _ = joint_reference(t + 1.0 / f, sc)
    np.testing.assert_allclose(qh[:, 1], 2 * np.pi - q0[:, 1], atol=1e-9)


@pytest.mark.parametrize(
    "name, max_qd, max_qdd",
    [("paper-0.1hz", 5.5, 10.3), ("paper-0.5hz", 27.7, 258.0)],
)
def test_smooth_branch_peaks_match_spec(name, max_qd, max_qdd):
    sc = scenario(name)
    f = sc.reference.frequency
    # One period (2/f) sampled at 1e-4 of it: the peaks are smooth maxima, so the grid misses them
    # by a relative O((pi * 1e-4)^2), far below the 2% tolerance given to docs/model.md's rounded values.
    t = np.linspace(0.0, 2.0 / f, 20001)
    _, qd, qdd = joint_reference(t, sc)
    assert np.abs(qd).max() == pytest.approx(max_qd, rel=0.02)
    assert np.abs(qdd).max() == pytest.approx(max_qdd, rel=0.02)


@pytest.mark.parametrize("name", PRESETS)
def test_standard_branch_range_and_velocity_jump_at_fold(name):
    sc = scenario(name, "standard")
    smooth = scenario(name)
    f = sc.reference.frequency
    t = dense_grid(f)
    q, _, _ = joint_reference(t, sc)
    assert np.all((q[:, 1] >= 0.0) & (q[:, 1] <= np.pi))
    # Where the smooth branch's elbow is in [0, pi] the two branches coincide.
    qs, _, _ = joint_reference(t, smooth)
    same = qs[:, 1] <= np.pi - 1e-6
    assert same.any() and (~same).any()
    np.testing.assert_allclose(wrap(q[same] - qs[same]), 0.0, atol=1e-12)

    # The jump, measured from the angles alone (one-sided differences on each side of the fold).
    tf = folds(f)[0]
    h = 1e-7
    qm, q0, qp = joint_reference(np.array([tf - h, tf, tf + h]), sc)[0]
    left = (q0 - qm) / h
    right = (qp - q0) / h
    # At the fold q2 = 2 acos(|k cos(pi f t)|) has slopes +-2 k pi f (k cos passes through 0 with
    # slope -k pi f): the elbow reaches pi and turns back. One-sided error O(h |qdd|) ~ 1e-4.
    slope = 2 * K_FOLD * np.pi * f
    assert left[1] == pytest.approx(slope, abs=1e-4 * (1 + 10 * f))
    assert right[1] == pytest.approx(-slope, abs=1e-4 * (1 + 10 * f))
    # The jump reaches ~6 rad/s (0.1 Hz) / ~30 rad/s (0.5 Hz) on q3 (docs/model.md: "up to 30 rad/s").
    assert np.abs(right - left).max() > 50 * f
    # The analytic velocities agree with those one-sided slopes on each side.
    _, qd, _ = joint_reference(np.array([tf - 1e-6, tf + 1e-6]), sc)
    np.testing.assert_allclose(qd[0], left, atol=1e-3 * (1 + 10 * f))
    np.testing.assert_allclose(qd[1], right, atol=1e-3 * (1 + 10 * f))


@pytest.mark.parametrize("name", PRESETS)
def test_standard_branch_derivatives_match_finite_differences_away_from_folds(name):
    sc = scenario(name, "standard")
    f = sc.reference.frequency
    t = np.linspace(0.0, 4.0 / f, 4001)
    t = t[np.min(np.abs(t[:, None] - folds(f)[None, :]), axis=1) > 1e-3]
    h = 1e-5
    qp, qdp, _ = joint_reference(t + h, sc)
    qm, qdm, _ = joint_reference(t - h, sc)
    _, qd, qdd = joint_reference(t, sc)
    # Same error budget as the smooth branch (the standard branch is a mirror image of it).
    np.testing.assert_allclose(qd, (qp - qm) / (2 * h), rtol=0, atol=1e-6 * np.abs(qd).max())
    np.testing.assert_allclose(qdd, (qdp - qdm) / (2 * h), rtol=0, atol=1e-6 * np.abs(qdd).max())
