"""PPO-Lagrangian (agents/lagrangian.py), its blf-train config, and the Safety-Gymnasium-style
wrapper (blf_gym/envs/safety.py)."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import blf_gym
from blf_gym import SafetyGymnasiumWrapper

pytest.importorskip("stable_baselines3")

import torch as th  # noqa: E402
from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.buffers import RolloutBuffer  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize  # noqa: E402

from agents.lagrangian import PPOLagrangian, gae, penalized_advantage, update_multiplier  # noqa: E402
from agents.loading import algorithm_class, load_agent  # noqa: E402
from agents.train import main as train_main  # noqa: E402
from agents.vec_env import BLFVecEnv  # noqa: E402

# the plain env with short episodes and termination off: the untrained policy's random torques
# (up to 150 N m) break the bounds within a few of its 20 steps
ENV = {"terminate_on_violation": False, "duration": 0.2, "control_period": 0.01}
SMALL = {"n_steps": 32, "batch_size": 32, "n_epochs": 1, "policy_kwargs": {"net_arch": [16, 16]}, "seed": 0,
         "device": "cpu"}


def _plain_venv(n: int = 2) -> VecNormalize:
    return VecNormalize(VecMonitor(BLFVecEnv(n, seed=0, threads=1, controller=None, **ENV)))


class _Toy(gym.Env):
    """10-step episodes (truncated) with cost 1 on every second step: each episode costs 5."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.t += 1
        obs = np.array([self.t / 10, np.sin(self.t)], np.float32)
        return obs, -float(np.abs(action).sum()), False, self.t >= 10, {"cost": float(self.t % 2 == 1)}


def _toy_model(n_steps: int, **kw) -> PPOLagrangian:
    venv = VecMonitor(DummyVecEnv([_Toy, _Toy]))
    return PPOLagrangian("MlpPolicy", venv, n_steps=n_steps, batch_size=10, n_epochs=1,
                         policy_kwargs={"net_arch": [8]}, seed=0, device="cpu", **kw)


# ---------------------------------------------------------------- (a) the multiplier
def test_multiplier_update_rule_on_known_numbers():
    # above the limit: up by lr * excess
    assert update_multiplier(1.0, 30.0, 25.0, 0.1) == pytest.approx(1.5)
    assert update_multiplier(0.0, 3.0, 0.0, 0.01) == pytest.approx(0.03)
    # met: down by lr * slack ...
    assert update_multiplier(1.0, 20.0, 25.0, 0.1) == pytest.approx(0.5)
    # ... never below zero
    assert update_multiplier(0.2, 0.0, 25.0, 0.1) == 0.0
    assert update_multiplier(0.0, 10.0, 1e6, 0.1) == 0.0
    # exactly at the limit, or lr 0: unchanged
    assert update_multiplier(0.7, 25.0, 25.0, 0.1) == pytest.approx(0.7)
    assert update_multiplier(0.7, 500.0, 25.0, 0.0) == pytest.approx(0.7)


def test_multiplier_follows_the_episode_cost_read_from_info_exactly():
    # one rollout of 20 steps x 2 envs = 4 whole toy episodes of cost 5 each
    m = _toy_model(20, cost_limit=2.0, lagrangian_lr=0.1, lagrangian_init=1.0)
    m.learn(40)
    assert list(m.ep_cost_buffer) == [5.0] * 4
    assert m.lagrangian_multiplier == pytest.approx(1.0 + 0.1 * (5 - 2))
    m.learn(40, reset_num_timesteps=False)
    assert m.lagrangian_multiplier == pytest.approx(1.0 + 2 * 0.1 * (5 - 2))
    # the limit met: down, clipped at 0
    m = _toy_model(20, cost_limit=10.0, lagrangian_lr=0.1, lagrangian_init=0.3)
    m.learn(40)
    assert m.lagrangian_multiplier == 0.0


def test_a_cost_limit_schedule_moves_the_limit_linearly_then_holds_it():
    # 40 agent steps per rollout (20 x 2 envs), toy episodes costing 5: the multiplier updates after
    # 40, 80 and 120 steps, against limits 5 + (1 - 5) * 40 / 80 = 3, then 1, then 1 (held)
    m = _toy_model(20, cost_limit=1.0, cost_limit_start=5.0, cost_limit_steps=80, lagrangian_lr=0.1)
    m.learn(40)
    assert m.lagrangian_multiplier == pytest.approx(0.1 * (5 - 3))
    m.learn(40, reset_num_timesteps=False)
    assert m.lagrangian_multiplier == pytest.approx(0.1 * (5 - 3) + 0.1 * (5 - 1))
    m.learn(40, reset_num_timesteps=False)
    assert m.lagrangian_multiplier == pytest.approx(0.1 * (5 - 3) + 2 * 0.1 * (5 - 1))
    assert m.current_cost_limit() == 1.0
    # without a schedule the limit is cost_limit from the first rollout
    assert _toy_model(20, cost_limit=1.0).current_cost_limit() == 1.0


@pytest.mark.parametrize("kwargs,match", [({"cost_limit_start": 10.0}, "cost_limit_steps must be > 0"),
                                          ({"cost_limit_start": -1.0, "cost_limit_steps": 5},
                                           "cost_limit_start must be a finite number >= 0"),
                                          ({"cost_limit_steps": -5}, "cost_limit_steps must be an integer >= 0"),
                                          ({"cost_limit_steps": 2.5}, "cost_limit_steps must be an integer >= 0")])
def test_a_bad_cost_limit_schedule_is_refused_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PPOLagrangian("MlpPolicy", None, **kwargs)


def test_episode_cost_is_carried_across_rollouts():
    # 15-step rollouts cut the 10-step episodes: each episode must still add up to 5, and the
    # multiplier must move only on the episodes that ended in its rollout
    m = _toy_model(15, cost_limit=0.0, lagrangian_lr=0.1)
    m.learn(30)  # one rollout: one episode per env ended
    assert list(m.ep_cost_buffer) == [5.0, 5.0]
    assert m.lagrangian_multiplier == pytest.approx(0.5)
    m.learn(30, reset_num_timesteps=False)  # steps 16-30: two more per env
    assert list(m.ep_cost_buffer) == [5.0] * 6
    assert m.lagrangian_multiplier == pytest.approx(1.0)


class _Stop(_Toy):
    """The toy's episodes cut short: terminated (not truncated) at the 4th step, costing 2."""

    def step(self, action):
        obs, rew, _, _, info = super().step(action)
        return obs, rew, self.t >= 4, False, info


def test_a_terminated_episode_is_charged_the_termination_cost_and_a_truncated_one_is_not():
    """Ending an episode early must not lower its cost when termination_cost is set: 4-step
    terminated episodes cost their 2 plus the charge, the toy's truncated 10-step ones only their 5."""
    m = PPOLagrangian("MlpPolicy", VecMonitor(DummyVecEnv([_Stop, _Stop])), n_steps=8, batch_size=8, n_epochs=1,
                      policy_kwargs={"net_arch": [8]}, seed=0, device="cpu", termination_cost=7.0)
    m.learn(16)
    assert list(m.ep_cost_buffer) == [9.0] * 4
    m = _toy_model(20, termination_cost=7.0)
    m.learn(40)
    assert list(m.ep_cost_buffer) == [5.0] * 4  # time-limit truncations are not charged
    m = PPOLagrangian("MlpPolicy", VecMonitor(DummyVecEnv([_Stop, _Stop])), n_steps=8, batch_size=8, n_epochs=1,
                      policy_kwargs={"net_arch": [8]}, seed=0, device="cpu")
    m.learn(16)
    assert list(m.ep_cost_buffer) == [2.0] * 4  # 0, the default: the cost as the env reports it


def test_multiplier_rises_on_the_plain_env_with_cost_limit_zero():
    m = PPOLagrangian("MlpPolicy", _plain_venv(), cost_limit=0.0, lagrangian_lr=0.01, **SMALL)
    m.learn(128)
    assert len(m.ep_cost_buffer) > 0 and np.mean(m.ep_cost_buffer) > 0  # the untrained policy violates
    assert all(0 <= c <= 20 for c in m.ep_cost_buffer)  # at most one cost per control step
    assert m.lagrangian_multiplier > 0.0


def test_multiplier_falls_to_zero_with_a_huge_cost_limit():
    m = PPOLagrangian("MlpPolicy", _plain_venv(), cost_limit=1e6, lagrangian_lr=0.01, lagrangian_init=0.5, **SMALL)
    m.learn(64)
    assert m.lagrangian_multiplier == 0.0
    m = PPOLagrangian("MlpPolicy", _plain_venv(), cost_limit=1e6, lagrangian_lr=0.01, **SMALL)
    m.learn(64)
    assert m.lagrangian_multiplier == 0.0


@pytest.mark.parametrize("field,value", [("cost_limit", -1.0), ("lagrangian_lr", -0.1), ("lagrangian_init", -2),
                                         ("cost_limit", float("nan")), ("lagrangian_lr", "5e-4"),
                                         ("lagrangian_init", True), ("termination_cost", -3.0),
                                         ("termination_cost", float("inf"))])
def test_bad_hyperparameters_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=f"{field} must be a finite number >= 0"):
        PPOLagrangian("MlpPolicy", None, **{field: value})


def test_an_env_without_a_cost_is_refused():
    class NoCost(_Toy):
        def step(self, action):
            obs, r, term, trunc, _ = super().step(action)
            return obs, r, term, trunc, {}

    m = PPOLagrangian("MlpPolicy", DummyVecEnv([NoCost]), n_steps=10, batch_size=10, device="cpu")
    with pytest.raises(ValueError, match=r"info\['cost'\]"):
        m.learn(10)


# ---------------------------------------------------------------- (b) the advantages
def test_penalized_advantage_on_known_arrays():
    adv_r = np.array([1.0, -2.0, 0.5])
    adv_c = np.array([0.5, 1.0, -1.0])
    np.testing.assert_allclose(penalized_advantage(adv_r, adv_c, 3.0), [-0.125, -1.25, 0.875])
    np.testing.assert_allclose(penalized_advantage(adv_r, adv_c, 0.0), adv_r)
    # a huge multiplier: nearly minus the cost advantage, the scale stays bounded
    np.testing.assert_allclose(penalized_advantage(adv_r, adv_c, 1e9), -adv_c, atol=1e-8)
    t = penalized_advantage(th.tensor(adv_r), th.tensor(adv_c), 1.0)
    np.testing.assert_allclose(t.numpy(), [0.25, -1.5, 0.75])


def test_cost_gae_matches_sb3s_reward_gae():
    rng = np.random.default_rng(0)
    n_steps, n_envs = 7, 3
    r = rng.normal(size=(n_steps, n_envs)).astype(np.float32)
    v = rng.normal(size=(n_steps, n_envs)).astype(np.float32)
    starts = (rng.random((n_steps, n_envs)) < 0.3).astype(np.float32)
    last_v = rng.normal(size=n_envs).astype(np.float32)
    last_d = np.array([True, False, True])
    buf = RolloutBuffer(n_steps, gym.spaces.Box(-1, 1, (1,)), gym.spaces.Box(-1, 1, (1,)), gamma=0.9,
                        gae_lambda=0.8, n_envs=n_envs)
    buf.rewards[:], buf.values[:], buf.episode_starts[:] = r, v, starts
    buf.compute_returns_and_advantage(th.tensor(last_v), last_d)
    adv, ret = gae(r, v, starts, last_v, last_d, 0.9, 0.8)
    np.testing.assert_allclose(adv, buf.advantages, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ret, buf.returns, rtol=1e-5, atol=1e-6)
    assert not np.allclose(adv, gae(r, v, starts, last_v, last_d, 0.9, 0.0)[0])  # lambda matters


def test_cost_returns_of_a_rollout_bootstrap_at_the_time_limit():
    m = _toy_model(20)
    _, callback = m._setup_learn(40, None)
    assert m.collect_rollouts(m.env, callback, m.rollout_buffer, 20)
    obs = m.rollout_buffer.observations
    values = m._cost_values(obs.reshape(-1, 2)).reshape(20, 2)
    # the toy's costs, written out: 1 on the odd steps of each 10-step episode; at its time limit
    # (t = 9, 19) the cost-to-go beyond it is bootstrapped with gamma * V_c(terminal observation)
    k = np.arange(20) % 10 + 1
    costs = np.repeat((k % 2 == 1).astype(np.float32)[:, None], 2, axis=1)
    costs[k == 10] += m.gamma * m._cost_values(np.array([[1.0, np.sin(10.0)]], np.float32))[0]
    _, expected = gae(costs, values, m.rollout_buffer.episode_starts, m._cost_values(m._last_obs),
                      np.ones(2, bool), m.gamma, m.gae_lambda)
    np.testing.assert_allclose(m._cost_returns, expected, rtol=1e-5, atol=1e-6)


def test_ppo_is_given_the_penalized_advantage(monkeypatch):
    seen = {}

    def fake_train(self):  # PPO's update, as PPOLagrangian calls it
        seen["adv"] = self.rollout_buffer.advantages.copy()
        seen["normalize"] = self.normalize_advantage

    class Spy(PPOLagrangian):
        def train(self):
            seen["adv_r"] = self.rollout_buffer.advantages.copy()
            seen["adv_c"] = self._cost_advantages.copy()
            super().train()

    monkeypatch.setattr(PPO, "train", fake_train)
    venv = VecMonitor(DummyVecEnv([_Toy, _Toy]))
    m = Spy("MlpPolicy", venv, n_steps=20, batch_size=10, n_epochs=1, cost_limit=0.0, lagrangian_lr=0.1,
            lagrangian_init=1.0, policy_kwargs={"net_arch": [8]}, seed=0, device="cpu")
    m.learn(40)
    lam = 1.0 + 0.1 * 5  # updated before the policy update
    assert m.lagrangian_multiplier == pytest.approx(lam)

    def std(a):
        return (a - a.mean()) / (a.std() + 1e-8)

    assert np.abs(seen["adv_c"]).max() > 0.1  # the toy's costs give a cost advantage
    # the reward's advantage standardised, the cost's only centred (its scale is what lambda weighs)
    np.testing.assert_allclose(seen["adv"], (std(seen["adv_r"]) - lam * (seen["adv_c"] - seen["adv_c"].mean()))
                               / (1 + lam), rtol=1e-5, atol=1e-6)
    assert seen["normalize"] is False and m.normalize_advantage is True  # restored after the update


class _Costly(gym.Env):
    """The same observation forever, cost 1 on every step, truncated every 10 steps: a continuing
    task whose discounted cost-to-go is 1 / (1 - gamma) in every state."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.full(2, 0.5, np.float32), {}

    def step(self, action):
        self.t += 1
        return np.full(2, 0.5, np.float32), 0.0, False, self.t >= 10, {"cost": 1.0}


def test_the_cost_critic_learns_the_known_cost_to_go():
    # gamma 0.8: V_c = 1 / (1 - 0.8) = 5 in every state, time-limit truncations bootstrapped
    venv = VecMonitor(DummyVecEnv([_Costly, _Costly]))
    m = PPOLagrangian("MlpPolicy", venv, n_steps=50, batch_size=50, n_epochs=10, gamma=0.8, gae_lambda=0.95,
                      learning_rate=3e-3, lagrangian_lr=0.0, policy_kwargs={"net_arch": [16]}, seed=0,
                      device="cpu")
    m.learn(6000)
    assert m._cost_values(np.full((1, 2), 0.5, np.float32))[0] == pytest.approx(5.0, rel=0.03)


class _Velocity(gym.Env):
    """A point on a line (Safety-Gymnasium's velocity tasks in one dimension, where PPO-Lagrangian
    is known to work): the reward is its velocity, the cost 1 on every step faster than 0.5. An
    episode is 50 steps. At full speed (2, after 10 steps) an episode costs 48; the best policy
    within a cost limit of 5 reaches 0.5 and stays near it, for a return of about 25."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t, self.v = 0, 0.0
        return np.array([0.0, 0.0], np.float32), {}

    def step(self, action):
        self.t += 1
        self.v = float(np.clip(self.v + 0.2 * float(np.clip(action[0], -1.0, 1.0)), -2.0, 2.0))
        return (np.array([self.v, self.t / 50], np.float32), self.v, False, self.t >= 50,
                {"cost": float(self.v > 0.5)})


def test_on_a_task_where_it_is_known_to_work_it_meets_the_limit_and_still_earns():
    from stable_baselines3.common.callbacks import BaseCallback

    rollouts = []  # per rollout: the mean cost and return of the episodes that ended in it

    class Log(BaseCallback):
        def _on_rollout_end(self) -> None:
            m = self.model
            if m._rollout_episode_costs:
                rollouts.append((np.mean(m._rollout_episode_costs),
                                 np.mean([e["r"] for e in list(m.ep_info_buffer)[-len(m._rollout_episode_costs):]])))

        def _on_step(self) -> bool:
            return True

    venv = VecMonitor(DummyVecEnv([_Velocity] * 4))
    m = PPOLagrangian("MlpPolicy", venv, cost_limit=5.0, lagrangian_lr=0.05, n_steps=250, batch_size=250, n_epochs=5,
                      learning_rate=1e-3, policy_kwargs={"net_arch": [32, 32]}, seed=0, device="cpu")
    m.learn(50_000, callback=Log())
    late = np.array(rollouts[len(rollouts) // 2:])
    cost, ret = late.mean(axis=0)
    # over the second half of training: the cost near its limit (full speed costs 48), the return
    # well above that of standing still (0) and near the constrained best (about 25)
    assert cost <= 7.5, (cost, ret)
    assert ret >= 15.0, (cost, ret)


# ---------------------------------------------------------------- (c) save and load
def test_save_load_keeps_the_multiplier_and_the_cost_critic(tmp_path):
    venv = _plain_venv()
    m = PPOLagrangian("MlpPolicy", venv, cost_limit=0.0, lagrangian_lr=0.01, lagrangian_init=0.25, **SMALL)
    m.learn(64)
    assert m.lagrangian_multiplier > 0.25
    m.save(tmp_path / "model.zip")
    loaded = PPOLagrangian.load(tmp_path / "model.zip", device="cpu")
    assert loaded.lagrangian_multiplier == m.lagrangian_multiplier
    assert (loaded.cost_limit, loaded.lagrangian_lr, loaded.lagrangian_init) == (0.0, 0.01, 0.25)
    obs = np.stack([venv.observation_space.sample() for _ in range(16)])
    for det in (True, False):
        if not det:
            th.manual_seed(1)
        a, _ = m.predict(obs, deterministic=det)
        if not det:
            th.manual_seed(1)
        b, _ = loaded.predict(obs, deterministic=det)
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(m._cost_values(obs), loaded._cost_values(obs))
    assert not np.allclose(m._cost_values(obs), 0)
    for k, v in m.cost_optimizer.state_dict()["state"].items():
        assert th.equal(v["exp_avg"], loaded.cost_optimizer.state_dict()["state"][k]["exp_avg"])
    # the registered name loads the same class, and the loaded model trains on
    assert algorithm_class("ppo_lagrangian") is PPOLagrangian
    loaded.set_env(venv)
    loaded.learn(64, reset_num_timesteps=False)
    assert loaded.num_timesteps == 128


# ---------------------------------------------------------------- (d) blf-train and blf-eval
TINY = """
n_envs: 2
normalize: true
env:
  control_period: 0.01
  terminate_on_violation: false
  duration: 0.2
hyperparams: {{n_steps: 32, batch_size: 32, n_epochs: 1, cost_limit: {limit}, lagrangian_lr: 0.01}}
policy_kwargs:
  net_arch: [16, 16]
eval_freq: 200
checkpoint_freq: 200
curve_suite_seeds: 1
"""


def test_tiny_training_through_blf_train_and_eval(tmp_path, capsys):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from agents.evaluate import main as eval_main

    cfg = tmp_path / "lag.yaml"
    cfg.write_text(TINY.format(limit=0))
    out = tmp_path / "run"
    assert train_main(["--algo", "ppo_lagrangian", "--mode", "plain", "--timesteps", "256", "--config", str(cfg),
                       "--out", str(out), "--no-progress"]) == 0
    assert (out / "model.zip").is_file() and (out / "vecnormalize.pkl").is_file()
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["algo"] == "ppo_lagrangian" and meta["mode"] == "plain" and meta["completed"]
    assert meta["env_kwargs"]["terminate_on_violation"] is False
    assert len(json.loads((out / "eval" / "curve.json").read_text())["points"]) >= 2
    model, _, norm = load_agent(out)
    assert isinstance(model, PPOLagrangian) and model.lagrangian_multiplier > 0 and norm is not None
    # the multiplier and the episode cost reach TensorBoard
    (events,) = list((out / "tb").rglob("events.out.tfevents*"))
    acc = EventAccumulator(str(events))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"lagrangian/multiplier", "lagrangian/mean_episode_cost", "rollout/ep_cost_mean",
            "train/cost_value_loss"} <= tags
    assert acc.Scalars("lagrangian/multiplier")[-1].value > 0
    # blf-eval scores the run (its termination setting is the training env's, not the evaluation's)
    capsys.readouterr()
    assert eval_main(["--agents", str(out), "--controllers", "--suite-seeds", "0", "--duration", "0.5",
                      "--out", str(tmp_path / "eval"), "--no-plots", "--no-progress"]) == 0
    recs = json.loads((tmp_path / "eval" / "results.json").read_text())["records"]
    assert [r["policy"] for r in recs] == ["run", "run"] and all(r["score_vs_law"] > 0 for r in recs)
    # a bad hyperparameter is refused by name, before anything is written
    cfg.write_text(TINY.format(limit=-1))
    assert train_main(["--algo", "ppo_lagrangian", "--mode", "plain", "--timesteps", "64", "--config", str(cfg),
                       "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    assert "cost_limit must be a finite number >= 0" in capsys.readouterr().err


def test_the_shipped_config_is_valid_and_plain():
    from agents.config import CONFIG_DIR
    from agents.train import load_config

    cfg = load_config(CONFIG_DIR / "ppo_lagrangian_PlanarBLF-v0.yaml")
    assert cfg["env"]["terminate_on_violation"] is False
    hp = cfg["hyperparams"]
    for key in ("cost_limit", "lagrangian_lr", "lagrangian_init"):
        assert isinstance(hp[key], (int, float)) and hp[key] >= 0, key  # YAML's 5e-4 would be a string
    # a rollout is whole 30 s episodes, so every rollout updates the multiplier
    assert hp["n_steps"] * cfg["env"]["control_period"] == pytest.approx(30.0)


# ---------------------------------------------------------------- (e) the six-value wrapper
def _safe_env(**kw) -> SafetyGymnasiumWrapper:
    return SafetyGymnasiumWrapper(gym.make("PlanarBLF-v0", **{**ENV, **kw}))


def test_wrapper_returns_six_values_with_the_info_cost():
    env = _safe_env()
    assert env.observation_space == env.unwrapped.observation_space
    assert env.action_space == env.unwrapped.action_space
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and isinstance(info, dict)
    env.action_space.seed(0)
    costs, info_costs, steps = [], [], 0
    while True:
        out = env.step(np.full(3, 0.05, np.float32))  # 7.5 N m on every joint: out of the bounds
        assert len(out) == 6
        obs, reward, cost, terminated, truncated, info = out
        assert obs.shape == (31,) and obs.dtype == np.float32 and env.observation_space.contains(obs)
        assert isinstance(reward, float) and isinstance(cost, float)
        assert isinstance(terminated, bool) and isinstance(truncated, bool)
        assert cost == info["cost"] and cost in (0.0, 1.0)
        costs.append(cost)
        info_costs.append(info["cost"])
        steps += 1
        if terminated or truncated:
            break
    assert truncated and not terminated and steps == 20  # termination off: the full 0.2 s
    assert 0 < sum(costs) < 20 and costs == info_costs  # the first step is still inside
    env.close()


def test_wrapper_is_deterministic_under_a_seed_and_keeps_the_envs_behaviour():
    from gymnasium.utils import env_checker

    # gymnasium's checks that apply to it (reset is the wrapped env's; check_step_determinism
    # and check_env expect five values)
    env = _safe_env()
    env_checker.check_reset_return_type(env)
    env_checker.check_reset_seed_determinism(env)
    env_checker.check_reset_options(env)
    env_checker.check_observation_space(env.observation_space)
    env_checker.check_action_space(env.action_space)

    # step determinism, env_checker-style: same seed, same actions -> the same six values; and
    # they are the wrapped env's five with the info's cost inserted
    def run(env, n=5):
        obs, _ = env.reset(seed=3)
        rng = np.random.default_rng(0)
        rows = [obs]
        for _ in range(n):
            rows.append(env.step(rng.uniform(-1, 1, 3).astype(np.float32)))
        return rows

    a, b = run(_safe_env()), run(_safe_env())
    plain = run(gym.make("PlanarBLF-v0", **ENV))
    assert env_checker.data_equivalence(a, b)
    for x, p in zip(a[1:], plain[1:]):
        np.testing.assert_array_equal(x[0], p[0])
        assert (x[1], x[3], x[4]) == (p[1], p[2], p[3]) and x[2] == p[4]["cost"]


def test_wrapper_with_termination_on_and_without_a_cost():
    env = _safe_env(terminate_on_violation=True)
    env.reset(seed=0)
    while True:
        *_, cost, terminated, truncated, info = env.step(np.full(3, 0.05, np.float32))
        if terminated or truncated:
            break
    assert terminated and info["termination_reason"] == "violation" and cost == 1.0
    bad = SafetyGymnasiumWrapper(gym.make("Pendulum-v1"))
    bad.reset(seed=0)
    with pytest.raises(ValueError, match="no 'cost'"):
        bad.step(bad.action_space.sample())


def test_wrapper_is_exported_without_torch():
    assert blf_gym.SafetyGymnasiumWrapper is SafetyGymnasiumWrapper and "SafetyGymnasiumWrapper" in blf_gym.__all__
    import subprocess
    import sys

    code = ("import sys, blf_gym.envs.safety; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'stable_baselines3', 'agents')); "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[1])
