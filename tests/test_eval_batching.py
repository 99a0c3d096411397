"""blf-eval steps an agent's groups together and asks its network for actions without SB3's
per-call overhead; neither may change a number.

* ``_Actor`` must return, bit for bit, what ``model.predict(obs, deterministic=True)`` returns: for
  the shipped agents (PPO, PPO-Lagrangian) and for the squashed SAC policy, on one row and on many;
* a batch that packs several groups must give each group's episodes exactly as stepping the group
  alone does (the arms are independent, and the network is still called on each group's rows alone);
* the batch plan never exceeds the batch size, never leaves a one-episode part of a longer group
  and keeps every episode once, in order.
"""

from __future__ import annotations

import numpy as np
import pytest

from agents.episodes import (AGENT_BATCH, _Actor, _batch_plan, agent_episodes, agent_group_episodes,
                             build_scenarios, law_env_kwargs)
from agents.loading import PRETRAINED, load_agent, pretrained_agents
from blf_gym.results.metrics import episode_stats


@pytest.mark.parametrize("name", pretrained_agents())
def test_the_lean_actor_is_predict_bit_for_bit_on_the_shipped_agents(name):
    model, meta, norm = load_agent(PRETRAINED / name / "model.zip")
    rng = np.random.default_rng(0)
    dim = model.observation_space.shape[0]
    for rows in (1, 7, 20, 50):
        obs = rng.normal(0.0, 3.0, (rows, dim)).astype(np.float32)
        want = model.predict(obs, deterministic=True)[0]
        got = _Actor(model)(obs)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert np.array_equal(got, want), (name, rows)
        # and it took the lean path, not predict (which would make this test vacuous)
        assert _Actor(model).policy is not None and _Actor(model).mean and _Actor(model).plain


def test_the_lean_actor_follows_other_actor_nets_as_predict_does():
    import gymnasium as gym
    import torch
    from stable_baselines3 import PPO

    env = gym.make("Pendulum-v1")
    obs = np.random.default_rng(3).normal(size=(12, 3)).astype(np.float32)
    for arch in (dict(activation_fn=torch.nn.ReLU), dict(activation_fn=torch.nn.ELU)):
        model = PPO("MlpPolicy", env, seed=0, policy_kwargs=arch)
        actor = _Actor(model)
        # ReLU is a plain operation; ELU is not, and goes through the policy's own modules
        assert actor.mean and actor.plain == (arch["activation_fn"] is torch.nn.ReLU)
        for rows in (1, 12):
            assert np.array_equal(actor(obs[:rows]), model.predict(obs[:rows], deterministic=True)[0])


def test_the_lean_actor_unscales_a_squashed_policy_as_predict_does():
    import gymnasium as gym
    from stable_baselines3 import SAC

    env = gym.make("Pendulum-v1")
    model = SAC("MlpPolicy", env, seed=0, learning_starts=0)
    assert model.policy.squash_output and not _Actor(model).mean
    obs = np.random.default_rng(1).normal(size=(9, 3)).astype(np.float32)
    assert np.array_equal(_Actor(model)(obs), model.predict(obs, deterministic=True)[0])


class _Linear:
    """A model without an SB3 policy: the actor must ask its predict."""

    def predict(self, obs, deterministic=True):
        return np.tanh(obs[:, :3]).astype(np.float32), None


def test_a_model_without_an_sb3_policy_is_asked_through_its_predict():
    obs = np.random.default_rng(2).normal(size=(4, 30)).astype(np.float32)
    actor = _Actor(_Linear())
    assert actor.policy is None and np.array_equal(actor(obs), np.tanh(obs[:, :3]).astype(np.float32))


@pytest.mark.parametrize("sizes", [[1, 1, 20, 50], [1, 1, 120, 200], [3], [0, 5, 51], [60, 1]])
def test_the_batch_plan_keeps_every_episode_once_in_order_and_bounded(sizes):
    class _Sc:
        class sim:
            duration = 1.0

    groups = [[_Sc()] * k for k in sizes]
    plan = _batch_plan(groups, AGENT_BATCH)
    flat = [(g, i) for parts in plan for g, lo, hi in parts for i in range(lo, hi)]
    assert flat == [(g, i) for g, k in enumerate(sizes) for i in range(k)]
    for parts in plan:
        assert sum(hi - lo for _, lo, hi in parts) <= AGENT_BATCH
        for g, lo, hi in parts:
            assert hi - lo >= 2 or sizes[g] == 1, (sizes, parts)


def test_packed_groups_score_as_each_group_alone():
    model, meta, norm = load_agent(PRETRAINED / "ppo_residual" / "model.zip")
    groups = [scs for _, scs in build_scenarios(["paper-0.1hz", "paper-0.5hz"], 9, {}, 0.3, "randomized")]
    assert [len(g) for g in groups] == [1, 1, 9] and len(_batch_plan(groups, AGENT_BATCH)) == 1  # one packed batch
    packed: list[list] = [[] for _ in groups]
    for g, tr in agent_group_episodes(model, meta, norm, groups, threads=1):
        packed[g].append(episode_stats(tr))
    for g, scs in enumerate(groups):
        alone = [episode_stats(t) for t in agent_episodes(model, meta, norm, scs, threads=1)]
        assert len(packed[g]) == len(alone) == len(scs)
        for a, b in zip(packed[g], alone):
            assert a.rmse_deg == b.rmse_deg and np.array_equal(a.sq, b.sq) and np.array_equal(a.u_sq, b.u_sq)


def test_agents_that_differ_only_where_the_law_does_not_look_share_one_law_reference():
    plain = {"env_kwargs": {"control_period": 0.01, "privileged": True}}
    residual = {"env_kwargs": {"controller": "proposed", "control_period": 0.01, "residual_scale": 8.0,
                               "residual_filter": "barrier"}}
    slower = {"env_kwargs": {"controller": "proposed", "control_period": 0.002}}
    assert law_env_kwargs(plain) == law_env_kwargs(residual) != law_env_kwargs(slower)
