"""PPO-Lagrangian (``blf-train --algo ppo_lagrangian``): PPO with a Lagrange multiplier on the
episode cost, the usual baseline of constrained (safe) RL benchmarks. docs/lagrangian.md explains
the method and its settings.

The per-step cost is read from ``info["cost"]`` (PlanarBLF: 1.0 on a control step in which a bound
was broken; run the env with ``terminate_on_violation=False`` so the episode goes on and the costs
add up). On top of SB3's :class:`~stable_baselines3.PPO`, with everything else unchanged:

* **A cost critic** ``V_c``, an MLP of the value net's size, fitted by mean squared error to the
  discounted cost-to-go with an optimizer of its own (PPO's optimizer class, learning rate,
  epochs, minibatch size and gradient clipping), after PPO's update. The cost advantage ``A_c`` is computed by GAE with PPO's ``gamma`` and
  ``gae_lambda``, exactly as SB3 computes the reward's (:func:`gae`), and a time-limit
  truncation bootstraps the cost with ``gamma * V_c(terminal observation)`` as SB3 does the reward.
* **A multiplier** ``lambda >= 0``, updated once per rollout, before the policy update, by
  projected gradient ascent on the constraint (:func:`update_multiplier`)::

      lambda <- max(0, lambda + lagrangian_lr * (mean_episode_cost - cost_limit))

  where ``mean_episode_cost`` is the mean total cost of the episodes that ended during the
  rollout (a rollout in which no episode ended leaves lambda unchanged). No PID terms, no
  optimizer on lambda: plain gradient ascent.
* **The penalised advantage** replaces PPO's in the clipped surrogate
  (:func:`penalized_advantage`)::

      A = (A_r - lambda * A_c) / (1 + lambda)

  With ``normalize_advantage`` (PPO's default, on) ``A_r`` is standardised over the whole
  rollout and ``A_c`` only centred (its scale, in cost units, is what lambda weighs; OmniSafe does
  the same), and the combination is used as it is; PPO's own per-minibatch normalisation is
  skipped, since it would undo the ``1 / (1 + lambda)`` scale.

The multiplier, the cost critic and its optimizer are saved and loaded with SB3's ``save`` and
``load``; ``predict`` is PPO's. The multiplier and the episode cost go to the SB3 logger
(TensorBoard): ``lagrangian/multiplier``, ``lagrangian/mean_episode_cost`` (the rollout's,
when an episode ended), ``lagrangian/cost_limit``, ``rollout/ep_cost_mean`` (over the last 100
episodes) and ``train/cost_value_loss``.

>>> from agents.lagrangian import PPOLagrangian
>>> model = PPOLagrangian("MlpPolicy", venv, cost_limit=25.0, lagrangian_lr=5e-4)  # doctest: +SKIP
>>> model.learn(100_000); model.lagrangian_multiplier                              # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

__all__ = ["PPOLagrangian", "gae", "penalized_advantage", "update_multiplier"]


def update_multiplier(multiplier: float, mean_episode_cost: float, cost_limit: float, lr: float) -> float:
    """One step of projected gradient ascent on the Lagrange multiplier:
    ``max(0, multiplier + lr * (mean_episode_cost - cost_limit))``. It rises while the measured
    episode cost exceeds the limit and falls, never below 0, while the limit is met."""
    return max(0.0, float(multiplier) + float(lr) * (float(mean_episode_cost) - float(cost_limit)))


def penalized_advantage(adv_reward, adv_cost, multiplier: float):
    """``(adv_reward - multiplier * adv_cost) / (1 + multiplier)``: the advantage PPO-Lagrangian
    optimises. Dividing by ``1 + multiplier`` keeps its scale bounded as the multiplier grows (it
    tends to ``-adv_cost``). Works on numpy arrays and torch tensors alike."""
    return (adv_reward - multiplier * adv_cost) / (1.0 + multiplier)


def gae(rewards: np.ndarray, values: np.ndarray, episode_starts: np.ndarray, last_values: np.ndarray,
        last_dones: np.ndarray, gamma: float, gae_lambda: float) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation over a rollout of shape (n_steps, n_envs), with SB3's
    conventions (``episode_starts[t]`` marks that step t began an episode; ``last_values`` and
    ``last_dones`` are those after the rollout's last step). Returns (advantages, returns), with
    returns = advantages + values, as SB3's RolloutBuffer computes them for the reward."""
    n_steps = rewards.shape[0]
    advantages = np.zeros_like(rewards, dtype=np.float32)
    running = np.zeros(rewards.shape[1:], dtype=np.float32)
    for t in reversed(range(n_steps)):
        if t == n_steps - 1:
            non_terminal = 1.0 - np.asarray(last_dones, dtype=np.float32)
            next_values = last_values
        else:
            non_terminal = 1.0 - episode_starts[t + 1]
            next_values = values[t + 1]
        delta = rewards[t] + gamma * next_values * non_terminal - values[t]
        running = delta + gamma * gae_lambda * non_terminal * running
        advantages[t] = running
    return advantages, advantages + values


def _check(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value) or value < 0:
        raise ValueError(f"PPOLagrangian: {name} must be a finite number >= 0, got {value!r}")
    return float(value)


class _CostRecorder(VecEnvWrapper):
    """Passes the env through unchanged for one rollout and hands each step's infos and dones to
    the model, which keeps the costs."""

    def __init__(self, venv: VecEnv, model: "PPOLagrangian") -> None:
        super().__init__(venv)
        self.model = model

    def reset(self):
        return self.venv.reset()

    def step_wait(self):
        obs, rewards, dones, infos = self.venv.step_wait()
        self.model._record_costs(infos, dones)
        return obs, rewards, dones, infos


class PPOLagrangian(PPO):
    """PPO with a Lagrange multiplier on the episode cost (module docstring; docs/lagrangian.md).

    :param cost_limit: the allowed cost per episode, in cost units (PlanarBLF: violating control
        steps per episode), >= 0 (default 25)
    :param lagrangian_lr: the multiplier's step size per unit of excess episode cost, >= 0 (0
        keeps the multiplier at ``lagrangian_init``: PPO with a fixed cost penalty; default 5e-4)
    :param lagrangian_init: the multiplier's initial value, >= 0 (default 0)
    :param termination_cost: a cost added on a step that ends its episode by termination, not by
        the time limit, >= 0 (default 0). The episode cost can otherwise be lowered by ending the
        episode: on PlanarBLF with termination off, the learner met its limit by making the
        simulation diverge within 0.15 s (docs/budget.md section 4). Set to at least what a whole
        episode could cost (PlanarBLF: its control steps), a short episode cannot meet the limit.
    :param cost_limit_start: a schedule on the limit: the limit at step 0, >= 0, from which it moves
        linearly to ``cost_limit`` over the first ``cost_limit_steps`` agent steps and stays there
        (default None: ``cost_limit`` throughout). Started near what the untrained policy costs, the
        constraint is never far from what the policy can meet, so the multiplier grows only as fast
        as the limit tightens (docs/budget.md section 4).
    :param cost_limit_steps: the agent steps over which the limit moves from ``cost_limit_start`` to
        ``cost_limit``, an integer > 0 when ``cost_limit_start`` is set (default 0)

    The other arguments are PPO's. Observations must be a ``Box`` (the cost critic is an MLP on
    the flattened observation).
    """

    def __init__(self, policy, env, cost_limit: float = 25.0, lagrangian_lr: float = 5e-4,
                 lagrangian_init: float = 0.0, termination_cost: float = 0.0, cost_limit_start: float | None = None,
                 cost_limit_steps: int = 0, _init_setup_model: bool = True, **kwargs: Any) -> None:
        self.cost_limit = _check("cost_limit", cost_limit)
        self.termination_cost = _check("termination_cost", termination_cost)
        self.cost_limit_start = None if cost_limit_start is None else _check("cost_limit_start", cost_limit_start)
        if isinstance(cost_limit_steps, bool) or not isinstance(cost_limit_steps, (int, np.integer)) \
                or cost_limit_steps < 0:
            raise ValueError(f"PPOLagrangian: cost_limit_steps must be an integer >= 0, got {cost_limit_steps!r}")
        if self.cost_limit_start is not None and cost_limit_steps == 0:
            raise ValueError("PPOLagrangian: cost_limit_steps must be > 0 when cost_limit_start is set (the steps over "
                             f"which the limit moves from {self.cost_limit_start:g} to {self.cost_limit:g}), got 0")
        self.cost_limit_steps = int(cost_limit_steps)
        self.lagrangian_lr = _check("lagrangian_lr", lagrangian_lr)
        self.lagrangian_init = _check("lagrangian_init", lagrangian_init)
        self.lagrangian_multiplier = self.lagrangian_init
        super().__init__(policy, env, _init_setup_model=False, **kwargs)
        self.ep_cost_buffer: deque[float] = deque(maxlen=100)
        self._running_cost = np.zeros(0)  # each env's cost so far in its current episode
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------ set-up, saving
    def _setup_model(self) -> None:
        super()._setup_model()
        if not isinstance(self.observation_space, spaces.Box):
            raise ValueError(f"PPOLagrangian: the observation space must be a Box (the cost critic is an MLP), "
                             f"got {self.observation_space}")
        arch = self.policy.net_arch
        hidden = list(arch.get("vf", []) if isinstance(arch, dict) else arch)
        layers = create_mlp(get_flattened_obs_dim(self.observation_space), 1, hidden, self.policy.activation_fn)
        self.cost_critic = th.nn.Sequential(*layers).to(self.device)
        self.cost_optimizer = self.policy.optimizer_class(self.cost_critic.parameters(), lr=self.lr_schedule(1),
                                                          **self.policy.optimizer_kwargs)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, tensors = super()._get_torch_save_params()
        return [*state_dicts, "cost_critic", "cost_optimizer"], tensors

    def _excluded_save_params(self) -> list[str]:
        # one rollout's working arrays
        return [*super()._excluded_save_params(), "_costs", "_cost_step", "_rollout_episode_costs",
                "_cost_truncations", "_cost_advantages", "_cost_returns"]

    def _setup_learn(self, total_timesteps, callback=None, reset_num_timesteps=True, tb_log_name="run",
                     progress_bar=False):
        if reset_num_timesteps or self._last_obs is None or self._running_cost.shape != (self.n_envs,):
            self._running_cost = np.zeros(self.n_envs)  # the env is about to be reset
        return super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)

    # ------------------------------------------------------------------ rollouts
    def _cost_values(self, obs: np.ndarray) -> np.ndarray:
        with th.no_grad():
            x = th.as_tensor(np.asarray(obs, dtype=np.float32).reshape(len(obs), -1), device=self.device)
            return self.cost_critic(x).squeeze(-1).cpu().numpy()

    def _record_costs(self, infos: list[dict[str, Any]], dones: np.ndarray) -> None:
        t = self._cost_step
        for i, info in enumerate(infos):
            if "cost" not in info:
                raise ValueError("PPOLagrangian reads the per-step cost from info['cost'], and the env's info has "
                                 f"no 'cost' (keys: {sorted(info)})")
            self._costs[t, i] = float(info["cost"])
            if dones[i] and not info.get("TimeLimit.truncated", False):
                self._costs[t, i] += self.termination_cost  # ended early: charged (0 by default)
        self._running_cost += self._costs[t]
        for i in np.flatnonzero(dones):
            self._rollout_episode_costs.append(float(self._running_cost[i]))
            self._running_cost[i] = 0.0
            if infos[i].get("terminal_observation") is not None and infos[i].get("TimeLimit.truncated", False):
                self._cost_truncations.append((t, int(i), infos[i]["terminal_observation"]))
        self._cost_step = t + 1

    def collect_rollouts(self, env, callback, rollout_buffer, n_rollout_steps: int) -> bool:
        """PPO's rollout, with each step's cost recorded; then the cost values and the cost GAE."""
        self._costs = np.zeros((n_rollout_steps, env.num_envs), dtype=np.float32)
        self._cost_step = 0
        self._rollout_episode_costs: list[float] = []
        self._cost_truncations: list[tuple[int, int, np.ndarray]] = []
        if self._running_cost.shape != (env.num_envs,):
            self._running_cost = np.zeros(env.num_envs)
        complete = super().collect_rollouts(_CostRecorder(env, self), callback, rollout_buffer, n_rollout_steps)
        self.ep_cost_buffer.extend(self._rollout_episode_costs)
        if not complete:
            return False
        costs = self._costs
        if self._cost_truncations:  # as SB3 does for the reward: bootstrap the cost at a time limit
            v = self._cost_values(np.stack([np.asarray(o) for _, _, o in self._cost_truncations]))
            for (t, i, _), vi in zip(self._cost_truncations, v):
                costs[t, i] += self.gamma * vi
        obs = rollout_buffer.observations  # (n_steps, n_envs, ...), not yet flattened
        values = self._cost_values(obs.reshape(-1, *obs.shape[2:])).reshape(costs.shape)
        last = self._cost_values(self._last_obs)
        self._cost_advantages, self._cost_returns = gae(
            costs, values, rollout_buffer.episode_starts, last, np.asarray(self._last_episode_starts),
            self.gamma, self.gae_lambda)
        return True

    # ------------------------------------------------------------------ update
    def current_cost_limit(self) -> float:
        """The limit at the current step: ``cost_limit``, or, with ``cost_limit_start`` set, the
        linear interpolation from it to ``cost_limit`` over the first ``cost_limit_steps`` agent
        steps (``num_timesteps``, which counts on across a resumed run)."""
        if self.cost_limit_start is None:
            return self.cost_limit
        frac = min(1.0, self.num_timesteps / self.cost_limit_steps)
        return self.cost_limit_start + frac * (self.cost_limit - self.cost_limit_start)

    def train(self) -> None:
        """Update the multiplier from the rollout's episodes, run PPO's update on the penalised
        advantage, then fit the cost critic."""
        episodes = self._rollout_episode_costs
        if episodes:
            mean_cost = float(np.mean(episodes))
            self.lagrangian_multiplier = update_multiplier(self.lagrangian_multiplier, mean_cost,
                                                           self.current_cost_limit(), self.lagrangian_lr)
            self.logger.record("lagrangian/mean_episode_cost", mean_cost)
        self.logger.record("lagrangian/multiplier", self.lagrangian_multiplier)
        self.logger.record("lagrangian/cost_limit", self.current_cost_limit())
        self.logger.record("lagrangian/episodes", len(episodes))
        if self.ep_cost_buffer:
            self.logger.record("rollout/ep_cost_mean", float(np.mean(self.ep_cost_buffer)))

        buf = self.rollout_buffer
        adv_r, adv_c = buf.advantages, self._cost_advantages
        normalize = self.normalize_advantage
        if normalize:
            adv_r = (adv_r - adv_r.mean()) / (adv_r.std() + 1e-8)
            # centred, not scaled: scaled to unit spread, a cost advantage that is all critic noise
            # (a rollout where no step costs, or every step does) would weigh as much as a real one
            adv_c = adv_c - adv_c.mean()
        # buf.returns (the value net's target) were computed before; only the surrogate changes
        buf.advantages = penalized_advantage(adv_r, adv_c, self.lagrangian_multiplier).astype(np.float32)
        self.normalize_advantage = False
        try:
            super().train()
        finally:
            self.normalize_advantage = normalize
        self._train_cost_critic()

    def _train_cost_critic(self) -> None:
        self._update_learning_rate(self.cost_optimizer)
        buf = self.rollout_buffer
        obs = buf.observations if buf.generator_ready else buf.swap_and_flatten(buf.observations)
        # in the order of the flattened buffer: (n_envs * n_steps, ...)
        x = th.as_tensor(obs.reshape(len(obs), -1), device=self.device)
        target = th.as_tensor(buf.swap_and_flatten(self._cost_returns).reshape(-1), device=self.device)
        n, batch = len(x), self.batch_size
        losses = []
        self.cost_critic.train()
        for _ in range(self.n_epochs):
            for idx in th.randperm(n).split(batch):
                loss = th.nn.functional.mse_loss(self.cost_critic(x[idx]).squeeze(-1), target[idx])
                self.cost_optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(self.cost_critic.parameters(), self.max_grad_norm)
                self.cost_optimizer.step()
                losses.append(loss.item())
        self.logger.record("train/cost_value_loss", float(np.mean(losses)))
