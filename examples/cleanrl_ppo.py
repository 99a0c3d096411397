"""PPO in one file, in the style of CleanRL, on PlanarBLF with Gymnasium 1.x.

    python examples/cleanrl_ppo.py --env-id PlanarBLFResidual-v0 --total-timesteps 1000000 --seed 0

CleanRL's own ``ppo_continuous_action.py`` pins gymnasium 0.29. On Gymnasium 1.x it needs three
changes, all made here:

1. ``TransformObservation`` (and ``TransformReward``) take the transformed space: the clipped
   observation's box is passed as ``observation_space``.
2. The sync vector env is asked for same-step autoreset (``AutoresetMode.SAME_STEP``), the 0.29
   behaviour CleanRL's loop assumes: the observation returned with ``done`` is already the next
   episode's, and the last one is in ``info["final_obs"]``. (Gymnasium's vector-level normalising
   wrappers refuse that mode, so the wrappers stay per env, as in CleanRL.)
3. ``info["final_info"]`` is a dict of arrays with a ``_`` mask per key, not a list of dicts.

A truncated episode (the 30 s time limit) is bootstrapped from the value of its final observation;
a terminated one (a violation) is not. The env's own ``episode_metrics`` give each finished
episode's RMSE, violations and how it ended; with the default score reward an episode's return is
``log(score_vs_law)``, so ``exp(return)`` is its score against the law.

This script is written for reading, not for speed: ``blf-train`` (SB3, sbx) is the project's
trainer, with checkpoints, resumption and evaluation on the protocol.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
from gymnasium.vector import AutoresetMode
from torch.distributions import Normal

import blf_gym  # noqa: F401  (registers the env ids)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env-id", default="PlanarBLFResidual-v0")
    p.add_argument("--scenario", default="randomized", help="the env's scenario (default: the training suite)")
    p.add_argument("--duration", type=float, default=None, help="episode length in s (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--total-timesteps", type=int, default=1_000_000)
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--num-steps", type=int, default=256, help="steps per env per rollout")
    p.add_argument("--learning-rate", type=float, default=3e-4)
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--gae-lambda", type=float, default=0.95)
    p.add_argument("--num-minibatches", type=int, default=8)
    p.add_argument("--update-epochs", type=int, default=10)
    p.add_argument("--clip-coef", type=float, default=0.2)
    p.add_argument("--ent-coef", type=float, default=0.0)
    p.add_argument("--vf-coef", type=float, default=0.5)
    p.add_argument("--max-grad-norm", type=float, default=0.5)
    p.add_argument("--out", default=None, help="folder for summary.json and model.pt (default: none written)")
    return p.parse_args(argv)


def make_env(args: argparse.Namespace, kwargs: dict):
    """One env with CleanRL's wrappers (a thunk, as SyncVectorEnv wants)."""
    def thunk() -> gym.Env:
        env = gym.make(args.env_id, **kwargs)
        env = gym.wrappers.RecordEpisodeStatistics(env)  # before the normalisation: raw returns
        env = gym.wrappers.NormalizeObservation(env)
        # change 1: Gymnasium 1.x's TransformObservation takes the transformed space
        clipped = gym.spaces.Box(-10.0, 10.0, env.observation_space.shape, np.float32)
        env = gym.wrappers.TransformObservation(env, lambda o: np.clip(o, -10, 10).astype(np.float32), clipped)
        env = gym.wrappers.NormalizeReward(env, gamma=args.gamma)
        env = gym.wrappers.TransformReward(env, lambda r: float(np.clip(r, -10, 10)))
        return env

    return thunk


def make_envs(args: argparse.Namespace) -> gym.vector.VectorEnv:
    kwargs = {"scenario": args.scenario}
    if args.duration is not None:
        kwargs["duration"] = args.duration
    # change 2: same-step autoreset, the behaviour of gymnasium 0.29 that the loop below assumes
    return gym.vector.SyncVectorEnv([make_env(args, kwargs) for _ in range(args.num_envs)],
                                    autoreset_mode=AutoresetMode.SAME_STEP)


def layer(n_in: int, n_out: int, std: float = math.sqrt(2)) -> nn.Linear:
    lin = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(lin.weight, std)
    nn.init.zeros_(lin.bias)
    return lin


class Agent(nn.Module):
    """Separate value and policy networks (64 x 64, tanh), a state-independent log std."""

    def __init__(self, n_obs: int, n_act: int) -> None:
        super().__init__()
        self.critic = nn.Sequential(layer(n_obs, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, 1, 1.0))
        self.actor = nn.Sequential(layer(n_obs, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, n_act, 0.01))
        self.log_std = nn.Parameter(torch.zeros(1, n_act))

    def value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def act(self, x: torch.Tensor, action: torch.Tensor | None = None):
        mean = self.actor(x)
        dist = Normal(mean, self.log_std.expand_as(mean).exp())
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action).sum(-1), dist.entropy().sum(-1), self.value(x)


def train(args: argparse.Namespace) -> dict:
    torch.set_num_threads(1)  # the env has its own thread; two busy pools on two cores wait on each other
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    envs = make_envs(args)
    n_obs = envs.single_observation_space.shape[0]
    n_act = envs.single_action_space.shape[0]
    agent = Agent(n_obs, n_act)
    opt = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    T, N = args.num_steps, args.num_envs
    batch = T * N
    minibatch = batch // args.num_minibatches
    updates = max(1, args.total_timesteps // batch)
    obs_buf = torch.zeros((T, N, n_obs))
    act_buf = torch.zeros((T, N, n_act))
    logp_buf = torch.zeros((T, N))
    rew_buf = torch.zeros((T, N))
    done_buf = torch.zeros((T, N))
    val_buf = torch.zeros((T, N))

    obs, _ = envs.reset(seed=args.seed)
    obs = torch.as_tensor(obs, dtype=torch.float32)
    episodes: list[dict] = []
    losses: list[float] = []
    start = time.perf_counter()
    step = 0
    for update in range(updates):
        for t in range(T):
            step += N
            obs_buf[t] = obs
            with torch.no_grad():
                action, logp, _, value = agent.act(obs)
            act_buf[t], logp_buf[t], val_buf[t] = action, logp, value
            nxt, reward, terminated, truncated, info = envs.step(action.numpy())
            reward = torch.as_tensor(reward, dtype=torch.float32)
            # change 2: same-step autoreset; a truncated episode is bootstrapped from its last observation
            if "final_obs" in info and truncated.any():
                idx = np.flatnonzero(truncated & ~terminated)
                if idx.size:
                    last = np.stack([info["final_obs"][i] for i in idx]).astype(np.float32)
                    with torch.no_grad():
                        reward[idx] += args.gamma * agent.value(torch.as_tensor(last))
            rew_buf[t] = reward
            done_buf[t] = torch.as_tensor(terminated | truncated, dtype=torch.float32)
            # change 3: final_info is a dict of arrays, masked per key (not a list of dicts)
            if "final_info" in info:
                fin = info["final_info"]
                for i in np.flatnonzero(fin.get("_episode", np.zeros(N, dtype=bool))):
                    em = fin.get("episode_metrics", {})  # itself a dict of arrays
                    m = {k: v[i] for k, v in em.items() if not k.startswith("_")}
                    episodes.append({"step": step, "return": float(fin["episode"]["r"][i]),
                                     "length": int(fin["episode"]["l"][i]),
                                     "rmse_deg": np.asarray(m.get("rmse_deg"), dtype=float).tolist(),
                                     "violating_samples": int(m.get("violating_samples", 0)),
                                     "ended": m.get("termination_reason") or m.get("truncation_reason")})
            obs = torch.as_tensor(nxt, dtype=torch.float32)

        with torch.no_grad():  # generalised advantage estimation
            next_value = agent.value(obs)
            adv = torch.zeros((T, N))
            gae = torch.zeros(N)
            for t in reversed(range(T)):
                v_next = next_value if t == T - 1 else val_buf[t + 1]
                live = 1.0 - done_buf[t]
                delta = rew_buf[t] + args.gamma * v_next * live - val_buf[t]
                gae = delta + args.gamma * args.gae_lambda * live * gae
                adv[t] = gae
            ret = adv + val_buf

        b_obs, b_act = obs_buf.reshape(batch, n_obs), act_buf.reshape(batch, n_act)
        b_logp, b_adv, b_ret = logp_buf.reshape(-1), adv.reshape(-1), ret.reshape(-1)
        order = np.arange(batch)
        for _ in range(args.update_epochs):
            np.random.shuffle(order)
            for s in range(0, batch, minibatch):
                mb = order[s:s + minibatch]
                _, logp, entropy, value = agent.act(b_obs[mb], b_act[mb])
                ratio = (logp - b_logp[mb]).exp()
                a = b_adv[mb]
                a = (a - a.mean()) / (a.std() + 1e-8)
                pg = torch.max(-a * ratio, -a * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
                v_loss = 0.5 * ((value - b_ret[mb]) ** 2).mean()
                loss = pg - args.ent_coef * entropy.mean() + args.vf_coef * v_loss
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                opt.step()
        losses.append(loss.item())
        recent = [e["return"] for e in episodes[-20:]]
        sps = step / (time.perf_counter() - start)
        print(f"update {update + 1}/{updates}  steps {step}  sps {sps:,.0f}  loss {losses[-1]:.4f}  "
              f"episodes {len(episodes)}  mean return (last 20) "
              f"{(np.mean(recent) if recent else float('nan')):.3f}", flush=True)

    envs.close()
    summary = {"args": vars(args), "steps": step, "wall_s": time.perf_counter() - start, "losses": losses,
               "episodes": episodes, "versions": {"gymnasium": gym.__version__, "torch": torch.__version__}}
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        torch.save(agent.state_dict(), out / "model.pt")
        (out / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary


if __name__ == "__main__":
    train(parse_args())
