"""Packed layouts are declared once: every entry lands where its declaration says."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from blf_gym.kernel import reward, simulate, status
from blf_gym.model.bounds import error_bounds
from blf_gym.model.params import PLANT_TAIL, DeadZoneParams, ForceParams, FrictionParams, SimParams, plant_length, preset
from blf_gym.model.reference import joint_reference


def test_the_plant_tail_is_written_where_its_declaration_says():
    sc = replace(preset("paper-0.1hz"), friction=FrictionParams(viscous=0.11, coulomb=0.22, tanh_slope=3.3),
                 dead_zone=DeadZoneParams(slope_right=1.1, slope_left=1.3, break_right=0.4, break_left=-0.5),
                 force=ForceParams(wrench=(7.0, 8.0, 9.0), onset=12.5),
                 sim=SimParams(max_torque=99.0, divergence_limit=5e5, error_rtol=0.3, error_atol=0.04,
                               unstable_steps=77))
    packed = sc.pack_plant()
    n = sc.arm.n_links
    assert packed.shape == (plant_length(n),)
    expected = {"viscous": 0.11, "coulomb": 0.22, "tanh_slope": 3.3, "slope_right": 1.1, "slope_left": 1.3,
                "break_right": 0.4, "break_left": -0.5, "f_x": 7.0, "f_y": 8.0, "moment": 9.0, "onset": 12.5,
                "max_torque": 99.0, "divergence_limit": 5e5, "error_rtol": 0.3, "error_atol": 0.04,
                "unstable_steps": 77.0}
    assert set(expected) == set(PLANT_TAIL)
    for name, value in expected.items():
        assert packed[2 * n + 1 + PLANT_TAIL.index(name)] == value, name


def _run(sc, controller="proposed"):
    loop = simulate.ClosedLoop([sc], controller, threads=1)
    rec, nrec, st = loop.advance(sc.sim.n_steps, record_samples=sc.sim.n_samples)
    return {c: rec[0, : nrec[0], i, :] for i, c in enumerate(simulate.CHANNELS)}, st[0], loop


def test_the_kernel_reads_the_actuator_cap_where_the_plant_tail_puts_it():
    # a cap far below what BC asks for at the start: the applied torque reaches it exactly and never
    # passes it, and the saturation flag and count say so (a kernel reading another offset of the
    # packed plant would clip at another value)
    base = preset("paper-0.5hz", duration=0.5)
    sc = replace(base, sim=replace(base.sim, max_torque=2.5))
    ch, st, _ = _run(sc, "bc")
    u = ch["u"]
    assert np.max(np.abs(u)) == 2.5
    assert np.all((np.abs(u) == 2.5) == (ch["saturated"] != 0))
    assert st[status.ST_SAT_STEPS] > 0


def test_the_kernel_reads_the_force_onset_where_the_plant_tail_puts_it():
    # the same episode with and without a force that switches on at 1.2 s: identical to the bit
    # before the onset, different after it
    base = preset("paper-0.5hz", duration=2.0)
    off, _, _ = _run(replace(base, force=ForceParams(wrench=(0.0, 0.0, 0.0), onset=1.2)))
    on, _, _ = _run(replace(base, force=ForceParams(wrench=(30.0, -20.0, 3.0), onset=1.2)))
    t = off["t"][:, 0]
    before, after = t < 1.2 - 1e-3, t > 1.25
    assert np.array_equal(off["q"][before], on["q"][before])
    assert np.all(np.any(off["q"][after] != on["q"][after], axis=1))


def test_every_recorded_channel_holds_what_its_name_says():
    # against references computed outside the kernel: the sample clock, the joint reference and
    # bounds (blf_gym.model's NumPy functions), the error's definition, and the actuator cap
    sc = preset("paper-0.1hz", duration=1.0)
    ch, _, _ = _run(sc)
    t = ch["t"][:, 0]
    np.testing.assert_array_equal(t, (np.arange(t.size) * sc.sim.steps_per_sample) * sc.sim.dt)  # step k at k dt
    assert np.all(ch["t"] == t[:, None])
    q_ref, qd_ref, _ = joint_reference(t, sc)
    np.testing.assert_allclose(ch["q_ref"], q_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ch["qd_ref"], qd_ref, rtol=0, atol=1e-10)
    k_a, k_b = error_bounds(t, sc.bounds)
    np.testing.assert_allclose(ch["k_a"], np.broadcast_to(np.asarray(k_a).reshape(-1, 1), ch["k_a"].shape), atol=1e-15)
    np.testing.assert_allclose(ch["k_b"], np.broadcast_to(np.asarray(k_b).reshape(-1, 1), ch["k_b"].shape), atol=1e-15)
    np.testing.assert_array_equal(ch["e1"], ch["q"] - ch["q_ref"])
    assert np.all(np.abs(ch["u"]) <= sc.sim.max_torque)
    # the LESO's estimates are its states: x1_hat follows the measured angle y closely
    assert np.max(np.abs(ch["x1_hat"] - ch["y"])[t > 0.1]) < 1e-3
    # the velocity channel integrates to the angle channel (the trapezoid rule over each 1 ms
    # sample, once the start's transient has passed: its error is then about 1e-8 rad a sample,
    # against steps of about 4e-4 rad)
    h, late = sc.sim.sample_period, t[1:] > 0.1
    trapezoid = (ch["q"][1:] - ch["q"][:-1]) - 0.5 * h * (ch["qd"][1:] + ch["qd"][:-1])
    assert np.max(np.abs(trapezoid[late])) < 1e-6


def test_status_and_sums_land_in_the_named_columns():
    sc = preset("paper-0.5hz", duration=4.0)
    loop = simulate.ClosedLoop([sc], "lesobc", threads=1)
    rec, nrec, st = loop.advance(sc.sim.n_steps, record_samples=sc.sim.n_samples)
    e1 = rec[0, : nrec[0], 5, :]
    assert st[0, status.ST_STEPS] == sc.sim.n_steps
    assert loop.sums[0, reward.SUM_SAMPLES] == nrec[0] == sc.sim.n_samples
    np.testing.assert_allclose(loop.sums[0, reward.SUM_E2_JOINT:], np.sum(e1 ** 2, axis=0), rtol=1e-12)
    viol = (e1 >= rec[0, : nrec[0], 6, :]) | (e1 <= -rec[0, : nrec[0], 7, :])
    assert st[0, status.ST_VIOL_SAMPLES] == int(viol.any(axis=1).sum()) > 0
