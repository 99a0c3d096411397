"""Packed layouts are declared once: every entry lands where its declaration says."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from blf_gym import reward, simulate, status
from blf_gym.params import PLANT_TAIL, DeadZoneParams, ForceParams, FrictionParams, SimParams, plant_length, preset


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
    # the kernel's offsets come from the same tuple
    assert simulate._UMAX == PLANT_TAIL.index("max_torque") and simulate._ONSET == PLANT_TAIL.index("onset")


def test_status_and_sums_columns_come_from_their_declarations():
    assert status.N_STATUS == len(status.STATUS_COLUMNS)
    assert status.STATUS_COLUMNS[status.ST_FIRST_VIOL] == "first_violating_step"
    assert reward.SUM_E2_JOINT == len(reward.SUM_COLUMNS)
    # a run's status and sums land in the named columns
    sc = preset("paper-0.5hz", duration=4.0)
    loop = simulate.ClosedLoop([sc], "lesobc", threads=1)
    rec, nrec, st = loop.advance(sc.sim.n_steps, record_samples=sc.sim.n_samples)
    e1 = rec[0, : nrec[0], 5, :]
    assert st[0, status.ST_STEPS] == sc.sim.n_steps
    assert loop.sums[0, reward.SUM_SAMPLES] == nrec[0] == sc.sim.n_samples
    np.testing.assert_allclose(loop.sums[0, reward.SUM_E2_JOINT:], np.sum(e1 ** 2, axis=0), rtol=1e-12)
    viol = (e1 >= rec[0, : nrec[0], 6, :]) | (e1 <= -rec[0, : nrec[0], 7, :])
    assert st[0, status.ST_VIOL_SAMPLES] == int(viol.any(axis=1).sum()) > 0
