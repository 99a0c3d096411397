"""The NMPC (baselines/mpc.py) and the preview it reads: its model against the kernel's dynamics and
plant, tracking on the nominal plant against BC, its output constraints, a forced solver failure,
and the registered policy through gym.make and SB3's evaluate_policy.

The solver is built without C code generation here (``compiled=False``, no compiler run) and with a
short horizon, so each solve takes tens of ms."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401  (registers the env)
from blf_gym.model.dynamics import coriolis_matrix, gravity, mass_matrix
from blf_gym.envs.observation import PREVIEW_EXTRAS, PREVIEW_POINTS, PREVIEW_STEP, observation_index, observation_layout
from blf_gym.model.params import BoundParams, DeadZoneParams, ForceParams, FrictionParams, preset

ca = pytest.importorskip("casadi")

from baselines.mpc import NMPC, NMPCParams, NMPCPolicy, casadi_dynamics  # noqa: E402


def test_the_preview_gives_the_reference_and_bounds_the_env_shows_later():
    env = gym.make("PlanarBLF-v0", scenario="paper-0.5hz", observation_extras=PREVIEW_EXTRAS)
    ix = observation_index(3, False, PREVIEW_EXTRAS)
    assert env.observation_space.shape == (len(observation_layout(3, False, PREVIEW_EXTRAS)),)
    assert ix["q_d_preview"].stop - ix["q_d_preview"].start == 3 * PREVIEW_POINTS
    obs, _ = env.reset(seed=3)
    first = obs.copy()
    rng = np.random.default_rng(0)
    for k in range(1, 13):  # the env's control period is PREVIEW_STEP: step k is preview point k
        obs, *_ = env.step(rng.uniform(-0.1, 0.1, 3).astype(np.float32))
        np.testing.assert_array_equal(obs[ix["q_d"]], first[ix["q_d_preview"]].reshape(-1, 3)[k - 1])
        np.testing.assert_array_equal(obs[ix["qd_d"]], first[ix["qd_d_preview"]].reshape(-1, 3)[k - 1])
        assert obs[ix["k_a"]][0] == first[ix["k_a_preview"]][k - 1]
        assert obs[ix["k_b"]][0] == first[ix["k_b_preview"]][k - 1]
    # a preview changes over time: point 1 now is not point 1 at the start
    assert not np.array_equal(obs[ix["q_d_preview"]][:3], first[ix["q_d_preview"]][:3])
    assert PREVIEW_STEP * PREVIEW_POINTS == pytest.approx(0.3)


def test_the_casadi_model_is_the_kernels_nominal_arm():
    """Derived from the Lagrangian here, checked against blf_gym.model.dynamics's M, C and G, and the
    friction against blf_gym.model.uncertainty's."""
    from blf_gym.model.uncertainty import friction

    fp = FrictionParams()
    bare, rough = casadi_dynamics(), casadi_dynamics(friction=fp)
    rng = np.random.default_rng(1)
    for _ in range(20):
        q, qd, u, d = rng.uniform(-3, 3, 3), rng.uniform(-5, 5, 3), rng.uniform(-50, 50, 3), rng.uniform(-9, 9, 3)
        rest = u - coriolis_matrix(q, qd) @ qd - gravity(q)
        fr = np.array([friction(v, fp.viscous, fp.coulomb, fp.tanh_slope) for v in qd])
        for f, want in ((bare, np.linalg.solve(mass_matrix(q), rest) + d),
                        (rough, np.linalg.solve(mass_matrix(q), rest - fr) + d)):
            got = np.asarray(f(np.concatenate([q, qd]), u, d)).ravel()
            np.testing.assert_allclose(got[:3], qd, rtol=0, atol=1e-12)
            np.testing.assert_allclose(got[3:], want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("n", [2, 5, 7])
def test_the_casadi_model_is_the_kernels_on_every_member_of_the_task_family(n):
    # the second model cross-checked against the package's dynamics on the task family's arms
    # (blf_gym.model.family), whose mass matrix tests/test_dynamics.py checks against Pinocchio
    from blf_gym.model.family import family_arm

    arm = family_arm(n)
    f = casadi_dynamics(arm)
    rng = np.random.default_rng(n)
    for _ in range(10):
        q, qd, u, d = rng.uniform(-3, 3, n), rng.uniform(-5, 5, n), rng.uniform(-50, 50, n), rng.uniform(-9, 9, n)
        want = np.linalg.solve(mass_matrix(q, arm), u - coriolis_matrix(q, qd, arm) @ qd - gravity(q, arm)) + d
        got = np.asarray(f(np.concatenate([q, qd]), u, d)).ravel()
        np.testing.assert_allclose(got[:n], qd, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[n:], want, rtol=1e-9, atol=1e-9)


def _nominal(freq: float = 0.5, wide: bool = True, duration: float = 2.0):
    """The paper preset without friction, dead-zone or force: the arm as the model has it."""
    sc = preset("paper-0.5hz" if freq == 0.5 else "paper-0.1hz")
    kw = dict(friction=FrictionParams(viscous=0.0, coulomb=0.0),
              dead_zone=DeadZoneParams(slope_right=1.0, slope_left=1.0, break_right=0.0, break_left=0.0),
              force=ForceParams(wrench=(0.0, 0.0, 0.0)), sim=dataclasses.replace(sc.sim, duration=duration))
    if wide:
        kw["bounds"] = BoundParams(upper_amplitude=0.0, upper_floor=1.0, lower_amplitude=0.0, lower_floor=1.0)
    return dataclasses.replace(sc, **kw)


def _frictional(duration: float = 2.0):
    """The paper preset with its friction but no dead-zone or force: the plant the default model
    (with the nominal friction) has."""
    sc = preset("paper-0.5hz")
    return dataclasses.replace(
        sc, dead_zone=DeadZoneParams(slope_right=1.0, slope_left=1.0, break_right=0.0, break_left=0.0),
        force=ForceParams(wrench=(0.0, 0.0, 0.0)), sim=dataclasses.replace(sc.sim, duration=duration))


_NO_FRICTION = dict(friction=FrictionParams(viscous=0.0, coulomb=0.0), substeps=1)
"""The model of the friction-free plant of :func:`_nominal` (RK4 needs no substeps without it)."""


def _open_loop(scenario, torques, steps=10):
    """The plant's true states after each torque held over 10 ms, from its reset state."""
    env = gym.make("PlanarBLF-v0", scenario=scenario, controller="none", control_period=0.01,
                   terminate_on_violation=False)
    env.reset(seed=0)
    x0 = env.unwrapped.core.loop.X[0, :6].copy()
    out = []
    for u in torques[:steps]:
        env.step((u / 150).astype(np.float32))
        out.append(env.unwrapped.core.loop.X[0, :6].copy())
    return x0, np.array(out)


@pytest.mark.parametrize("frictional", [False, True])
def test_the_prediction_matches_the_kernels_plant(frictional):
    """Torques held over 10 ms: the model's RK4 steps against the kernel's ODE3 at 0.1 ms, within
    1e-4 rad over 10 intervals, on the friction-free plant (one RK4 step per interval: its error at
    these torques is about 1e-7 rad per interval) and on the plant with the paper's friction (ten
    steps of 1 ms, the default: about 4e-5 rad). Without its friction the model is wrong by over
    0.1 rad on the frictional plant within those 100 ms: the friction's mode on the light third link
    sets the arm's response to a held torque."""
    sc = _frictional() if frictional else _nominal()
    nmpc = NMPC(NMPCParams(horizon=10, **({} if frictional else _NO_FRICTION)), compiled=False)
    x0, _ = _open_loop(sc, np.zeros((0, 3)))
    # gravity's torque at the start plus up to 2 N m: the size of the NMPC's own torques
    torques = gravity(x0[:3]) + np.random.default_rng(2).uniform(-2, 2, (10, 3))
    _, true = _open_loop(sc, torques)
    pred = nmpc.predict_states(x0, torques)
    np.testing.assert_allclose(pred[:, :3], true[:, :3], rtol=0, atol=1e-4)
    assert np.abs(pred[-1, :3] - x0[:3]).max() > 1e-3  # the torques moved the arm
    if frictional:
        bare = NMPC(NMPCParams(horizon=10, **_NO_FRICTION), compiled=False).predict_states(x0, torques)
        assert np.abs(bare[:, :3] - true[:, :3]).max() > 0.1


def test_the_estimator_finds_the_velocity_and_a_constant_disturbance():
    """The NMPC's extended Kalman filter on the frictional plant, from angles alone at 10 ms: the
    velocity it estimates after 30 samples is the plant's to 0.02 rad/s, although it starts from zero
    velocity and a wrong model (the plant's friction is doubled, a disturbance the estimate absorbs,
    so it must not drift either)."""
    from baselines.mpc import _Arm, _estimate

    sc = _frictional()
    sc = dataclasses.replace(sc, friction=FrictionParams(viscous=1.0, coulomb=0.4))
    nmpc = NMPC(NMPCParams(horizon=10), compiled=False)
    x0, _ = _open_loop(sc, np.zeros((0, 3)))
    torques = gravity(x0[:3]) + 0.5 * np.sin(np.arange(40)[:, None] * 0.3 + np.arange(3))  # a slow sweep
    _, true = _open_loop(sc, torques, 40)
    arm = _Arm()
    _estimate(nmpc, arm, x0[:3], np.zeros(3))
    errs = []
    for k in range(40):
        z = _estimate(nmpc, arm, true[k, :3], torques[k])
        errs.append(np.abs(z[3:6] - true[k, 3:]).max())
    assert errs[0] > 0.05  # it did have something to find
    assert max(errs[30:]) < 0.02, errs


def _run(policy, scenario, steps):
    env = gym.make("PlanarBLF-v0", scenario=scenario, terminate_on_violation=False, **policy.env_kwargs)
    policy.check_env(env)
    obs, _ = env.reset(seed=0)
    errs, viol = [], 0
    for _ in range(steps):
        a, _ = policy.predict(obs)
        obs, _, _, _, info = env.step(a)
        errs.append(info["e1"])
        viol += int(np.any(info["g_upper"] > 0) or np.any(info["g_lower"] > 0))
    return np.array(errs), viol


def test_it_tracks_the_nominal_plant_better_than_bc():
    from blf_gym.kernel.simulate import simulate_batch
    from blf_gym.plugins.registry import make_controller

    sc = _nominal(wide=True, duration=1.0)
    errs, _ = _run(NMPCPolicy(NMPCParams(horizon=10, **_NO_FRICTION), compiled=False), sc, 100)
    rmse_mpc = np.sqrt(np.mean(errs[20:] ** 2, axis=0))
    tr = simulate_batch([sc], make_controller("bc"))[0]
    late = tr.signals["t"] >= 0.2  # the same window as the NMPC's (steps 20-99 of 10 ms)
    rmse_bc = np.sqrt(np.mean(tr.signals["e1"][late] ** 2, axis=0))
    assert np.all(rmse_mpc < rmse_bc), (rmse_mpc, rmse_bc)


def test_it_keeps_active_output_constraints_on_the_nominal_plant():
    """Weights that favour torque over tracking make the funnel the active limit: the soft
    constraints keep the error inside it, where the unconstrained optimum would leave it."""
    sc = _nominal(wide=False, duration=1.0)
    lazy = dict(horizon=10, q_weight=1e-2, qd_weight=0.0, u_weight=1.0, du_weight=0.0, **_NO_FRICTION)
    errs, viol = _run(NMPCPolicy(NMPCParams(**lazy), compiled=False), sc, 100)
    assert viol == 0
    errs_free, viol_free = _run(NMPCPolicy(NMPCParams(**lazy, penalty=0.0), compiled=False), sc, 100)
    assert viol_free > 0  # without the constraints the same weights break the bounds


def test_a_forced_solver_failure_takes_the_fallback_and_is_counted():
    pol = NMPCPolicy(NMPCParams(horizon=10, scheme="ipopt", max_iter=1, retry_every=1, **_NO_FRICTION),
                     compiled=False)
    errs, _ = _run(pol, _nominal(wide=True, duration=0.2), 20)
    rep = pol.report()
    assert rep["solves"] == 20 and rep["fallbacks"] == 20
    assert set(rep["statuses"]) == {"Maximum_Iterations_Exceeded"}
    assert np.all(np.isfinite(errs)) and np.abs(errs).max() < 0.2  # the computed-torque fallback holds it


def test_while_the_fallback_acts_a_solve_is_tried_only_every_retry_every_samples():
    """Every solve fails (one iteration): the samples 0, 5, 10, 15 try one and the others keep the
    computed-torque fallback without one; every sample is still a fallback."""
    pol = NMPCPolicy(NMPCParams(horizon=10, scheme="ipopt", max_iter=1, retry_every=5, **_NO_FRICTION),
                     compiled=False)
    errs, _ = _run(pol, _nominal(wide=True, duration=0.2), 20)
    rep = pol.report()
    assert rep["samples"] == 20 and rep["solves"] == 4 and rep["fallbacks"] == 20
    assert rep["statuses"] == {"Maximum_Iterations_Exceeded": 4, "Skipped_In_Fallback": 16}
    assert np.all(np.isfinite(errs)) and np.abs(errs).max() < 0.2
    with pytest.raises(ValueError, match="retry_every"):
        NMPCParams(retry_every=0)


def test_repeated_real_time_iterations_reach_ipopts_optimum():
    """An RTI step is one Gauss-Newton SQP step; repeated at the same sample from its own result it
    must converge to a KKT point of the problem, which IPOPT finds independently (the same
    Gauss-Newton Hessian, so the same problem). A wrong linearisation, sign or shift breaks it."""
    params = dict(horizon=8, **_NO_FRICTION)
    rti = NMPC(NMPCParams(scheme="rti", **params), 150.0, compiled=False)
    ipopt = NMPC(NMPCParams(scheme="ipopt", **params), 150.0, compiled=False)
    x0, d = np.array([0.1, 0.2, 0.3, 0.5, -0.4, 0.2]), np.array([0.3, -0.2, 0.1])
    qref = np.tile(x0[:3, None], (1, 9)) + np.linspace(0.0, 0.05, 9)  # a ramp the bounds make binding
    args = (x0, d, qref, np.full((3, 9), 0.6), np.full(9, 0.02), np.full(9, 0.02))
    u_opt, facts, _ = ipopt.solve(*args)
    assert facts["success"]
    warm, steps = None, []
    for _ in range(15):
        u, facts, new = rti.solve(*args, warm=warm)
        assert facts["success"], facts
        # solve() shifts the warm start by one interval (the next sample's); undo it to stay put
        warm = tuple(np.hstack([a[:, :1], a[:, :-1]]) if a.ndim == 2 else a for a in new)
        steps.append(u)
    assert np.abs(steps[0] - u_opt).max() > 1e-2  # one step from a cold start is not yet the optimum
    np.testing.assert_allclose(steps[-1], u_opt, atol=1e-4 * 150)


def test_a_failed_qp_is_reported_as_a_failure():
    """The RTI's QP solver reports no success on data it cannot solve (here a NaN state): solve()
    calls it a failure and gives no warm start, as for IPOPT, so the policy takes its fallback."""
    rti = NMPC(NMPCParams(scheme="rti", horizon=3, **_NO_FRICTION), 150.0, compiled=False)
    x0 = np.array([np.nan, 0.2, 0.3, 0.0, 0.0, 0.0])
    args = (x0, np.zeros(3), np.zeros((3, 4)), np.zeros((3, 4)), np.full(4, 0.1), np.full(4, 0.1))
    _, facts, warm = rti.solve(*args)
    assert not facts["success"] and warm is None


def test_a_diverged_estimator_restarts_at_the_measured_angle_and_is_counted():
    """A filter state that is no longer finite (the stress suite produced one) must not reach the
    torque: the arm's estimator starts again at y, the action is finite, and the restart counted."""
    pol = NMPCPolicy(NMPCParams(horizon=10, **_NO_FRICTION), compiled=False, workers=0)
    env = gym.make("PlanarBLF-v0", scenario=_nominal(wide=True, duration=0.2), **pol.env_kwargs)
    pol.check_env(env)
    obs, _ = env.reset(seed=0)
    a, _ = pol.predict(obs[None])
    obs, *_ = env.step(a[0])
    pol._arms[0].z[:] = np.nan  # what a diverged filter leaves
    a, _ = pol.predict(obs[None])
    assert np.all(np.isfinite(a)) and pol.report()["estimator_restarts"] == 1
    y = obs[pol._index["y"]]
    np.testing.assert_allclose(pol._arms[0].z[:3], y, atol=1e-6)  # it restarted at the measured angle
    a, _ = pol.predict(env.step(a[0])[0][None])
    assert np.all(np.isfinite(a)) and pol.report()["estimator_restarts"] == 1


def test_the_registered_policy_runs_under_evaluate_policy():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from blf_gym.plugins.registry import available_policies, make_policy

    assert "nmpc" in available_policies()
    pol = make_policy("nmpc", horizon=5, compiled=False, **_NO_FRICTION)
    venv = make_vec_env("PlanarBLF-v0", n_envs=1, seed=0,
                        env_kwargs=dict(scenario=_nominal(duration=0.1), **pol.env_kwargs))
    mean, _ = evaluate_policy(pol, venv, n_eval_episodes=1)
    assert np.isfinite(mean) and pol.report()["solves"] == 10
    with pytest.raises(ValueError, match="unknown NMPC parameter"):
        make_policy("nmpc", horizon_s=1.0)
    with pytest.raises(ValueError, match="NMPCParams.qp_solver"):
        NMPC(NMPCParams(qp_solver="no_such_solver"), 150.0, compiled=False)
    with pytest.raises(ValueError, match="horizon x sample_period"):
        NMPCParams(horizon=40)
    with pytest.raises(ValueError, match="control_period"):
        pol.check_env(gym.make("PlanarBLF-v0", observation_extras=PREVIEW_EXTRAS, control_period=0.02))
    with pytest.raises(ValueError, match="preview"):
        pol.check_env(gym.make("PlanarBLF-v0"))


def test_a_compiled_build_leaves_no_files_in_the_working_folder(tmp_path, monkeypatch):
    """CasADi's compiler writes its C, object and library files into the working folder unless told
    otherwise (they once piled up in the repository's root): the build uses a scratch folder, and
    what remains is the cache's one solver file, which solves as the uncompiled build does."""
    import shutil

    if not (shutil.which("gcc") or shutil.which("cc")):
        pytest.skip("no C compiler on the PATH")
    work, cache = tmp_path / "work", tmp_path / "cache"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.setenv("BLF_GYM_CACHE_DIR", str(cache))
    params = NMPCParams(horizon=3, **_NO_FRICTION)
    built = NMPC(params, 150.0, compiled=True)
    plain = NMPC(params, 150.0, compiled=False)
    x0, d = np.array([0.1, 0.2, 0.3, 0.0, 0.0, 0.0]), np.zeros(3)
    qref = np.tile(x0[:3, None], (1, 4)) + 0.01
    args = (x0, d, qref, np.zeros((3, 4)), np.full(4, 0.1), np.full(4, 0.1))
    u_built, facts, _ = built.solve(*args)
    u_plain, _, _ = plain.solve(*args)
    assert facts["success"]
    np.testing.assert_allclose(u_built, u_plain, rtol=1e-6, atol=1e-6)
    assert list(work.iterdir()) == []
    assert [p.suffix for p in (cache / "nmpc").iterdir()] == [".casadi"]
