"""The Gymnasium environments ``PlanarBLF-v0`` / ``PlanarBLFResidual-v0`` and the native vector env.

Covers API conformance (Gymnasium's and SB3's checkers), registration, determinism, the zero
residual against the reproduction (``simulate``), termination at the first violating integration
step, vector == single envs, the reward contract, the applied torque and what the observer sees,
a fuzz over the documented safe ranges, input validation, the privileged observation, rendering
and truncation. Reference values come from independent computations (the trajectory of
``simulate``, a bare ``ClosedLoop``, the reference and bounds functions, the documented formulas),
never from the env's own output.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401  (registers the ids)
from blf_gym.model.bounds import error_bounds
from blf_gym.envs.envcore import RewardWeights, observation_layout
from blf_gym.results.metrics import violation_mask
from blf_gym.model.params import preset
from blf_gym.model.reference import joint_reference
from blf_gym.envs.scenarios import SAFE_RANGES, VARIATIONS
from blf_gym.kernel.simulate import ClosedLoop, simulate
from blf_gym.envs.vector import PlanarBLFVectorEnv

IDS = ("PlanarBLF-v0", "PlanarBLFResidual-v0")
ZERO = np.zeros(3, dtype=np.float32)
REPO = Path(__file__).resolve().parents[1]


def _obs_index(prefix: str, privileged: bool = False) -> list[int]:
    """Indices of the observation entries whose documented name starts with ``prefix``."""
    return [i for i, row in enumerate(observation_layout(3, privileged)) if row[0].startswith(prefix)]


def assert_same(a, b, path: str = "info") -> None:
    """Bit-for-bit equality of nested infos: dicts, sequences, arrays, scalars, None, scenarios."""
    if isinstance(a, dict) or isinstance(b, dict):
        assert isinstance(a, dict) and isinstance(b, dict), path
        assert a.keys() == b.keys(), path
        for k in a:
            assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), path
        for k, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{k}]")
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=path, strict=True)
    else:
        assert type(a) is type(b) and a == b, (path, a, b)


# --------------------------------------------------------------------------------------------
# 1. checkers


@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_and_sb3_env_checkers_pass_with_warnings_as_errors(env_id):
    from gymnasium.utils.env_checker import check_env as gym_check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make(env_id, render_mode="rgb_array")
        gym_check_env(env.unwrapped, skip_render_check=False)
        env.close()
        env = gym.make(env_id)
        sb3_check_env(env.unwrapped, warn=True)
        env.close()


# --------------------------------------------------------------------------------------------
# 2. registration


def test_make_with_module_prefix_in_a_fresh_interpreter(tmp_path):
    code = (
        "import sys\n"
        "import gymnasium as gym\n"
        "assert 'blf_gym' not in sys.modules\n"
        "env = gym.make('blf_gym:PlanarBLF-v0')\n"
        "obs, info = env.reset(seed=0)\n"
        "obs, r, term, trunc, info = env.step(env.action_space.sample())\n"
        "print(type(env.unwrapped).__module__, type(env.unwrapped).__name__, obs.shape, env.spec.id)\n"
    )
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["blf_gym.envs.env", "PlanarBLFEnv", "(31,)", "PlanarBLF-v0"]


def test_make_vec_returns_the_native_vector_env():
    envs = gym.make_vec("PlanarBLFResidual-v0", num_envs=3)
    try:
        assert isinstance(envs, PlanarBLFVectorEnv)
        assert envs.num_envs == 3
        assert envs.core.controller.name == "proposed"  # the residual id's kwargs reach the vector env
        obs, info = envs.reset(seed=0)
        assert obs.shape == (3, 31) and obs.dtype == np.float32
        assert envs.observation_space.contains(obs)
        obs, rew, term, trunc, info = envs.step(np.zeros((3, 3), dtype=np.float32))
        assert obs.shape == (3, 31) and rew.shape == (3,) and term.shape == (3,) and trunc.shape == (3,)
        assert info["_time"].all()
    finally:
        envs.close()


# --------------------------------------------------------------------------------------------
# 3. determinism


def _run(env, seed: int, actions: np.ndarray) -> list:
    """reset(seed) then the actions; on an episode end, reset() without a seed and go on."""
    obs, info = env.reset(seed=seed)
    out: list = [("reset", obs, info, env.unwrapped.scenario)]
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        out.append(("step", obs, r, term, trunc, info))
        if term or trunc:
            obs, info = env.reset()
            out.append(("reset", obs, info, env.unwrapped.scenario))
    return out


def test_same_seed_same_actions_are_bit_identical_and_other_seeds_differ():
    kw = dict(scenario="randomized", angle_noise_std=1e-4, duration=0.4)
    actions = np.random.default_rng(7).uniform(-1, 1, (100, 3)).astype(np.float32)
    a = gym.make("PlanarBLFResidual-v0", **kw)
    b = gym.make("PlanarBLFResidual-v0", **kw)
    ra = _run(a, 123, actions)
    # the randomized suite redraws angle_noise_std (in [0, 1e-4]) over the constructor's value;
    # either way the measurement noise stream is exercised
    assert a.unwrapped.scenario.angle_noise_std > 0
    rb = _run(b, 123, actions)
    assert len(ra) == len(rb)
    assert sum(r[0] == "reset" for r in ra) >= 3  # several episodes, seeded and unseeded resets
    for x, y in zip(ra, rb):
        assert_same(x, y, "run")
    # the same env reset with the same seed again: nothing carries over from the last episode
    assert_same(_run(a, 123, actions), ra, "rerun")

    a.reset(seed=123)
    sc123 = a.unwrapped.scenario
    b.reset(seed=124)
    assert b.unwrapped.scenario != sc123
    assert b.unwrapped.scenario.arm.masses != sc123.arm.masses
    a.reset(seed=123)
    assert a.unwrapped.scenario == sc123


# --------------------------------------------------------------------------------------------
# 4. zero residual == the reproduction


@pytest.mark.parametrize("scenario,controller", [("paper-0.1hz", "proposed"), ("paper-0.5hz", "lesobc")])
def test_zero_residual_reproduces_simulate_bit_for_bit(scenario, controller):
    traj = simulate(scenario, controller)
    assert not traj.diverged
    w = RewardWeights()  # the shaped reward's terms (the default reward is the score term alone)
    env = gym.make("PlanarBLFResidual-v0", scenario=scenario, controller=controller,
                   terminate_on_violation=False, reward_weights=w)
    env.reset(seed=0)
    loop = env.unwrapped.core.loop
    umax = env.unwrapped.scenario.sim.max_torque
    spp = 10  # 1 ms samples per 10 ms agent step (the default control_period)
    n_samples = traj.q.shape[0]
    mask = violation_mask(traj.e1, traj.k_a, traj.k_b).any(axis=1)
    # the reward's normalized error, by the bound on the error's side (RewardWeights docstring)
    en = np.where(traj.e1 >= 0, traj.e1 / traj.k_a, traj.e1 / traj.k_b)
    np.testing.assert_array_equal(loop.X[0, :3], traj.q[0])
    k = 0
    violating = 0
    while True:
        obs, r, term, trunc, info = env.step(ZERO)
        k += 1
        window = slice(spp * (k - 1), spp * k)  # this step's samples: t_start .. t_end - 1 ms
        if spp * k < n_samples:  # trajectory sample k*spp is the state at t = k * 10 ms
            np.testing.assert_array_equal(loop.X[0, :3], traj.q[spp * k], err_msg=f"agent step {k}")
        assert info["violating_samples"] == mask[window].sum(), k
        violating += info["violating_samples"]
        tracking = -w.tracking * np.mean(en[window] ** 2)
        torque = -w.torque * np.mean((traj.u[window] / umax) ** 2)
        assert info["reward_info"]["tracking"] == pytest.approx(tracking, rel=1e-9, abs=1e-300)
        assert info["reward_info"]["torque"] == pytest.approx(torque, rel=1e-9, abs=1e-300)
        if term or trunc:
            break
    assert trunc and not term
    assert k == n_samples // spp
    assert info["time"] == pytest.approx(traj.t[-1] + 1e-3)
    assert violating == mask.sum()
    if controller == "lesobc":
        assert violating > 0  # docs/model.md section 7: LESOBC breaks the bounds at 0.5 Hz, so the count is tested


# --------------------------------------------------------------------------------------------
# 5. termination at the first violating integration step


@pytest.mark.parametrize("action", [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.5, 0.0, 0.0]])
def test_termination_at_the_first_violating_integration_step(action):
    env = gym.make("PlanarBLF-v0")
    env.reset(seed=0)
    a = np.array(action, dtype=np.float32)
    while True:
        obs, r, term, trunc, info = env.step(a)
        if term or trunc:
            break
        assert info["termination_reason"] is None and info["cost"] == 0.0
    assert term and not trunc
    assert info["termination_reason"] == "violation"
    assert info["cost"] == 1.0
    assert max(np.max(info["g_upper"]), np.max(info["g_lower"])) > 0

    sc = env.unwrapped.scenario
    dt = sc.sim.dt
    torque = sc.sim.max_torque * np.array([action])  # plain mode: u = max_torque * a
    ref = ClosedLoop([sc], "none", threads=1)
    _, _, status = ref.advance(5000, residual=torque, terminate=False)
    first = int(status[0, 3])
    assert first > 0
    # both sides are (global step index) * dt, so they are equal as floats
    assert info["time"] == first * dt

    before = ClosedLoop([sc], "none", threads=1)
    before.advance(first - 1, residual=torque, terminate=False)
    t = float(before.time[0])
    e = before.X[0, :3] - joint_reference(t, sc)[0]
    ka, kb = error_bounds(t, sc.bounds)
    assert np.all(e < ka) and np.all(e > -kb), "one step earlier the arm must still be inside"
    before.advance(1, residual=torque, terminate=False)
    t = float(before.time[0])
    e = before.X[0, :3] - joint_reference(t, sc)[0]
    ka, kb = error_bounds(t, sc.bounds)
    assert np.any(e >= ka) or np.any(e <= -kb)
    # and the env stopped in exactly that state
    np.testing.assert_array_equal(env.unwrapped.core.loop.X[0], before.X[0])
    np.testing.assert_allclose(info["e1"], e, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# 6. vector env == single envs


@pytest.mark.parametrize("env_id,scales", [("PlanarBLF-v0", (0.01, 0.05, 0.5)),
                                           ("PlanarBLFResidual-v0", (1.0,))])
@pytest.mark.parametrize("mode", ["next_step", "same_step"])
def test_vector_env_equals_single_envs_across_autoresets(env_id, scales, mode):
    """Arm i of the native vector env is the single env seeded 10 + i, step for step, through
    several autoresets, in both of Gymnasium's autoreset modes: next-step (the default; the step
    after an end returns the reset observation with reward 0) and same-step (final_obs/final_info)."""
    from gymnasium.vector import AutoresetMode

    N = 4
    kw = dict(scenario="randomized", duration=0.3, angle_noise_std=1e-4)
    extra = {} if mode == "next_step" else {"autoreset_mode": AutoresetMode.SAME_STEP}
    venv = gym.make_vec(env_id, num_envs=N, **kw, **extra)
    assert venv.metadata["autoreset_mode"] is (AutoresetMode.NEXT_STEP if mode == "next_step"
                                               else AutoresetMode.SAME_STEP)
    envs = [gym.make(env_id, **kw) for _ in range(N)]
    vobs, vinfo = venv.reset(seed=10)
    for i, e in enumerate(envs):
        obs, info = e.reset(seed=10 + i)
        np.testing.assert_array_equal(vobs[i], obs)
        assert vinfo["time"][i] == info["time"]
    rng = np.random.default_rng(3)
    ends = {"violation": 0, "time_limit": 0}
    resets = np.zeros(N, dtype=int)
    pending = np.zeros(N, dtype=bool)  # next-step mode: the arm resets on this step
    for step in range(100):
        acts = (rng.uniform(-1, 1, (N, 3)) * rng.choice(scales, (N, 1))).astype(np.float32)
        vobs, vrew, vterm, vtrunc, vinfo = venv.step(acts)
        for i, e in enumerate(envs):
            msg = f"step {step}, arm {i}"
            if pending[i]:
                obs, info = e.reset()  # the autoreset continues each arm's stream
                resets[i] += 1
                pending[i] = False
                assert vrew[i] == 0.0 and not vterm[i] and not vtrunc[i], msg
                assert not vinfo["_cost"][i] and vinfo["_time"][i] and vinfo["time"][i] == info["time"], msg
                np.testing.assert_array_equal(vobs[i], obs, err_msg=msg)
                continue
            obs, r, term, trunc, info = e.step(acts[i])
            assert vrew[i] == r, msg
            assert bool(vterm[i]) == term and bool(vtrunc[i]) == trunc, msg
            for key in ("time", "e1", "u", "u_law", "x3", "x3_hat", "cost", "violating_samples",
                        "termination_reason", "truncation_reason"):
                np.testing.assert_array_equal(vinfo[key][i], info[key], err_msg=f"{msg}: {key}")
            assert vinfo["reward_info"]["tracking"][i] == info["reward_info"]["tracking"], msg
            if term or trunc:
                ends[info["termination_reason"] or info["truncation_reason"]] += 1
                if mode == "next_step":
                    assert "final_obs" not in vinfo
                    np.testing.assert_array_equal(vobs[i], obs, err_msg=msg)  # the last observation
                    pending[i] = True
                    continue
                assert vinfo["_final_obs"][i] and vinfo["_final_info"][i], msg
                np.testing.assert_array_equal(vinfo["final_obs"][i], obs, err_msg=msg)
                assert vinfo["final_info"]["termination_reason"][i] == info["termination_reason"], msg
                assert vinfo["final_info"]["time"][i] == info["time"], msg
                obs, info = e.reset()
                resets[i] += 1
            else:
                assert not ("_final_obs" in vinfo and vinfo["_final_obs"][i]), msg
            np.testing.assert_array_equal(vobs[i], obs, err_msg=msg)
    assert np.all(resets >= 3), resets  # duration 0.3 s, 1 s simulated: several autoresets per arm
    # plain mode: the arm leaves the bounds within 0.3 s; residual mode: the law keeps it inside
    assert ends["violation" if env_id == "PlanarBLF-v0" else "time_limit"] >= 3 * N, ends


# --------------------------------------------------------------------------------------------
# 7. reward


def test_reward_contract_under_random_policies():
    rng = np.random.default_rng(11)
    seen = {"inside": 0, "violation": 0}
    # the last config has no alive term: its terminal penalty is sized instead (100 agent steps)
    zero_alive = {"tracking": 2.0, "torque": 0.5, "alive": 0.0, "violation": 250.0}
    # the shaped reward (RewardWeights' field defaults; the env's default is the score term,
    # tests/test_conventions.py)
    configs = [("PlanarBLF-v0", {"reward_weights": {}}, (0.01, 0.03, 0.1, 1.0)),
               ("PlanarBLFResidual-v0", {"residual_scale": 60.0, "reward_weights": {}}, (0.1, 1.0)),
               ("PlanarBLF-v0", {"reward_weights": zero_alive}, (0.1, 1.0))]
    for env_id, extra, scales in configs:
        for scenario in ("paper-0.1hz", "paper-0.5hz", "randomized"):
            env = gym.make(env_id, scenario=scenario, duration=1.0, **extra)
            w = env.unwrapped.core.weights
            for seed in range(3):
                env.reset(seed=seed)
                scale = scales[seed % len(scales)]
                while True:
                    a = rng.uniform(-1, 1, 3) * scale
                    if rng.random() < 0.1:
                        a = rng.choice([-1.0, 1.0], 3)  # an occasional large action
                    obs, r, term, trunc, info = env.step(a.astype(np.float32))
                    ri = info["reward_info"]
                    assert set(ri) == {"alive", "tracking", "torque", "score", "violation"}
                    assert ri["score"] == 0.0  # score weight 0
                    # r = alive - tracking * E - torque * U - violation * [ended by it]
                    assert r == pytest.approx(ri["alive"] + ri["tracking"] + ri["torque"] + ri["violation"],
                                              rel=1e-12, abs=1e-12)
                    assert ri["alive"] == w.alive
                    # ending now forfeits at most max_episode_steps steps of the worst inside reward
                    worst_inside = w.alive - w.tracking - w.torque
                    assert -w.violation <= env.unwrapped.core.max_episode_steps * min(worst_inside, 0.0)
                    assert -w.torque <= ri["torque"] <= 0.0
                    assert ri["tracking"] <= 0.0
                    if info["termination_reason"] is None:
                        assert not term
                        assert ri["violation"] == 0.0
                        assert ri["tracking"] >= -w.tracking  # every sample inside: |e1 / bound| < 1
                        assert r >= worst_inside
                        seen["inside"] += 1
                    else:
                        assert term and info["termination_reason"] in ("violation", "diverged")
                        assert ri["violation"] == -w.violation
                        assert r < 0.0
                        seen[info["termination_reason"]] = seen.get(info["termination_reason"], 0) + 1
                    if term or trunc:
                        break
    assert seen["inside"] > 100 and seen["violation"] >= 5, seen


def test_reward_weights_validation_and_custom_weights():
    for bad in ({"tracking": -1.0}, {"torque": float("nan")}, {"violation": float("inf")}, {"alive": -1.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            RewardWeights(**bad)
    assert RewardWeights(tracking=2.0, torque=0.5).alive == 2.5
    with pytest.raises(ValueError, match="alive"):
        gym.make("PlanarBLF-v0", reward_weights={"alive": 0.1})
    # a small alive term needs a terminal penalty that outweighs the rest of the episode:
    # 3000 agent steps of 30 s at 10 ms, each losing at most tracking + torque - alive = 1
    with pytest.raises(ValueError, match="violation must be >= "):
        gym.make("PlanarBLF-v0", reward_weights={"alive": 0.01, "violation": 2999.0})
    gym.make("PlanarBLF-v0", reward_weights={"alive": 0.01, "violation": 3000.0})
    with pytest.raises(ValueError, match="violation must be >= "):  # shorter episodes need less
        gym.make("PlanarBLF-v0", duration=1.0, reward_weights={"alive": 0.01, "violation": 99.0})
    gym.make("PlanarBLF-v0", duration=1.0, reward_weights={"alive": 0.01, "violation": 100.0})
    # custom weights given as a mapping reach the reward
    env = gym.make("PlanarBLF-v0", reward_weights={"tracking": 2.0, "torque": 0.0, "violation": 5.0})
    env.reset(seed=0)
    while True:
        obs, r, term, trunc, info = env.step(np.array([0.0, 0.0, 1.0], dtype=np.float32))
        ri = info["reward_info"]
        assert ri["alive"] == 2.0 and ri["torque"] == 0.0
        if term or trunc:
            break
    assert term and ri["violation"] == -5.0
    assert r == pytest.approx(2.0 + ri["tracking"] - 5.0, rel=1e-12)


# --------------------------------------------------------------------------------------------
# 8. applied torque and the observer


@pytest.mark.parametrize("controller", ["proposed", "lesobc", "bc"])
@pytest.mark.parametrize("residual_scale,action,control_period,flip", [
    (2.0, [0.3, -0.7, 1.0], 0.01, False),
    (400.0, [0.5, -0.5, 0.02], 0.01, False),
    # the law soon cancels a constant residual; flipping it every 1 ms keeps |u_law + residual|
    # above max_torque at many step ends, so the clip itself is exercised
    (400.0, [0.5, -0.5, 0.02], 0.001, True),
])
def test_applied_torque_is_law_plus_scaled_residual_clipped(controller, residual_scale, action,
                                                            control_period, flip):
    env = gym.make("PlanarBLFResidual-v0", controller=controller, residual_scale=residual_scale,
                   control_period=control_period, duration=0.2, terminate_on_violation=False)
    env.reset(seed=0)
    umax = env.unwrapped.scenario.sim.max_torque
    i_u = _obs_index("u_")
    clipped = 0
    k = 0
    while True:
        a = np.array(action, dtype=np.float32) * (-1 if flip and k % 2 else 1)
        obs, r, term, trunc, info = env.step(a)
        k += 1
        assert info["termination_reason"] is None
        unclipped = info["u_law"] + residual_scale * a.astype(np.float64)  # both at the same instant
        np.testing.assert_array_equal(info["u"], np.clip(unclipped, -umax, umax))
        np.testing.assert_array_equal(info["u_residual"], residual_scale * a.astype(np.float64))
        np.testing.assert_allclose(obs[i_u], info["u"] / umax, rtol=1e-6, atol=1e-7)
        if np.any(np.abs(unclipped) > umax):
            assert info["saturated"]
            clipped += 1
        if term or trunc:
            break
    assert trunc
    if flip:
        assert clipped > 10


def test_observer_is_fed_the_applied_torque():
    """A constant 1 N m residual on joint 3 is part of the applied u the LESO sees, so the lumped
    disturbance estimate does not absorb it. An observer fed only u_law would see an extra
    (M^-1 [0, 0, 1])_3 >= 1 / M33 ~ 444 rad/s^2 of 'disturbance' on joint 3 (M33 = 0.00225 kg m^2,
    docs/model.md section 6) and its estimate would settle that far from x3."""
    errs = {}
    for a3 in (0.0, 1.0):
        env = gym.make("PlanarBLFResidual-v0", residual_scale=1.0, duration=0.5)
        env.reset(seed=0)
        e, t = [], []
        while True:
            obs, r, term, trunc, info = env.step(np.array([0.0, 0.0, a3], dtype=np.float32))
            assert info["u"][2] - info["u_law"][2] == pytest.approx(a3, abs=1e-9)
            e.append(info["x3_hat"] - info["x3"])
            t.append(info["time"])
            if term or trunc:
                break
        assert trunc and not term
        errs[a3] = np.array(e)[:, 2]
    settled = np.array(t) > 0.1  # the LESO (k0 = 200 1/s) has converged
    assert np.max(np.abs(errs[1.0][settled])) < 444 / 4
    assert np.max(np.abs(errs[1.0] - errs[0.0])) < 444 / 10


# --------------------------------------------------------------------------------------------
# 9. fuzz within the documented safe ranges


def _fuzz_case(seed: int) -> dict:
    """Env kwargs drawn within the documented safe ranges, the range ends included often."""
    rng = np.random.default_rng(seed)

    def draw(lo: float, hi: float) -> float:
        u = rng.random()
        return lo if u < 0.2 else hi if u < 0.4 else float(rng.uniform(lo, hi))

    variations = {}
    for k in VARIATIONS:
        if rng.random() < 0.7:
            lo, hi = SAFE_RANGES[k]
            if k == "initial_error" and rng.random() < 0.5:
                variations[k] = tuple(draw(lo, hi) for _ in range(3))
            else:
                variations[k] = draw(lo, hi)
    return dict(
        variations=variations,
        control_period=float(rng.choice([0.001, 0.002, 0.005, 0.01])),
        residual_scale=float(np.exp(rng.uniform(np.log(0.01), np.log(300.0)))),
        controller=[None, "bc", "lesobc", "proposed"][int(rng.integers(4))],
        terminate_on_violation=bool(rng.random() < 0.5),
    )


@pytest.mark.parametrize("seed", range(40))
def test_fuzz_short_episodes_stay_finite_and_inside_the_box(seed):
    kw = _fuzz_case(seed)
    action_mode = ("random", "extreme", "mixed")[seed % 3]
    env = gym.make("PlanarBLF-v0", duration=0.2, **kw)
    rng = np.random.default_rng(1000 + seed)
    obs, info = env.reset(seed=seed)
    assert np.all(np.isfinite(obs)) and env.observation_space.contains(obs)
    steps = 0
    while True:
        if action_mode == "random" or (action_mode == "mixed" and rng.random() < 0.5):
            a = rng.uniform(-1, 1, 3)
        else:
            a = rng.choice([-1.0, 1.0], 3)
        obs, r, term, trunc, info = env.step(a.astype(np.float32))
        steps += 1
        assert obs.dtype == np.float32 and np.all(np.isfinite(obs)), (kw, obs)
        assert env.observation_space.contains(obs), (kw, obs)
        assert isinstance(r, float) and np.isfinite(r), kw
        assert not (term and trunc)
        if term:
            assert info["termination_reason"] in ("violation", "diverged"), kw
            if info["termination_reason"] == "violation":
                assert kw["terminate_on_violation"]
            else:
                assert isinstance(info["diverged_message"], str) and "diverged" in info["diverged_message"]
            break
        assert info["termination_reason"] is None
        if trunc:
            assert info["truncation_reason"] == "time_limit"
            assert info["time"] == pytest.approx(0.2)
            assert steps == round(0.2 / kw["control_period"])
            break
        assert info["truncation_reason"] is None
        assert info["time"] < 0.2


# --------------------------------------------------------------------------------------------
# 10. bad input


@pytest.mark.parametrize("kwargs,match", [
    ({"control_period": 0.0015}, "control_period"),
    ({"control_period": 0}, "control_period"),
    ({"control_period": -0.01}, "control_period"),
    ({"residual_scale": -1}, "residual_scale"),
    ({"scenario": "nope"}, "nope"),
    ({"controller": "pid"}, "pid"),
    ({"variations": {"payload": 5.0}}, "payload.*safe range"),
    ({"variations": {"colour": 1}}, "colour"),
    ({"render_mode": "ascii"}, "render_mode"),
])
@pytest.mark.filterwarnings("ignore:.*render_mode='ascii'")  # gym.make's own warning before the error
def test_bad_constructor_arguments_raise_value_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gym.make("PlanarBLFResidual-v0", **kwargs)
    if "render_mode" not in kwargs:
        with pytest.raises(ValueError, match=match):
            gym.make_vec("PlanarBLFResidual-v0", num_envs=2, **kwargs)


def test_bad_reset_options_and_actions_raise_and_leave_the_env_usable():
    env = gym.make("PlanarBLF-v0").unwrapped
    with pytest.raises(RuntimeError, match="reset"):
        env.step(ZERO)
    with pytest.raises(ValueError, match="bogus"):
        env.reset(options={"bogus": 1})
    with pytest.raises(ValueError, match="payload"):
        env.reset(options={"payload": 5.0})
    env.reset(seed=0)
    env.step(ZERO)
    X = env.core.loop.X.copy()
    for bad, match in (([np.nan, 0.0, 0.0], "finite"), ([0.0, np.inf, 0.0], "finite"),
                       ([0.0, 0.0, -np.inf], "finite"), ([0.0, 0.0], "shape"), (np.zeros(4), "shape")):
        with pytest.raises(ValueError, match=match):
            env.step(np.array(bad, dtype=np.float32))
    np.testing.assert_array_equal(env.core.loop.X, X)  # a rejected action does not advance the arm
    obs, r, term, trunc, info = env.step(ZERO)
    assert info["time"] == pytest.approx(0.02)
    # after an episode ends, step() needs a reset again
    while not (term or trunc):
        obs, r, term, trunc, info = env.step(ZERO)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(ZERO)
    venv = gym.make_vec("PlanarBLF-v0", num_envs=2)
    with pytest.raises(RuntimeError, match="reset"):
        venv.step(np.zeros((2, 3), dtype=np.float32))
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        venv.step(np.zeros((3, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="finite"):
        venv.step(np.full((2, 3), np.nan, dtype=np.float32))


# --------------------------------------------------------------------------------------------
# 11. privileged observation


def test_privileged_observation_appends_the_squashed_true_velocity():
    kw = dict(duration=0.3, terminate_on_violation=False)
    env = gym.make("PlanarBLF-v0", **kw)
    penv = gym.make("PlanarBLF-v0", privileged=True, **kw)
    assert env.observation_space.shape == (31,)
    assert penv.observation_space.shape == (37,)
    obs, _ = env.reset(seed=0)
    pobs, _ = penv.reset(seed=0)
    assert obs.shape == (31,) and pobs.shape == (37,)
    np.testing.assert_array_equal(pobs[:31], obs)
    i_qd = [i for i in _obs_index("qd_", privileged=True) if "true" in observation_layout(3, True)[i][0]]
    assert i_qd == [31, 32, 33]
    X = penv.unwrapped.core.loop.X
    rng = np.random.default_rng(5)
    big = 0
    for k in range(30):
        # extreme torques first (fast joints, where the squash shows), then small ones
        a = rng.choice([-1.0, 1.0], 3) if k < 10 else 0.05 * rng.uniform(-1, 1, 3)
        a = a.astype(np.float32)
        obs, *_ = env.step(a)
        pobs, _, term, trunc, info = penv.step(a)
        np.testing.assert_array_equal(pobs[:31], obs)  # privileged only appends
        qd = X[0, 3:6]
        np.testing.assert_array_equal(info["qd"], qd)
        # to float32 precision: |float32(x) - x| <= 2^-24 |x|
        np.testing.assert_allclose(pobs[31:34].astype(np.float64), 100.0 * np.tanh(qd / 100.0),
                                   rtol=2.0**-23, atol=1e-30)
        big += np.any(np.abs(qd) > 10.0)  # where the squash is visible at float32 precision
        assert penv.observation_space.contains(pobs)
        if term or trunc:
            break
    assert big > 0


# --------------------------------------------------------------------------------------------
# 12. rendering


def test_render_rgb_array_returns_a_picture():
    env = gym.make("PlanarBLFResidual-v0", render_mode="rgb_array")
    env.reset(seed=0)
    f0 = env.render()
    assert isinstance(f0, np.ndarray) and f0.dtype == np.uint8
    assert f0.ndim == 3 and f0.shape[2] == 3
    assert f0.shape[0] > 100 and f0.shape[1] > 100
    assert f0.min() != f0.max()
    for _ in range(10):
        env.step(np.array([0.0, 0.0, 0.05], dtype=np.float32))
    f1 = env.render()
    assert f1.shape == f0.shape and not np.array_equal(f0, f1)  # the picture follows the arm / time
    env.close()


def test_the_first_frame_shows_the_end_effector_its_legend_names():
    """The legend names a blue end effector; on an episode's first frame (no path yet) the pixel at
    the end effector's position is that blue, not the arm's black or the background."""
    from matplotlib.colors import to_rgb

    from blf_gym.model.dynamics import joint_positions

    env = gym.make("PlanarBLF-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render().astype(float)
    u = env.unwrapped
    ax = u._renderer.ax_arm
    assert "end effector" in [t.get_text() for t in ax.get_legend().get_texts()][1]
    x, y = ax.transData.transform(joint_positions(u.core.loop.X[0, :3], u.scenario.arm)[-1])
    row, col = int(round(frame.shape[0] - y)), int(round(x))
    patch = frame[row - 1:row + 2, col - 1:col + 2].reshape(-1, 3)
    blue = np.array(to_rgb("tab:blue")) * 255
    assert np.abs(patch - blue).max(axis=1).min() < 30, patch
    env.close()


# --------------------------------------------------------------------------------------------
# 13. truncation


@pytest.mark.parametrize("control_period", [0.01, 0.005, 0.001])
def test_truncation_at_the_duration_without_max_episode_steps(control_period):
    """The env truncates itself at its duration; the spec reports that length (duration /
    control_period) and gym.make adds no TimeLimit that could cut an episode elsewhere."""
    env = gym.make("PlanarBLFResidual-v0", duration=0.05, control_period=control_period)
    expected_steps = {0.01: 5, 0.005: 10, 0.001: 50}[control_period]  # 0.05 s / control_period
    assert env.spec.max_episode_steps == expected_steps
    w = env
    while isinstance(w, gym.Wrapper):
        assert not isinstance(w, gym.wrappers.TimeLimit)
        w = w.env
    env.reset(seed=0)
    for k in range(1, expected_steps + 1):
        obs, r, term, trunc, info = env.step(ZERO)
        assert not term, k
        assert trunc == (k == expected_steps), k
        assert info["truncation_reason"] == ("time_limit" if k == expected_steps else None)
        assert info["time"] == pytest.approx(k * control_period)
    assert obs[_obs_index("t / duration")[0]] == 1.0
    with pytest.raises(RuntimeError):
        env.unwrapped.step(ZERO)


# --------------------------------------------------------------------------------------------
# fixes after review: info timing, randomized + variations, shapes, duration


def test_info_x3_and_x3_hat_are_from_the_same_1ms_sample():
    traj = simulate(preset("paper-0.1hz", duration=1.0), "proposed")
    env = gym.make("PlanarBLFResidual-v0", duration=1.0)
    env.reset(seed=0)
    for k in range(1, 101):
        _, _, term, trunc, info = env.step(ZERO)
        # the step's last sample is at t_end - 1 ms: trajectory index 10 k - 1
        np.testing.assert_array_equal(info["x3"], traj.x3[10 * k - 1])
        np.testing.assert_array_equal(info["x3_hat"], traj.x3_hat[10 * k - 1])
        if term or trunc:
            break


def test_constructor_variations_override_the_randomized_suite():
    env = gym.make("PlanarBLF-v0", scenario="randomized", angle_noise_std=0.0,
                   variations={"payload": 0.3, "force": 0.0})
    for seed in range(3):
        env.reset(seed=seed)
        sc = env.unwrapped.scenario
        assert sc.arm.masses[-1] == 0.3
        assert sc.force.wrench[0] == 0.0
        assert sc.angle_noise_std == 0.0
    # the other knobs are still drawn
    env.reset(seed=0)
    f0 = env.unwrapped.scenario.reference.frequency
    env.reset(seed=1)
    assert env.unwrapped.scenario.reference.frequency != f0


def test_single_env_rejects_a_batched_action_shape():
    env = gym.make("PlanarBLF-v0").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((1, 3), dtype=np.float32))


def test_duration_must_be_a_whole_number_of_control_periods():
    with pytest.raises(ValueError, match="control periods"):
        gym.make("PlanarBLF-v0", duration=0.05, control_period=0.02)


def test_unknown_keyword_argument_is_a_value_error_listing_the_accepted_ones():
    with pytest.raises(ValueError, match="bogus.*accepted.*control_period"):
        gym.make("PlanarBLF-v0", bogus=1)
    with pytest.raises(ValueError, match="bogus"):
        gym.make_vec("PlanarBLF-v0", num_envs=2, bogus=1)


def test_observation_index_matches_the_layout_table():
    from blf_gym.envs.envcore import observation_index

    rows = observation_layout(3, privileged=True)
    idx = observation_index(3)
    assert rows[idx["qd_d"].start][0].startswith("qd_d_1")
    assert rows[idx["k_a_rate"].start][0] == "k_a'"
    assert rows[idx["time"].start][0] == "t / duration"
    assert rows[idx["x3_hat"].start][0].startswith("x3_hat_1")
    assert rows[idx["qd"].start][0].startswith("qd_1 true") and idx["x3"].stop == len(rows)


def _tracking_terms(env, action, seed):
    """One episode of a constant action: the per-step tracking terms (sign flipped, so >= 0 means
    a loss), the rewards, and whether it terminated."""
    env.reset(seed=seed)
    terms, rewards = [], []
    while True:
        _, r, term, trunc, info = env.step(np.asarray(action, dtype=np.float32))
        terms.append(-info["reward_info"]["tracking"])
        rewards.append(r)
        if term or trunc:
            return np.array(terms), np.array(rewards), term


def test_relative_reward_is_one_per_step_on_average_for_the_law_itself():
    """With relative=True, E = mean_j E_j / E_law_j where E_law_j is the law's episode mean; a zero
    residual reproduces the law bit for bit, so the episode mean of E must be 1 (up to rounding) on
    every scenario, however different their error scales are."""
    w = {"relative": True, "relative_cap": 1e9, "tracking": 1.0, "torque": 0.0, "alive": 0.0,
         "violation": 1e9 * 200}
    for scenario in ("paper-0.1hz", "paper-0.5hz", "randomized"):
        # the law's reference episode has no measurement noise, so the suite's is switched off here
        env = gym.make("PlanarBLFResidual-v0", scenario=scenario, duration=2.0, reward_weights=w,
                       angle_noise_std=0.0)
        terms, _, term = _tracking_terms(env, np.zeros(3), seed=3)
        assert not term
        assert np.mean(terms) == pytest.approx(1.0, rel=1e-9), scenario
        assert np.std(terms) > 0.05  # per step it varies: the ratio is not trivially 1
    # with the law's own per-step error subtracted, the law itself scores exactly 0 at every step
    wb = dict(w, law_baseline=True)
    env = gym.make("PlanarBLFResidual-v0", scenario="randomized", duration=2.0, reward_weights=wb,
                   angle_noise_std=0.0)
    terms_law, rewards_law, term = _tracking_terms(env, np.zeros(3), seed=5)
    assert not term and np.all(terms_law == 0.0) and np.all(rewards_law == 0.0)
    # a residual that pushes the arm off the reference costs more than the law
    push = np.array([1.0, -1.0, 1.0])
    env = gym.make("PlanarBLFResidual-v0", duration=2.0, reward_weights=w, residual_scale=5.0)
    terms, _, _ = _tracking_terms(env, push, seed=3)
    assert np.mean(terms) > 2.0
    env = gym.make("PlanarBLFResidual-v0", duration=2.0, reward_weights=wb, residual_scale=5.0)
    terms_b, _, _ = _tracking_terms(env, push, seed=3)
    # the same episode: the baseline shifts the episode's mean by exactly the law's level (1)
    assert np.mean(terms_b) == pytest.approx(np.mean(terms) - 1.0, rel=1e-9)
    with pytest.raises(ValueError, match="law_baseline needs relative"):
        RewardWeights(law_baseline=True)
    # the cap bounds each joint's ratio, and the violation check uses it
    with pytest.raises(ValueError, match="violation must be >= "):
        gym.make("PlanarBLFResidual-v0", reward_weights={"relative": True, "alive": 0.0, "violation": 1e5})
    assert RewardWeights(relative=True, relative_cap=10.0).alive == pytest.approx(10.0 + 0.01)
