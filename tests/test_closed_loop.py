"""The closed loop (plant + LESO + law under ODE3): the paper cases, the observer, the barrier
guard, step-size convergence and divergence detection."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from baselines.controllers import leso, proposed
from blf_gym.results.metrics import summarize
from blf_gym.model.params import preset
from blf_gym.kernel.simulate import ClosedLoop, SimulationDiverged, simulate


@pytest.fixture(scope="module")
def paper_runs():
    return {(p, c): simulate(p, c) for p in ("paper-0.1hz", "paper-0.5hz") for c in ("bc", "lesobc", "proposed")}


@pytest.mark.parametrize("name", ["paper-0.1hz", "paper-0.5hz"])
def test_proposed_law_never_leaves_the_bounds(paper_runs, name):
    traj = paper_runs[(name, "proposed")]
    assert not traj.diverged
    rec = summarize([traj], "proposed", "baseline", name, traj.dt)
    assert rec["violations"] == [0, 0, 0]
    # every integration step, not only the 1 ms samples
    assert traj.step_violations == 0
    assert rec["min_margin_deg"][0] > 0


def test_the_comparison_has_the_shape_spec_section_7_describes(paper_runs):
    # docs/model.md section 7 (an independent prototype): observer-based laws track to hundredths or tenths of
    # a degree; LESOBC breaks the bounds at 0.5 Hz; BC breaks them at 0.5 Hz.
    rm = {k: np.array(summarize([t], k[1], "baseline", k[0], t.dt)["rmse_deg"]) for k, t in paper_runs.items()}
    assert np.all(rm[("paper-0.1hz", "proposed")] < 0.2)
    assert np.all(rm[("paper-0.5hz", "proposed")] < 1.0)
    assert paper_runs[("paper-0.5hz", "lesobc")].step_violations > 0
    assert paper_runs[("paper-0.5hz", "bc")].step_violations > 0
    # the barrier term only helps: proposed beats LESOBC on every joint in both cases
    for p in ("paper-0.1hz", "paper-0.5hz"):
        assert np.all(rm[(p, "proposed")] < rm[(p, "lesobc")])


def test_signals_are_on_the_1ms_grid_and_consistent(paper_runs):
    traj = paper_runs[("paper-0.1hz", "proposed")]
    assert traj.t.shape == (30000,)
    np.testing.assert_allclose(np.diff(traj.t), 1e-3, rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj.e1, traj.q - traj.q_ref, atol=1e-15)
    # k_a, k_b are the paper's bounds
    np.testing.assert_allclose(traj.k_a[:, 0], 0.5 * np.exp(-0.6 * traj.t) + 0.02, rtol=1e-12)
    np.testing.assert_allclose(traj.k_b[:, 0], 0.6 * np.exp(-0.6 * traj.t) + 0.04, rtol=1e-12)
    # H(u) is the dead-zone of u
    from blf_gym.model.uncertainty import dead_zone_array

    np.testing.assert_allclose(traj.h_u, dead_zone_array(traj.u), atol=1e-12)
    # no residual, so the commanded torque is the law's
    np.testing.assert_array_equal(traj.u, traj.u_law)


def test_force_switches_on_at_20_s(paper_runs):
    # The step of f_ext shows up as a jump of the true lumped disturbance at t = 20 s.
    traj = paper_runs[("paper-0.1hz", "proposed")]
    i = int(round(20.0 / 1e-3))
    jump = np.abs(traj.x3[i + 1] - traj.x3[i - 2])
    typical = np.abs(np.diff(traj.x3[i - 200 : i - 2], axis=0)).max(axis=0)
    assert np.all(jump > 10 * typical)


def _observer_errors(k0: float) -> tuple[float, float]:
    sc = preset("paper-0.1hz", duration=4.0)
    traj = simulate(sc, "proposed", leso(k0=k0))
    sl = slice(1000, None)  # after the observer's initial transient
    e2 = np.sqrt(np.mean((traj.x2_hat[sl] - traj.qd[sl]) ** 2))
    e3 = np.sqrt(np.mean((traj.x3_hat[sl] - traj.x3[sl]) ** 2))
    assert np.all(np.isfinite(traj.x3_hat))
    return e2, e3


def test_leso_errors_are_bounded_and_shrink_as_k0_grows():
    # Theory (bandwidth-parametrised ESO): the estimation error scales like 1/k0^(3-i) of the
    # disturbance's rate, so it must fall monotonically as k0 rises.
    errs = [_observer_errors(k0) for k0 in (100.0, 200.0, 400.0)]
    e2 = [e[0] for e in errs]
    e3 = [e[1] for e in errs]
    assert e2[0] > e2[1] > e2[2]
    assert e3[0] > e3[1] > e3[2]
    assert e3[1] < 50.0  # rad/s^2: bounded, against a disturbance of order 10^2-10^3 rad/s^2


def _excursion_run(amplitude: float, joint: int = 2):
    """Run the proposed law to t = 10 s, then push one joint with a 30 ms residual pulse."""
    sc = preset("paper-0.1hz")
    loop = ClosedLoop([sc], "proposed", threads=1)
    loop.advance(100_000)
    res = np.zeros((1, 3))
    res[0, joint] = amplitude
    _, _, st_pulse = loop.advance(300, residual=res)
    rec, nrec, st = loop.advance(5000, record_samples=5000)
    r = rec[0, : nrec[0]]
    e = r[:, 5, joint]
    ka = r[:, 6, joint]
    kb = r[:, 7, joint]
    ratio = np.max(np.where(e > 0, e / ka, -e / kb))
    diverged = bool(st_pulse[0, 1] or st[0, 1])
    return ratio, diverged, r, loop


def test_barrier_guard_survives_an_error_forced_to_099_of_a_bound():
    # Find a pulse that takes the error to at least 0.99 of the bound (docs/model.md section 5), doubling it.
    amp = 0.5
    for _ in range(16):
        ratio, diverged, r, loop = _excursion_run(amp)
        assert not diverged, f"diverged with a {amp} N m pulse"
        if ratio >= 0.99:
            break
        amp *= 2.0
    assert ratio >= 0.99, "no pulse reached 0.99 of the bound"
    assert np.all(np.isfinite(r))
    assert np.all(np.isfinite(loop.X))
    # and the law brings it back inside within the 0.5 s recorded after the pulse
    assert abs(r[-1, 5, 2]) < 0.5 * r[-1, 6, 2]
    # A pulse four times larger pushes the error beyond the bound: still finite, no divergence.
    ratio, diverged, r, loop = _excursion_run(4 * amp)
    assert ratio > 1.0
    assert not diverged and np.all(np.isfinite(r))


@pytest.mark.parametrize("name", ["paper-0.1hz", "paper-0.5hz"])
def test_halving_the_step_changes_rmse_by_less_than_one_percent(paper_runs, name):
    coarse = summarize([paper_runs[(name, "proposed")]], "p", "baseline", name, 1e-4)["rmse_deg"]
    fine_traj = simulate(preset(name, dt=5e-5), "proposed")
    fine = summarize([fine_traj], "p", "baseline", name, 5e-5)["rmse_deg"]
    rel = np.abs(np.array(coarse) - np.array(fine)) / np.array(fine)
    assert np.all(rel < 0.01), rel


def test_paper_step_of_1ms_is_reported_as_divergence():
    traj = simulate(preset("paper-0.1hz", dt=1e-3), "proposed")
    assert traj.diverged
    # detected within SimParams.unstable_steps (100) steps of the start
    assert traj.diverged_at is not None and traj.diverged_at <= 0.1 + 1e-9
    assert "dt" in traj.message
    # what was recorded before the blow-up is kept, and is finite
    for name, arr in traj.signals.items():
        assert np.all(np.isfinite(arr)), name
    with pytest.raises(SimulationDiverged, match="diverged"):
        simulate(preset("paper-0.1hz", dt=1e-3), "proposed", raise_on_divergence=True)
    rec = summarize([traj], "proposed", "baseline", "paper-0.1hz", 1e-3)
    assert rec["diverged"] is True and rec["failure_rate"] == 1.0


@pytest.mark.parametrize("max_torque, code", [(150.0, 2), (1e12, 1)])
def test_divergence_kinds_and_state_never_holds_nan(max_torque, code):
    # With the default actuator limit an unstable step stays finite and is caught by the error
    # estimate (code 2); with an effectively unbounded actuator, as in the paper, the state blows up
    # within a few steps (code 1, docs/model.md section 6: "every controller ... blow up within 3 ms").
    sc = preset("paper-0.5hz", dt=1e-3, max_torque=max_torque)
    loop = ClosedLoop([sc], "lesobc", threads=1)
    _, _, st = loop.advance(1000)
    assert st[0, 1] == code
    if code == 1:
        assert st[0, 0] <= 5
    assert np.all(np.isfinite(loop.X))


def test_same_inputs_give_bit_identical_runs():
    a = simulate(preset("paper-0.5hz", duration=2.0), "proposed")
    b = simulate(preset("paper-0.5hz", duration=2.0), "proposed")
    for k in a.signals:
        np.testing.assert_array_equal(a.signals[k], b.signals[k])


def test_batch_with_threads_equals_single_runs():
    scs = [preset("paper-0.1hz", duration=1.0), preset("paper-0.5hz", duration=1.0),
           dataclasses.replace(preset("paper-0.5hz", duration=1.0), initial_error=(0.01, -0.02, 0.0))]
    loop = ClosedLoop(scs, "proposed", threads=2)
    rec, nrec, _ = loop.advance(10_000)
    for i, sc in enumerate(scs):
        single = ClosedLoop([sc], "proposed", threads=1)
        r1, n1, _ = single.advance(10_000)
        np.testing.assert_array_equal(rec[i, : nrec[i]], r1[0, : n1[0]])
        np.testing.assert_array_equal(loop.X[i], single.X[0])


@pytest.mark.parametrize("extra", [1, 10**6])
def test_a_batch_refuses_more_threads_than_the_process_may_use(extra):
    from blf_gym.model.params import usable_cores

    sc = preset("paper-0.1hz", duration=0.01)
    with pytest.raises(ValueError, match=r"ClosedLoop.threads must be an integer in \[1, %d\]" % usable_cores()):
        ClosedLoop([sc] * 4, "proposed", threads=usable_cores() + extra)
    with pytest.raises(ValueError, match="ClosedLoop.threads"):
        ClosedLoop([sc], "proposed", threads=0)
    assert ClosedLoop([sc], "proposed", threads=usable_cores()).threads == usable_cores()


def test_gains_are_validated():
    with pytest.raises(ValueError, match="K1"):
        proposed(K1=(1.0, 2.0))
    with pytest.raises(ValueError, match="barrier_clip"):
        proposed(barrier_clip=1.0)
    with pytest.raises(ValueError, match="k0"):
        leso(k0=-1.0)
    with pytest.raises(ValueError, match="unknown controller"):
        simulate("paper-0.1hz", "pid")
    with pytest.raises(ValueError, match="unknown controller gain"):
        proposed(K3=1.0)


def test_stateful_leso_recovers_velocity_and_disturbance_from_sampled_signals():
    # The thin LESO object, fed the measured angles and the commanded torque of a closed-loop run
    # on the 1 ms grid (held over each millisecond), must estimate the true velocity and the true
    # lumped disturbance: its errors are a small fraction of the signals (measured: x2 error
    # below 10 % of max |qd|, x3 RMS error below 4 % of the RMS of x3) and agree with the inner
    # observer's estimate.
    from baselines.leso import LESO

    tr = simulate(preset("paper-0.1hz", duration=5.0), "proposed")
    obs = LESO(k0=200.0)
    obs.reset(tr.q[0])
    x2, x3 = [], []
    for k in range(tr.n_samples):
        x2.append(obs.xhat[3:6].copy())
        x3.append(obs.xhat[6:9].copy())
        obs.step(tr.q[k], tr.u[k], 1e-3)
    x2, x3 = np.array(x2)[1000:], np.array(x3)[1000:]
    qd, x3_true = tr.qd[1000:], tr.x3[1000:]
    assert np.all(np.abs(x2 - qd).max(axis=0) < 0.1 * np.abs(qd).max(axis=0))
    rms = np.sqrt(np.mean((x3 - x3_true) ** 2, axis=0))
    assert np.all(rms < 0.04 * np.sqrt(np.mean(x3_true ** 2, axis=0)))
    assert np.all(np.abs(x3 - tr.x3_hat[1000:]).max(axis=0) < 1.0)
    with pytest.raises(ValueError, match="k0"):
        LESO(k0=0.0)


def test_the_cache_keeps_every_kernel_and_drops_only_stale_builds_of_the_same_one(tmp_path):
    # before: the stale-cache cleanup globbed simulate.{prefix}*, and the unfiltered kernel's prefix
    # (advance__n3__proposed__leso__) also matched both barrier kernels, so building one deleted the
    # others and every blf-eval run with the certified agent recompiled (about 30 s each)
    from blf_gym.kernel.simulate import remove_stale_cache

    new, old = "0123456789", "abcdef0123"
    pre = "advance1__n3__proposed__leso__"
    names = {  # a build's module and lock beside numba's cache files in __pycache__
        f"{pre}{new}.py": True, f"{pre}{new}.compile.lock": True,                               # this build: kept
        f"__pycache__/{pre}{new}.advance-329.py311.nbi": True,
        f"__pycache__/{pre}{new}.advance-329.py311.1.nbc": True,
        f"{pre}{old}.py": False, f"{pre}{old}.compile.lock": False,                             # a stale build: gone
        f"__pycache__/{pre}{old}.advance-329.py311.nbi": False,
        f"__pycache__/{pre}{old}.advance-329.py311.1.nbc": False,
        f"advance1__n3__proposed__leso__barrier__{old}.py": True,                               # other kernels
        f"__pycache__/advance1__n3__proposed__leso__barrier__{old}.advance-329.py311.nbi": True,
        f"advance1__n3__proposed__leso__barrier_plain__{old}.py": True,
        f"advance1__n3__proposed__leso2__{old}.py": True,
        f"advance4__n3__proposed__leso__{old}.py": True,                                        # the other width
        f"glue_proposed__leso__n3__{old}ab.py": True,
    }
    (tmp_path / "__pycache__").mkdir()
    for name in names:
        (tmp_path / name).write_text("x")
    gone = remove_stale_cache(tmp_path, pre, new)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in gone) == sorted(k for k, keep in names.items() if not keep)
    left = sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file())
    assert left == sorted(k for k, keep in names.items() if keep)


def test_building_one_kernel_leaves_the_others_in_the_disk_cache():
    # the real cache: the unfiltered law, then both barrier kernels, then the law again; every
    # kernel's index file is still on disk at the end
    from pathlib import Path

    from blf_gym.model.params import preset
    from blf_gym.kernel.simulate import ClosedLoop

    sc = preset("paper-0.1hz", duration=0.01)
    loops = [ClosedLoop([sc], "proposed", threads=1),
             ClosedLoop([sc], "proposed", threads=1, residual_filter="barrier"),
             ClosedLoop([sc], "proposed", threads=1, residual_filter="barrier", plain=True)]
    for loop in loops:  # each compiled (or loaded) and run once, so its cache is written
        loop.advance(10)
    ClosedLoop([sc], "proposed", threads=1).advance(10)
    for loop in loops:
        assert Path(loop._kernel._cache._cache_file._index_path).is_file(), loop._kernel.__name__
    # the filter's two uses, on a residual and on a plain agent's whole torque, are one build (plain
    # is a runtime flag), and the flag is real: the same input is filtered differently
    assert loops[1]._kernel is loops[2]._kernel and loops[0]._kernel is not loops[1]._kernel
    u = []
    for loop in loops[1:]:
        loop.set_scenarios([sc])
        loop.advance(20, residual=np.full((1, 3), 5.0))
        u.append(loop.last.copy())
    assert not np.array_equal(u[0], u[1])
    with pytest.raises(ValueError, match="plain=True needs a residual filter"):
        ClosedLoop([sc], "proposed", threads=1, plain=True)
