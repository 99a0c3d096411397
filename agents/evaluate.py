"""``blf-eval``: score controllers and trained agents on the same scenarios and metrics.

Controllers (``bc``, ``lesobc``, ``proposed``) run on the fast inner path (the law at every ODE3
stage, all episodes of a controller in one threaded kernel call). Agents are SB3 model zips with
a metadata JSON beside them (written by ``blf-train``: algorithm, env arguments, plain or
residual); all their episodes step together in one batched env. Episodes always run their full
duration with termination off, and violations are counted.

The run is cut into independent pieces (a baseline on one scenario group, an agent on all groups,
the law's reference for an agent's env set-up) that ``--jobs`` worker processes score at once,
the costliest first (default: one per CPU, at most :data:`MAX_DEFAULT_JOBS`). Every piece draws
from its own seeds, so the records are the same, to the bit, for any number of workers.

Examples::

    blf-eval                                  # the whole protocol: every baseline + the shipped agents
    blf-eval --agents runs/mine               # one new agent against the law, on the whole protocol
    blf-eval --agents runs/mine --suite-seeds 0   # the same, on the paper presets alone (seconds)
    blf-eval --suite-seeds 0                  # every baseline and shipped agent on the presets alone
    blf-eval --controllers proposed --agents runs/ppo --suite stress --suite-seeds 50 --out results/
    blf-eval --suite-seeds 0 --scenario-kwargs '{"payload": 0.15}' --duration 10

With ``--agents``, the baselines default to the proposed law alone (the reference of every score):
scoring one agent costs that agent and the law, not BC's and LESOBC's rows.

By default every policy is judged on the benchmark's three scenario groups: the paper presets, 20
held-out episodes of the training suite (seeds from 10,000) and 50 of the stress suite (seeds from
20,000, never trained or selected on).

Writes, with ``--out DIR``: ``results.json`` and ``results.csv`` (docs/model.md section 8), PNG plots of
the tracking error with its bounds and of the torques, per scenario, and last ``manifest.json``. Before
anything else the manifest is replaced by one saying ``"complete": false``; ``results.json`` is
rewritten after each finished record, so an interrupted run keeps those records; only when every file
is written does the manifest say ``"complete": true`` and list each file with its size and sha256.
A set without such a manifest is incomplete. A failed write (a full disk) names the file, exit code 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from blf_gym.results.io import begin_output_set, check_out_dir, finish_output_set, help_text, os_error_message
from blf_gym.results.metrics import METRIC_CHANNELS, EpisodeStats, episode_stats, summarize, write_results
from blf_gym.envs.levels import DEFAULT_LEVEL, apply_level, check_level
from blf_gym.model.params import PRESETS, Scenario, preset
from blf_gym.envs.protocol import (CURVE_GROUPS, EVAL_SEED_OFFSET, PROTOCOL_SEEDS, REFERENCE, SUITES,  # noqa: F401 (re-exported)
                                   suite_seed_offset)
from blf_gym.envs.scenarios import apply_variations, sample_suite, variation_label

from . import lawcache
from .lawcache import law_key, load_law, store_law
# the one agent loader, re-exported here
from .loading import POLICY_PREFIX, PRETRAINED, load_agent, load_policy, scoring_env_kwargs

__all__ = ["main", "evaluate_controller", "evaluate_agent", "controller_episodes", "agent_episodes",
           "agent_group_episodes", "law_env_kwargs", "law_reference", "law_reference_groups",
           "build_scenarios", "load_agent"]


def registered_controllers() -> list[str]:
    """The inner controllers registered in the ``blf_gym.controllers`` entry-point group."""
    from blf_gym.plugins.registry import available_controllers

    return [c for c in available_controllers() if c != "none"]


def curve_scenarios(suite_seeds: int, duration: float | None = None,
                    level: int = DEFAULT_LEVEL) -> list[tuple[str, list[Scenario]]]:
    """The scenarios of :data:`CURVE_GROUPS`, labelled by group: the paper presets and
    ``suite_seeds`` held-out episodes of the training suite, ``duration`` seconds each (None: the
    presets' 30 s), at difficulty ``level`` (an agent's curve is drawn at the level it trains at)."""
    groups = build_scenarios(list(PRESETS), suite_seeds, {}, duration, level=level)
    return [(label.split("@L")[0], scs) for label, scs in groups]


def build_scenarios(
    presets: Sequence[str], suite_seeds: "int | Sequence[int]", kwargs: dict[str, Any], duration: float | None,
    suite: "str | Sequence[str]" = "randomized", level: int = DEFAULT_LEVEL,
) -> list[tuple[str, list[Scenario]]]:
    """[(scenario label, episodes)]: each preset is one episode; each suite in ``suite`` has its
    ``suite_seeds`` episodes (one count for all suites, or one per suite).

    With variations (``kwargs``) every label gains them (:func:`variation_label`: ``+frequency=0.5``,
    or ``+custom`` when they do not fit in a short label), so a varied result is never mistaken for
    the plain one; the variations themselves are recorded in each record's provenance by blf-eval.
    Below the full benchmark (``level`` 3, blf_gym.envs.levels) every episode is taken to that level after
    its draw and its variations, and every label gains ``@L<level>``."""
    level = check_level("blf-eval: --level", level)
    tag = "" if level == DEFAULT_LEVEL else f"@L{level}"
    suites = [suite] if isinstance(suite, str) else list(suite)
    counts = [suite_seeds] * len(suites) if isinstance(suite_seeds, int) else list(suite_seeds)
    if len(counts) == 1 and len(suites) > 1:
        counts = counts * len(suites)
    if len(counts) != len(suites):
        raise ValueError(f"--suite-seeds needs one count or one per suite ({len(suites)}), got {len(counts)}")
    for c in counts:
        if isinstance(c, bool) or not isinstance(c, int) or c < 0:
            raise ValueError(f"--suite-seeds must be integers >= 0, got {c!r}")
    groups: list[tuple[str, list[Scenario]]] = []
    sim_over = {"duration": duration} if duration is not None else {}
    for name in presets:
        if name not in PRESETS:
            raise ValueError(f"unknown scenario {name!r}; accepted: {sorted(PRESETS)} (and --suite-seeds)")
        sc = preset(name, **sim_over)
        if kwargs:
            sc = apply_variations(sc, kwargs)  # named with the variations' label (blf_gym.envs.scenarios)
        sc = apply_level(sc, level)  # named with its level
        groups.append((sc.name, [sc]))
    for name, count in zip(suites, counts):
        if count == 0:
            continue
        offset = suite_seed_offset(name)
        eps = []
        for k in range(count):
            sc = sample_suite(np.random.default_rng(offset + k), preset("paper-0.1hz", **sim_over), name)
            if kwargs:
                sc = apply_variations(sc, kwargs)
            eps.append(apply_level(sc, level))
        groups.append((name + variation_label(kwargs) + tag, eps))
    return groups


CONTROLLER_BATCH = 8
"""Episodes a baseline controller runs at once on the inner path (its arms are independent, so the
results do not depend on it; it bounds the memory of their 1 ms records: 8 episodes of 30 s keep
about 100 MB, twice that while each is copied out; two blocks of lanes, as fast per arm as more)."""
AGENT_BATCH = 50
"""Most episodes an agent steps at once, in one batched env: the protocol's largest group (50 stress
episodes), so each of the protocol's groups is one batch, as it always was. Longer lists are split
into near-equal batches. An agent's actions come from one network call per step; measured on the
shipped agents, torch's actions for a row are the same to the bit for any batch of 7 to 200 rows,
but not for a batch of one row, so no batch is left with a single episode of a longer list."""


def controller_episodes(name: str, scenarios: Sequence[Scenario], threads: int | None = None,
                        observer: str = "leso", batch: int = CONTROLLER_BATCH) -> Iterator[Any]:
    """A baseline controller's trajectories on the inner path, one per scenario, in order, computed
    ``batch`` episodes at a time (episode i has noise seed ``EVAL_SEED_OFFSET + i``), so a caller
    that reduces each one as it comes keeps at most a batch of 1 ms records in memory."""
    from blf_gym.kernel.simulate import LANES, simulate_batch

    for lo in range(0, len(scenarios), batch):
        part = list(scenarios[lo : lo + batch])
        # the batch build even for one episode (a preset, a plot's trace): one build per law
        trajs = simulate_batch(part, name, observer, noise_seeds=[EVAL_SEED_OFFSET + lo + i for i in range(len(part))],
                               threads=threads, lanes=LANES)
        while trajs:
            yield trajs.pop(0)


def evaluate_controller(name: str, scenarios: Sequence[Scenario], threads: int | None = None,
                        observer: str = "leso"):
    """Trajectories of a baseline controller on the inner path, one per scenario."""
    return list(controller_episodes(name, scenarios, threads, observer))


class _Actor:
    """An agent's deterministic actions on a batch of observations: the first value of
    ``model.predict(obs, deterministic=True)``, bit for bit, at a fraction of its cost.

    ``predict`` costs about 0.26 ms a call on one row and 0.42 ms on 20 rows here, on one torch
    thread, most of it not the network: it switches every module to evaluation mode, checks the input
    and builds a torch ``Normal`` distribution (with its argument validation) to return its mean.
    Evaluation calls it once per group and step, 12,000 times per agent on the protocol, so that
    overhead was the largest share of an agent's cost after the physics. Here:

    * an SB3 actor-critic policy with a diagonal Gaussian (PPO's, PPO-Lagrangian's), whose
      ``get_distribution`` is SB3's own, gives the mean its distribution would return: the features,
      the actor's latent, ``action_net``, clipped to the action space (0.08 and 0.16 ms);
    * any other SB3 policy on Box spaces goes through its ``_predict`` (the path ``predict`` takes),
      with the mode switched once and the actions unscaled or clipped as ``predict`` does;
    * any other model (a plug-in algorithm's) is asked through its ``predict``.

    ``tests/test_eval_batching.py`` checks the bits against ``predict`` on every shipped agent."""

    def __init__(self, model: Any) -> None:
        from gymnasium import spaces

        from stable_baselines3.common.policies import BasePolicy

        self.model = model
        pol = getattr(model, "policy", None)
        # a torch policy of SB3's, with torch parameters; any other (sbx's JAX policies subclass
        # BasePolicy but hold none) acts through model.predict
        ok = (isinstance(pol, BasePolicy) and next(pol.parameters(), None) is not None
              and callable(getattr(pol, "_predict", None))
              and isinstance(getattr(pol, "observation_space", None), spaces.Box)
              and isinstance(getattr(pol, "action_space", None), spaces.Box)
              and len(pol.observation_space.shape) == 1)
        self.policy = pol if ok else None
        self.mean = self.plain = False
        self.layers: list[Any] | None = None  # the actor as torch functions, or None: the policy's _predict
        if ok:
            import torch
            from stable_baselines3.common.distributions import DiagGaussianDistribution
            from stable_baselines3.common.policies import ActorCriticPolicy, BaseModel

            self._torch = torch
            self.device = pol.device  # SB3 finds it by walking the parameters, at every call
            cls = type(pol)
            self.mean = (isinstance(pol, ActorCriticPolicy) and isinstance(pol.action_dist, DiagGaussianDistribution)
                         and not pol.squash_output
                         and all(getattr(cls, m) is getattr(ActorCriticPolicy, m)
                                 for m in ("_predict", "get_distribution", "_get_action_dist_from_latent")))
            pol.set_training_mode(False)
            if self.mean:
                self.layers = self._plain_layers(pol)
                if self.layers is None:  # the distribution's mean through the policy's own modules
                    self.layers = [lambda x: pol.action_net(pol.mlp_extractor.forward_actor(
                        BaseModel.extract_features(pol, x, pol.pi_features_extractor)))]
                else:
                    self.plain = True

    @staticmethod
    def _plain_layers(pol: Any) -> list[Any] | None:
        """The actor as a list of torch functions, when it is SB3's default MLP: a flatten feature
        extractor (SB3's preprocessing of a Box observation is ``.float()``; a batch of vectors is
        already flat), then Linear layers and element-wise activations, then ``action_net``. Each is
        the function the module's ``forward`` calls (``F.linear``, ``torch.tanh``, ...), so the bits
        are the same, without the per-module call machinery (about 10 us per module here)."""
        import torch
        from stable_baselines3.common.torch_layers import FlattenExtractor

        acts = {torch.nn.Tanh: torch.tanh, torch.nn.ReLU: torch.relu}
        net = pol.mlp_extractor.policy_net
        if (type(pol.pi_features_extractor) is not FlattenExtractor or type(pol.action_net) is not torch.nn.Linear
                or type(net) is not torch.nn.Sequential):
            return None
        ops: list[Any] = [lambda x: x.float()]
        for m in [*net, pol.action_net]:
            if type(m) is torch.nn.Linear:
                ops.append(lambda x, w=m.weight, b=m.bias: torch.nn.functional.linear(x, w, b))
            elif type(m) in acts:
                ops.append(acts[type(m)])
            elif type(m) is not torch.nn.Identity:
                return None
        return ops

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        pol = self.policy
        if pol is None:
            return self.model.predict(obs, deterministic=True)[0]
        torch = self._torch
        space = pol.action_space
        x = torch.as_tensor(np.array(obs).reshape((-1, *pol.observation_space.shape)), device=self.device)
        with torch.inference_mode():
            if self.layers is not None:
                for f in self.layers:
                    x = f(x)
                actions = x
            else:
                actions = pol._predict(x, deterministic=True)
        actions = actions.cpu().numpy().reshape((-1, *space.shape))
        if pol.squash_output:
            return pol.unscale_action(actions)
        return np.clip(actions, space.low, space.high)


def _batch_plan(groups: Sequence[Sequence[Scenario]], batch: int) -> list[list[tuple[int, int, int]]]:
    """How :func:`agent_group_episodes` steps ``groups``: a list of batches, each a list of parts
    ``(group, lo, hi)``. A group longer than ``batch`` is split into near-equal parts (none of one
    episode unless the group has one); consecutive parts of one duration share a batch while it
    holds at most ``batch`` episodes."""
    plan: list[list[tuple[int, int, int]]] = []
    size, dur = 0, None
    for g, scs in enumerate(groups):
        if not scs:
            continue
        parts = -(-len(scs) // batch)
        edges = np.linspace(0, len(scs), parts + 1).round().astype(int)
        for lo, hi in zip(edges[:-1], edges[1:]):
            d = scs[0].sim.duration
            if not plan or size + (hi - lo) > batch or d != dur:
                plan.append([])
                size, dur = 0, d
            plan[-1].append((g, int(lo), int(hi)))
            size += int(hi - lo)
    return plan


LAW_HOLD_S = 1.0
"""The law's reference runs advance this much simulated time per kernel call (``EnvCore.hold``):
the same numbers as one call per control period, without the Python of a step for each."""


def agent_group_episodes(model: Any, meta: dict[str, Any], norm: Any, groups: Sequence[Sequence[Scenario]],
                         threads: int | None = None, batch: int = AGENT_BATCH,
                         on_batch: Any = None, channels: Sequence[str] | None = None,
                         noise_seeds: Sequence[Sequence[int]] | None = None) -> Iterator[tuple[int, Any]]:
    """A trained agent's trajectories on several groups of scenarios: ``(group index, trajectory)``,
    each group's episodes in order, the groups in order.

    Episode i of a group draws its noise from ``default_rng(EVAL_SEED_OFFSET + i)``. The groups'
    episodes are packed into batched envs of at most ``batch`` arms (:func:`_batch_plan`), so the
    paper presets' single episodes ride along with a suite's instead of costing an env step each.
    The network is still called once per group (or part of a group) per step, on that part's rows
    alone, so every action is what it was when each group was stepped in a batch of its own (torch's
    last bits depend on the rows of a call: one row differs from several). Each record is released as
    its trajectory is handed over, so a caller that reduces them keeps at most one batch of records.
    ``on_batch(parts, wall_s)``, if given, is called after each batch with its parts and wall time.
    ``channels`` are the signals each trajectory keeps (``EnvCore``'s ``record_channels``; default
    all): :data:`blf_gym.results.metrics.METRIC_CHANNELS` is what the records read, a third of the memory.
    ``noise_seeds`` (one sequence per group, one seed per episode) replaces ``EVAL_SEED_OFFSET + i``
    as each episode's generator seed (blf-falsify searches over them).

    ``model`` None is the proposed law alone (a zero residual, the agent's env set-up otherwise): its
    episodes advance :data:`LAW_HOLD_S` at a time (``EnvCore.hold``), each arm drawing the same noise
    as a stepped agent's, so the trajectories are those of a zero residual stepped period by period."""
    from blf_gym.envs.envcore import EnvCore

    # the scenarios are given, no reward is needed (the metrics do not read it), termination is off:
    # the same env the loader checked the agent against
    kw = scoring_env_kwargs(meta["env_kwargs"])
    act = None if model is None else _Actor(model)
    # a policy that keeps per-arm state (``whole_batch``, e.g. the NMPC) sees every arm in one call
    whole = bool(getattr(model, "whole_batch", False))
    for parts in _batch_plan(groups, batch):
        t0 = time.perf_counter()
        scs = [sc for g, lo, hi in parts for sc in groups[g][lo:hi]]
        core = EnvCore(len(scs), record=True, record_channels=channels, threads=threads, **kw)
        rows, r = [], 0
        for g, lo, hi in parts:
            rows.append(slice(r, r + hi - lo))
            for i in range(hi - lo):
                seed = EVAL_SEED_OFFSET + lo + i if noise_seeds is None else int(noise_seeds[g][lo + i])
                core.rngs[r + i] = np.random.default_rng(seed)
            r += hi - lo
        core.reset_envs(range(len(scs)), scenarios=scs)
        obs = core.observe()
        periods = int(round(scs[0].sim.duration / core.control_period))
        if act is None and core.steps_per_period % core.sim.steps_per_sample == 0:
            zero, chunk = np.zeros((len(scs), core.n)), max(1, int(round(LAW_HOLD_S / core.control_period)))
            for lo in range(0, periods, chunk):
                core.hold(zero, min(chunk, periods - lo))
        else:  # an agent, or the law with periods shorter than a sample (hold needs whole samples)
            policy = act if act is not None else (lambda o: np.zeros((o.shape[0], core.n)))
            for _ in range(periods):
                o = norm.normalize_obs(obs) if norm is not None else obs
                if whole:  # one call with every arm: the policy keeps each row's state itself
                    obs, *_ = core.step(policy(o))
                    continue
                acts = [policy(o[rs]) for rs in rows]
                obs, *_ = core.step(acts[0] if len(acts) == 1 else np.concatenate(acts))
        if on_batch is not None:
            on_batch(parts, time.perf_counter() - t0)
        r = 0
        for g, lo, hi in parts:
            for _ in range(hi - lo):
                yield g, core.trajectory(r, release=True)
                r += 1


def agent_episodes(model: Any, meta: dict[str, Any], norm: Any, scenarios: Sequence[Scenario],
                   threads: int | None = None, batch: int = AGENT_BATCH) -> Iterator[Any]:
    """A trained agent's trajectories, one per scenario, in order (one group of
    :func:`agent_group_episodes`): ``batch`` episodes stepped together in one batched env at a time,
    episode i drawing its noise from ``default_rng(EVAL_SEED_OFFSET + i)``."""
    steps = {sc.sim.duration for sc in scenarios}
    if len(steps) > 1:
        raise ValueError("all evaluation scenarios of an agent must share one duration")
    for _, tr in agent_group_episodes(model, meta, norm, [scenarios], threads, batch):
        yield tr


def evaluate_agent(model: Any, meta: dict[str, Any], norm: Any, scenarios: Sequence[Scenario],
                   threads: int | None = None):
    """Trajectories of a trained agent, all episodes stepped together in batches of
    :data:`AGENT_BATCH` (:func:`agent_episodes`)."""
    return list(agent_episodes(model, meta, norm, scenarios, threads))


class _ZeroResidual:
    """The proposed law alone as an agent stepped period by period would be: a zero residual (the
    tests check the law's held runs, ``agent_group_episodes(None, ...)``, against it)."""

    def __init__(self, n: int = 3) -> None:
        self.n = n

    def predict(self, obs: np.ndarray, deterministic: bool = True):
        return np.zeros((obs.shape[0], self.n), dtype=np.float32), None


def with_filter(meta: dict[str, Any], name: str) -> dict[str, Any]:
    """An agent's metadata with its env's residual filter replaced: ``name`` (e.g. "barrier"), or
    "none" for no filter. The agent's name says so (``+barrier``, ``-filter``); the env kwargs, and
    so the results' provenance, record it. The look-ahead hand-back's keys (``lookahead``,
    ``demand``, ``predict``; blf_gym.envs.lookahead) may ride on the filter's:
    "barrier:handback=0.0033,lookahead=0.35"."""
    from blf_gym.envs.lookahead import split_lookahead
    from blf_gym.plugins.registry import make_controller

    if name != "none":
        try:
            # the name and its parameters, checked now
            make_controller("proposed").make_filter(split_lookahead(name)[0])
        except ValueError as exc:
            raise ValueError(f"--residual-filter must be 'none' or a filter of the proposed law "
                             f"{sorted(make_controller('proposed').filters)}, optionally with parameters "
                             f"('barrier:handback=0.0033', and lookahead=SECONDS for the look-ahead hand-back): "
                             f"{exc}") from None
    meta = json.loads(json.dumps(meta, default=str))
    kw = meta["env_kwargs"]
    had = kw.get("residual_filter")
    kw["residual_filter"] = None if name == "none" else name
    base = meta.get("name", "agent")
    if name == "none":
        meta["name"] = base + ("-filter" if had else "")
    elif had != name:
        meta["name"] = f"{base}+{name}"
    return meta


def law_env_kwargs(meta: dict[str, Any]) -> dict[str, Any]:
    """The env arguments of an agent's law reference (:func:`law_reference`): the agent's, with the
    proposed law as the inner controller and nothing the law alone does not use (no privileged
    observation, residual filter or extras). Two agents with the same ones share one reference."""
    kw = dict(meta["env_kwargs"])
    kw["controller"] = "proposed"
    # a zero residual is zero at any scale (and a plain agent's action scale is not the law's)
    for k in ("privileged", "residual_filter", "observation_extras", "residual_scale", "action_scale"):
        kw.pop(k, None)
    return scoring_env_kwargs(kw)


def law_reference_groups(groups: Sequence[Sequence[Scenario]], meta: dict[str, Any] | None = None,
                         threads: int | None = None,
                         noise_seeds: Sequence[Sequence[int]] | None = None) -> list[list[EpisodeStats]]:
    """:func:`law_reference` for several groups of scenarios at once (on the env path, their
    episodes share batched envs as an agent's do, :func:`agent_group_episodes`, and draw the same
    ``noise_seeds``)."""
    if meta is None:
        if noise_seeds is not None:
            raise ValueError("law_reference_groups: noise_seeds are for an agent's reference (meta given)")
        return [law_reference(scs, None, threads) for scs in groups]
    out: list[list[EpisodeStats]] = [[] for _ in groups]
    law = {"mode": "residual", "env_kwargs": law_env_kwargs(meta)}
    for g, tr in agent_group_episodes(None, law, None, groups, threads, channels=METRIC_CHANNELS,
                                      noise_seeds=noise_seeds):
        out[g].append(episode_stats(tr))
    return out


def law_reference(scenarios: Sequence[Scenario], meta: dict[str, Any] | None = None,
                  threads: int | None = None) -> list[EpisodeStats]:
    """The proposed law on the same episodes and noise as a policy's, each episode reduced to its
    :class:`blf_gym.results.metrics.EpisodeStats` (what ``summarize(law=...)`` reads; no signals are kept).

    For a baseline (``meta`` None) that is the inner path with the same noise seeds. For an agent
    it is the env path with a zero residual over the proposed law (:func:`law_env_kwargs`), the
    agent's control period and the same per-episode generators, so that the measurement noise
    sequence is the agent's."""
    if meta is None:
        return [episode_stats(t) for t in controller_episodes("proposed", scenarios, threads)]
    return law_reference_groups([scenarios], meta, threads)[0]


_EPILOG = """\
common cases:
  blf-eval                                      the whole protocol: every registered controller and
                                                the shipped agents, on the presets, the training
                                                suite's 20 held-out episodes and the 50 stress ones
  blf-eval --agents runs/mine                   one new agent against the law on the whole protocol:
                                                costs that agent (and the law, once)
  blf-eval --agents runs/mine --suite-seeds 0   the same on the paper presets alone (seconds)
  blf-eval --suite-seeds 0                      every controller and shipped agent, presets alone

The proposed law's episodes (its own row, and the reference of every score) are kept between runs
and reused when the code, numpy/numba, the CPU, the scenarios, the noise seeds and the env arguments
are all the same (records say law_reused); --fresh-law simulates them again."""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-eval", description=help_text(__doc__.split("\n\n")[0]), epilog=_EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--controllers", nargs="*", default=None, metavar="NAME",
                   help=f"baseline controllers to score on the inner path (default: every registered one, "
                        f"here {' '.join(registered_controllers())}; with --agents, the proposed law alone, the "
                        "reference every score is against; none with an empty list)")
    p.add_argument("--reference", default=REFERENCE, metavar="NAME",
                   help=f"the controller every record is also scored against (score_vs_reference; default "
                        f"{REFERENCE}, the best on the training suite when it was fixed; 'none' for no second "
                        "yardstick)")
    p.add_argument("--observer", default="leso", metavar="NAME",
                   help="observer of the baseline controllers (a registered plug-in; default leso)")
    p.add_argument("--agents", nargs="*", default=None, metavar="RUN",
                   help="trained agents: blf-train run folders or their model zips (default: the shipped "
                        "ones in agents/pretrained; none with an empty list)")
    p.add_argument("--policies", nargs="*", default=[], metavar="NAME",
                   help="registered policies (the blf_gym.policies entry points, e.g. nmpc or floor) to score like "
                        "agents, each with the env arguments it asks for; NAME:key=value,... passes parameters to "
                        "its factory (floor:control_period=0.001) (default: none; they can be slow)")
    p.add_argument("--residual-filter", default=None, metavar="NAME",
                   help="run every agent through this residual filter of the proposed law (barrier or cbf, with "
                        "parameters as barrier:handback=0.0033, and lookahead=0.35 for the look-ahead hand-back), its name "
                        "gaining +NAME, or 'none' to run every agent "
                        "without one (default: each agent's own, from its metadata)")
    p.add_argument("--scenarios", nargs="*", default=sorted(PRESETS), metavar="NAME",
                   help=f"paper presets (default: {' '.join(sorted(PRESETS))}; none with an empty list)")
    p.add_argument("--suite", nargs="+", default=list(PROTOCOL_SEEDS), choices=SUITES, metavar="SUITE",
                   help="suites to draw episodes from: randomized (the training suite's held-out seeds), stress "
                        "(held out, beyond the training ranges) and certificate (held out: early forces, corners "
                        "and uniform draws of the documented ranges, for the filters' certificate; not in the "
                        "protocol) (default: randomized stress)")
    p.add_argument("--suite-seeds", type=int, nargs="+", default=None, metavar="N",
                   help="episodes per suite, one count for all or one per --suite; 0 for the presets alone "
                        "(default: the protocol's 20 randomized and 50 stress, or 20 per suite named)")
    p.add_argument("--scenario-kwargs", type=str, default="{}", metavar="JSON",
                   help='scenario variations applied to every episode, e.g. \'{"payload": 0.15, "force": 20}\' '
                        "(default: none)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="episode length in s (default 30)")
    p.add_argument("--level", type=int, default=DEFAULT_LEVEL, metavar="L",
                   help="difficulty level of every episode, 0 to 3 (blf_gym.envs.levels; docs/levels.md): 0 the nominal "
                        "plant in 10x wider bounds, 1 the scenario's plant in 10x wider bounds, 2 no external force, "
                        f"3 the full benchmark (default {DEFAULT_LEVEL}); every record names its level")
    p.add_argument("--threads", type=int, default=None, metavar="T",
                   help="threads for each batched simulation (default: one per CPU with --jobs 1, else one, "
                        "as the workers share the CPUs)")
    p.add_argument("--jobs", type=int, default=None, metavar="J",
                   help=f"worker processes scoring pieces of the run at once, the costliest first: a policy's "
                        f"episodes, a baseline's group, the law's reference (default: one per CPU, at most "
                        f"{MAX_DEFAULT_JOBS}, or BLF_GYM_JOBS if set; 1 runs everything in this process). The "
                        "records are the same for any J; each worker runs its kernels on one thread unless "
                        "--threads says otherwise")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="folder for results.json, results.csv, plots and, written last, manifest.json, which "
                        "says complete: true only once every file is written (default: none, the table only)")
    p.add_argument("--save-traj", action="store_true",
                   help="with --out: also save trajectories as npz (default off)")
    p.add_argument("--no-plots", action="store_true", help="with --out: skip the PNG plots (default: drawn)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar (default: shown)")
    p.add_argument("--accept-changed-files", action="store_true",
                   help="score an agent whose model.zip or vecnormalize.pkl differs from the sha256 its metadata.json "
                        "recorded when it was saved (default: refused, naming the file)")
    p.add_argument("--fresh-law", action="store_true",
                   help="simulate the proposed law's episodes (its own row and every score's reference) even "
                        "when identical ones are kept from an earlier run: by default they are reused when the "
                        "code, the tools, the CPU, the scenarios, the noise seeds and the env arguments are all "
                        "the same (agents/lawcache.py), and the record's provenance says law_reused")
    return p


class _PlotTrace:
    """What the plots draw of a group's first episode (time, error, bounds, torque), kept instead of
    the whole trajectory: a third of its memory, for every policy and group."""

    def __init__(self, tr: Any) -> None:
        self.t, self.e1, self.k_a, self.k_b, self.u = tr.t, tr.e1, tr.k_a, tr.k_b, tr.u
        self.n_samples = tr.n_samples


TABLE_NAME_MAX = 28
"""The widest policy name blf-eval's table prints whole; a longer one keeps its start and end
around an ellipsis (results.json has every name whole)."""


def _fit(name: str, width: int = TABLE_NAME_MAX) -> str:
    if len(name) <= width:
        return name
    head = (width - 1) // 2
    return name[:head] + "\u2026" + name[len(name) - (width - 1 - head):]


def _num(x: float | None, digits: int = 4) -> str:
    """A table number in at most 8 characters: fixed point while it fits, else 1.23e+04."""
    if x is None:
        return "-"
    for p in range(digits, -1, -1):
        text = f"{x:.{p}f}"
        if len(text) <= 8 and (p >= 1 or abs(x) >= 100):
            return text
    return f"{x:.2e}"


def _table(records: Sequence[dict[str, Any]]) -> str:
    """blf-eval's console table: one row per record, each column as wide as its widest entry (so
    long names, labels and five-digit RMSEs keep the columns aligned), groups split by ``|``. The
    last column, ``div``, says ``yes`` when an episode of the group diverged."""
    head = [["policy", "kind", "scenario", "ep"], ["RMSE j1", "j2", "j3"], ["score"],
            ["viol", "frac", "fail", "cert"], ["CVaR"], ["excess", "margin"], ["1st viol"], ["u rms", "u peak"],
            ["div"]]
    rows = []
    for r in records:
        viol = sum(v for v in r["violations"] if v is not None)
        frac = max((v for v in r["violation_fraction"] if v is not None), default=0.0)
        exc = max((v for v in r["max_excursion_deg"] if v is not None), default=0.0)
        mar = min((v for v in r["min_margin_deg"] if v is not None), default=0.0)
        rows.append([
            [_fit(str(r["policy"])), r["kind"], r["scenario"], str(r["episodes"])],
            [_num(v) for v in r["rmse_deg"]],
            [_num(r.get("score_vs_law"), 3)],
            [str(viol), f"{frac:.4f}", f"{r['failure_rate']:.2f}", _num(r.get("certificate_broken"), 2)],
            [_num(r["rmse_cvar_deg"])],
            [_num(exc, 3), _num(mar, 3)],
            [_num(r["first_violation_s"], 3)],
            ["/".join("-" if v is None else f"{v:.1f}" for v in r[k]) for k in ("torque_rms", "torque_peak")],
            ["yes" if r["diverged"] else "-"]])
    widths = [[max(len(x) for x in col) for col in zip(*(row[g] for row in [head, *rows]))]
              for g in range(len(head))]
    left = {(0, 0), (0, 1), (0, 2)}  # names and labels read from the left, numbers from the right

    def line(row: list[list[str]]) -> str:
        return " | ".join(" ".join(x.ljust(w) if (g, i) in left else x.rjust(w)
                                   for i, (x, w) in enumerate(zip(cells, widths[g])))
                          for g, cells in enumerate(row)).rstrip()

    lines = [line(head)]
    lines.append("-" * len(lines[0]))
    lines += [line(row) for row in rows]
    return "\n".join(lines)


PLOT_STYLES = ("-", "-.", ":", (0, (5, 1, 1, 1, 1, 1)))
"""Line styles the plots cycle through, one per policy with its colour, widest first: so policies
whose curves overlap still show each other's (the bounds are black dashes)."""


def _figure(sc: str, rows: list[tuple[dict[str, Any], Any]], kind: str) -> Any:
    """One PNG's figure: each joint's tracking error with its bounds (``kind="error"``, as the
    paper's Figures 6 and 10) or its torque, for the group's first episode of each policy. Plain
    agents get a column of their own (their errors are often tens of degrees and would flatten the
    others'; a registered policy, such as the NMPC, is drawn with the laws). Each policy has its own
    colour, line style and width (:data:`PLOT_STYLES`), and the legend sits below the axes, where it
    covers no curve or bound."""
    import matplotlib.pyplot as plt

    def learned_plain(r: dict[str, Any]) -> bool:  # a registered policy (the NMPC) is drawn with the laws
        return r["kind"] == "plain" and not r.get("registered_policy")

    extra = [w for w, k in (("residual agents", "residual"), ("policies", "policy")) if any(
        (x[0]["kind"] == k) if k == "residual" else bool(x[0].get("registered_policy")) for x in rows)]
    columns = [("laws" + "".join(f" and {w}" for w in extra), [x for x in rows if not learned_plain(x[0])]),
               ("plain agents (own scale)", [x for x in rows if learned_plain(x[0])])]
    columns = [c for c in columns if c[1]]
    n = rows[0][1].e1.shape[1]  # joints: one row of axes each
    fig, axes = plt.subplots(n, len(columns), figsize=(9 if len(columns) == 1 else 14, 7.6 * (n / 3)), sharex=True,
                             squeeze=False)
    names = [r["policy"] for r, _ in rows]
    for col, (title, members) in enumerate(columns):
        plain = learned_plain(members[0][0])
        for j in range(n):
            ax = axes[j, col]
            for r, tr in members:
                i = names.index(r["policy"])
                y = np.degrees(tr.e1[:, j]) if kind == "error" else tr.u[:, j]
                ax.plot(tr.t, y, color=f"C{i % 10}", ls=PLOT_STYLES[i % len(PLOT_STYLES)],
                        lw=max(0.8, 2.0 - 0.3 * i), label=r["policy"])
            if kind == "error":
                tr = members[0][1]
                ax.plot(tr.t, np.degrees(tr.k_a[:, j]), "k--", lw=0.9, label="bounds")
                ax.plot(tr.t, -np.degrees(tr.k_b[:, j]), "k--", lw=0.9)
                if not plain:
                    # zoom on the steady bounds (they start at 29-34 deg and decay to 1-2 deg)
                    ax.set_ylim(-3 * np.degrees(tr.k_b[-1, j]), 3 * np.degrees(tr.k_a[-1, j]))
                ax.set_ylabel(f"e1_{j + 1} (deg)")
            else:
                ax.set_ylabel(f"u_{j + 1} (N m)")
            ax.grid(alpha=0.3)
        axes[0, col].set_title(title, fontsize=9)
        axes[-1, col].set_xlabel("t (s)")
    labels: dict[str, Any] = {}
    for ax in axes.flat:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            labels.setdefault(lab, h)
    fig.suptitle(f"{sc}: {'tracking error and its bounds' if kind == 'error' else 'commanded torque'}"
                 + ("" if rows[0][0]["episodes"] == 1 else f" (first of {rows[0][0]['episodes']} episodes)"),
                 fontsize=11)
    ncol = min(len(labels), 6)
    fig.legend(list(labels.values()), list(labels), loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    rows_of_legend = -(-len(labels) // ncol)
    fig.tight_layout(rect=(0, 0.03 + 0.035 * rows_of_legend, 1, 1))
    return fig


def _plots(results: list[tuple[dict[str, Any], list[Any]]], out: Path) -> list[Path]:
    """The PNGs of a blf-eval run: per scenario group, ``error_<group>.png`` and
    ``torque_<group>.png`` (:func:`_figure`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blf_gym.results.io import atomic_path

    written = []
    for sc in sorted({r["scenario"] for r, _ in results}):
        rows = [(r, trajs[0]) for r, trajs in results if r["scenario"] == sc and trajs and trajs[0].n_samples]
        if not rows:
            continue
        for kind in ("error", "torque"):
            fig = _figure(sc, rows, kind)
            path = out / f"{kind}_{sc}.png"
            with atomic_path(path) as tmp:
                fig.savefig(tmp, dpi=110, format="png")
            plt.close(fig)
            written.append(path)
    return written


def _checked_args(args: argparse.Namespace) -> dict[str, Any]:
    """Check blf-eval's arguments (ValueError names the option and what it accepts), fill in the
    defaults that depend on others; returns the scenario keyword arguments."""
    if args.save_traj and args.out is None:
        raise ValueError("--save-traj needs --out DIR")
    try:
        kwargs = json.loads(args.scenario_kwargs)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--scenario-kwargs is not valid JSON ({exc}); example: "
                         '\'{"payload": 0.15}\'') from exc
    if not isinstance(kwargs, dict):
        raise ValueError("--scenario-kwargs must be a JSON object")
    if args.jobs is None:
        args.jobs = default_jobs()
    elif args.jobs < 1:
        raise ValueError(f"--jobs must be an integer >= 1, got {args.jobs}")
    if args.controllers is None:
        # scoring one's own agent costs that agent and the law, not every baseline's rows
        args.controllers = ["proposed"] if args.agents else registered_controllers()
    for c in args.controllers:
        if c not in registered_controllers():
            raise ValueError(f"unknown controller {c!r}; accepted values: {registered_controllers()}")
    from blf_gym.plugins.registry import available_observers

    if args.observer not in available_observers():
        raise ValueError(f"unknown observer {args.observer!r}; accepted values: {available_observers()}")
    if args.out is not None:
        try:
            check_out_dir(args.out)  # a file, a read-only folder: said before anything runs
        except OSError as exc:
            raise ValueError(os_error_message(exc, args.out)) from None
    return kwargs


def _load_agents(args: argparse.Namespace, agent_paths: list[Path]) -> list[tuple]:
    """(path or name, model, metadata, normalization) of every agent folder and registered policy."""
    if agent_paths:
        # torch on one thread: an agent's network on a batch of 50 rows gains nothing from more,
        # and its idle threads beside the env's (and any other job) made each call 100 times
        # slower under load; the actions are the same to the bit on one thread or two
        import torch

        torch.set_num_threads(1)
    agents = [(p, *load_agent(p, bool(getattr(args, "accept_changed_files", False)))) for p in agent_paths]
    if args.residual_filter is not None:
        agents = [(p, model, with_filter(meta, args.residual_filter), norm) for p, model, meta, norm in agents]
    from blf_gym.plugins.registry import available_policies

    for name in args.policies:
        if name.partition(":")[0] not in available_policies():  # NAME or NAME:key=value,...
            raise ValueError(f"unknown policy {name!r}; accepted values: {available_policies()} (the "
                             "blf_gym.policies entry points)")
    return agents + [(POLICY_PREFIX + name, *load_policy(name)) for name in args.policies]


def main(argv: Sequence[str] | None = None) -> int:
    import shlex

    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    args.command = shlex.join(["blf-eval", *argv])
    workers: _Workers | None = None
    try:
        kwargs = _checked_args(args)
        seeds = args.suite_seeds if args.suite_seeds is not None else [PROTOCOL_SEEDS[s] for s in args.suite]
        groups = build_scenarios(args.scenarios, seeds, kwargs, args.duration, args.suite, args.level)
        if not groups:
            raise ValueError("no scenarios: give --scenarios and/or --suite-seeds")
        agent_paths = (sorted(PRETRAINED.glob("*/model.zip")) if args.agents is None
                       else [Path(a) for a in args.agents])
        if args.jobs > 1:  # they boot while the agents load below
            workers = _Workers(args.jobs, bool(agent_paths))
        agents = _load_agents(args, agent_paths)
        if not args.controllers and not agents:
            raise ValueError("nothing to evaluate: give --controllers and/or --agents")
    except ValueError as exc:
        if workers is not None:
            workers.close(now=True)
        print(f"blf-eval: error: {exc}", file=sys.stderr)
        return 2
    try:
        return _run(args, groups, agents, kwargs, workers)
    except ValueError as exc:  # e.g. a --duration that is no whole number of an agent's control periods
        print(f"blf-eval: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except _WorkerLost as exc:
        print(f"blf-eval: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        # the failing file is named (blf_gym.results.io.atomic_path sees to it); the set stays marked incomplete
        tail = "" if args.out is None else f"; the set in {args.out} is incomplete (no complete manifest.json)"
        print(f"blf-eval: error: {os_error_message(exc, args.out)}{tail}", file=sys.stderr)
        return 2
    finally:
        if workers is not None:
            workers.close(now=True)  # after an error; a finished run has closed them already


def _group_provenance(label: str, scenarios: Sequence[Scenario], kwargs: dict[str, Any],
                      level: int = DEFAULT_LEVEL) -> dict[str, Any]:
    suite = label.split("+")[0].split("@")[0]
    prov: dict[str, Any] = {"scenario_kwargs": kwargs or None, "noise_seeds": _noise_seeds(scenarios), "level": level}
    if suite in SUITES:
        off = suite_seed_offset(suite)
        prov.update(suite=suite, suite_seeds=[off + k for k in range(len(scenarios))])
    else:
        prov.update(suite=None, suite_seeds=None)
    return prov


@dataclass(frozen=True)
class _Context:
    """What every piece of a blf-eval run needs to know (sent once to each worker process)."""

    groups: list[tuple[str, list[Scenario]]]
    observer: str
    threads: int | None
    fresh: bool
    save_traj: bool
    out: Path | None
    want_first: bool
    residual_filter: str | None
    law_folder: Path
    accept_changed_files: bool = False
    reference: str | None = None

    def reference_key(self, g: int) -> str:
        """The law cache's key of the reference controller on the inner path on group ``g``."""
        label, scs = self.groups[g]
        return law_key(f"inner:{self.reference}", self.observer, scs, _noise_seeds(scs))

    def inner_key(self, g: int) -> str:
        """The law cache's key of the proposed law with the LESO on the inner path, on group ``g``."""
        label, scs = self.groups[g]
        return law_key("inner", "leso", scs, _noise_seeds(scs))


def _noise_seeds(scs: Sequence[Scenario]) -> list[int]:
    """The noise seeds of a group's episodes: episode i draws from ``default_rng(EVAL_SEED_OFFSET + i)``."""
    return [EVAL_SEED_OFFSET + i for i in range(len(scs))]


def _law_tag(meta: dict[str, Any]) -> str:
    """Names an agent's law reference: agents with the same :func:`law_env_kwargs` share it."""
    return json.dumps(law_env_kwargs(meta), sort_keys=True, default=str)


@dataclass(frozen=True)
class _Piece:
    """One independent piece of a blf-eval run: ``kind`` names its function in :data:`_PIECES`,
    ``args`` its arguments after the context; ``cost`` orders the pieces, longest first, when they
    run in parallel (a rough estimate in seconds of one core, from measured rates)."""

    kind: str
    args: tuple
    cost: float
    label: str
    job: int = -1
    """The job (policy) whose records it gives, -1 for a law reference."""


def _reduce(ctx: _Context, name: str, g: int, k: int, tr: Any, stats: list[Any], first: list[Any],
            files: list[Path]) -> None:
    """Reduce one episode as it comes: only the group's first is kept (for the plots), and with
    --save-traj each is written as it finishes, so memory does not grow with the number of episodes."""
    if k == 0 and ctx.want_first:
        first.append(_PlotTrace(tr))
    if ctx.save_traj:
        path = ctx.out / "traj" / f"{ctx.groups[g][0]}__{name}__{k}.npz"
        tr.save_npz(path)
        files.append(path)
    stats.append(episode_stats(tr))


def _baseline_piece(ctx: _Context, name: str, g: int) -> dict[str, Any]:
    """A baseline controller's episodes on group ``g`` (the law's own row from the law cache when
    it is kept there)."""
    label, scs = ctx.groups[g]
    stats: list[Any] = []
    first: list[Any] = []
    files: list[Path] = []
    # the law's own row is every other row's reference: kept between runs
    own_law = name == "proposed" and ctx.observer == "leso"
    hit = load_law(ctx.inner_key(g), len(scs)) if own_law and not ctx.fresh and not ctx.save_traj else None
    if hit is not None:
        stats, wall = hit
        if ctx.want_first:  # the plots' trace: the group's first episode alone
            first.append(_PlotTrace(next(controller_episodes(name, scs[:1], ctx.threads))))
    else:
        t0 = time.perf_counter()
        for k, tr in enumerate(controller_episodes(name, scs, ctx.threads, ctx.observer)):
            _reduce(ctx, name, g, k, tr, stats, first, files)
            del tr
        wall = time.perf_counter() - t0
        if own_law:
            store_law(ctx.inner_key(g), stats, wall)
    return {"stats": stats, "first": first, "wall": wall, "reused": hit is not None, "files": files}


def _inner_law_piece(ctx: _Context, g: int) -> list[Any]:
    """The proposed law with the LESO on the inner path on group ``g``: the baselines' reference
    when the law's own row is not scored (or scored with another observer)."""
    key = ctx.inner_key(g)
    hit = None if ctx.fresh else load_law(key, len(ctx.groups[g][1]))
    if hit is not None:
        return hit[0]
    t0 = time.perf_counter()
    stats = law_reference(ctx.groups[g][1], None, ctx.threads)
    store_law(key, stats, time.perf_counter() - t0)
    return stats


def _reference_piece(ctx: _Context, g: int) -> list[Any]:
    """The reference controller (:data:`REFERENCE`) on the inner path on group ``g``, reduced to
    EpisodeStats and kept in the law cache, when it is not one of the run's own rows."""
    key = ctx.reference_key(g)
    hit = None if ctx.fresh else load_law(key, len(ctx.groups[g][1]))
    if hit is not None:
        return hit[0]
    t0 = time.perf_counter()
    stats = [episode_stats(t) for t in controller_episodes(ctx.reference, ctx.groups[g][1], ctx.threads,
                                                           ctx.observer)]
    store_law(key, stats, time.perf_counter() - t0)
    return stats


def _law_env_piece(ctx: _Context, meta: dict[str, Any], gs: list[int], keys: list[str]) -> list[list[Any]]:
    """The law on the same episodes and noise as an agent's (its env set-up: control period, noise
    draws) on groups ``gs``, all in one go, each group kept in the law cache under its key."""
    t0 = time.perf_counter()
    computed = law_reference_groups([ctx.groups[g][1] for g in gs], meta, ctx.threads)
    wall = time.perf_counter() - t0
    total = sum(len(ctx.groups[g][1]) for g in gs)
    for g, key, stats in zip(gs, keys, computed):
        store_law(key, stats, wall * len(ctx.groups[g][1]) / total)
    return computed


def _agent_piece(ctx: _Context, name: str, agent: Any) -> dict[str, Any]:
    """An agent's episodes on every group; ``agent`` is its (model, metadata, statistics) or, in a
    worker process, the path it is loaded from (with the run's --residual-filter)."""
    if isinstance(agent, str):  # a registered policy, by name
        model, meta, norm = load_policy(agent)
    elif isinstance(agent, Path):
        import torch

        torch.set_num_threads(1)  # as in the main process (see main)
        model, meta, norm = load_agent(agent, ctx.accept_changed_files)
        if ctx.residual_filter is not None:
            meta = with_filter(meta, ctx.residual_filter)
    else:
        model, meta, norm = agent
    # the groups' episodes share batched envs: a group's wall time is its share (by episodes) of the
    # batches that stepped it
    walls = [0.0] * len(ctx.groups)

    def on_batch(parts: list[tuple[int, int, int]], wall_s: float) -> None:
        total = sum(hi - lo for _, lo, hi in parts)
        for g, lo, hi in parts:
            walls[g] += wall_s * (hi - lo) / total
    per: list[tuple[list[Any], list[Any]]] = [([], []) for _ in ctx.groups]
    files: list[Path] = []
    # the signals the records and plots read, unless every signal is saved
    channels = None if ctx.save_traj else METRIC_CHANNELS
    for g, tr in agent_group_episodes(model, meta, norm, [scs for _, scs in ctx.groups], ctx.threads,
                                      on_batch=on_batch, channels=channels):
        stats, first = per[g]
        _reduce(ctx, name, g, len(stats), tr, stats, first, files)
        del tr
    # a registered policy's own account (the NMPC's solve times and fallbacks), for the records
    report = model.report() if callable(getattr(model, "report", None)) else None
    if callable(getattr(model, "close", None)) and isinstance(agent, str):
        model.close()
    return {"per": per, "walls": walls, "files": files, "report": report}


_PIECES = {"baseline": _baseline_piece, "inner_law": _inner_law_piece, "reference": _reference_piece,
           "law_env": _law_env_piece,
           "agent": _agent_piece}


def _worker_start() -> None:
    """A worker process's set-up: Ctrl-C is the main process's to handle (it ends the workers)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _warm_up(agents: bool) -> None:
    """What a worker imports before its first piece: torch (on one thread) and SB3 when there are agents."""
    if agents:
        import stable_baselines3  # noqa: F401
        import torch

        torch.set_num_threads(1)


def _worker_piece(ctx: _Context, piece: _Piece) -> Any:
    lawcache.use_folder(ctx.law_folder)
    return _PIECES[piece.kind](ctx, *piece.args)


class _Workers:
    """blf-eval's worker processes (spawned, not forked: this process has threads, the progress
    bar's and torch's, that a fork would copy in whatever state they were in). They are started
    before the agents are loaded, so that they boot (Python, numba, torch: seconds each) while this
    process checks the agents."""

    def __init__(self, jobs: int, agents: bool) -> None:
        import concurrent.futures as cf
        import multiprocessing as mp

        before = set(mp.active_children())
        self.pool = cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                                           initializer=_worker_start)
        for _ in range(jobs):  # each submit starts a worker while none is idle
            self.pool.submit(_warm_up, agents)
        self.processes = [p for p in mp.active_children() if p not in before]

    def close(self, now: bool = False) -> None:
        """Shut the workers down; ``now``: end them, whatever they are running."""
        if now:
            self.pool.shutdown(wait=False, cancel_futures=True)
            for proc in self.processes:
                if proc.is_alive():
                    proc.terminate()
        else:
            self.pool.shutdown()


def default_jobs() -> int:
    """blf-eval's default number of worker processes: ``BLF_GYM_JOBS`` if set, else one per CPU this
    process may run on, at most :data:`MAX_DEFAULT_JOBS`."""
    env = os.environ.get("BLF_GYM_JOBS")
    if env is not None:
        try:
            jobs = int(env)
        except ValueError:
            jobs = 0
        if jobs < 1:
            raise ValueError(f"BLF_GYM_JOBS must be an integer >= 1 (blf-eval's default --jobs), got {env!r}")
        return jobs
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, MAX_DEFAULT_JOBS))


MAX_DEFAULT_JOBS = 4
"""The most worker processes blf-eval starts unless told (``--jobs``): each holds its own compiled
kernels, torch and a batch of episodes, so memory grows with them."""


class _WorkerLost(RuntimeError):
    """A worker process ended without its result (killed, out of memory, or never started)."""


def _execute(ctx: _Context, pieces: list[_Piece], workers: _Workers | None, done: Any, started: Any) -> None:
    """Run ``pieces``: in this process, in order, without ``workers``; else in the worker processes,
    the costliest first (each worker takes the next piece when it is free). ``started(piece)`` and
    ``done(piece, result)`` are called in this process, ``done`` as each piece finishes. The results
    do not depend on the workers: every piece is computed from its own seeds, whatever runs beside it."""
    if workers is None:
        for piece in pieces:
            started(piece)
            done(piece, _PIECES[piece.kind](ctx, *piece.args))
        return
    import concurrent.futures as cf

    try:
        futures = {}
        for piece in sorted(pieces, key=lambda p: -p.cost):
            futures[workers.pool.submit(_worker_piece, ctx, piece)] = piece
            started(piece)
        for fut in cf.as_completed(futures):
            try:
                result = fut.result()
            except cf.process.BrokenProcessPool:
                raise _WorkerLost(
                    f"a worker process ended abruptly while scoring {futures[fut].label} (killed, out of memory, or "
                    "it could not start: a script that calls agents.evaluate.main needs an "
                    "'if __name__ == \"__main__\":' guard); --jobs 1 runs everything in this process") from None
            done(futures[fut], result)
    except BaseException:
        # Ctrl-C or a failed piece: the workers are ended now, not after their current piece
        workers.close(now=True)
        raise
    workers.close()


def _ready_kernels(jobs: Sequence[tuple[str, str, Any]], groups: Sequence[tuple[str, list[Scenario]]],
                   observer: str, laws_needed: bool, extra: Sequence[str] = ()) -> None:
    """Compile (or load) every closed-loop kernel the run steps, before the progress bar starts, as
    a phase of its own: each build says so on standard error, and the bar's rate and time left are
    then measured on the runs alone (a first run's compiles made the first step look like minutes
    and the bar predict hours). The agents' kernels were built when they were loaded
    (agents.loading); this builds the baselines' (and the law's, on both paths)."""
    import time

    from blf_gym.envs.envcore import EnvCore
    from blf_gym.kernel.simulate import ClosedLoop

    t0 = time.perf_counter()
    sc = groups[0][1][0] if groups and groups[0][1] else None
    if sc is None:
        return
    names = [name for name, _, agent in jobs if agent is None] + (["proposed"] if laws_needed else []) + list(extra)
    for name in dict.fromkeys(names):
        ClosedLoop([sc, sc], name, observer)  # a batch build, as the baselines' batches step
    for _, _, agent in jobs:
        if agent is not None and not agent[2].get("policy"):
            EnvCore(2, threads=1, **law_env_kwargs(agent[2]))  # the agent's law reference
    took = time.perf_counter() - t0
    if took > 2.0:
        print(f"blf-eval: closed-loop kernels ready ({took:.0f} s); scoring now", file=sys.stderr, flush=True)


def _reference_name(name: str | None) -> str | None:
    """The ``--reference`` controller, checked against the registered ones ('none': no reference)."""
    if name is None or name == "none":
        return None
    from blf_gym.plugins.registry import available_controllers

    if name not in available_controllers():
        raise ValueError(f"--reference {name!r} is not a registered controller; accepted: "
                         f"{[c for c in available_controllers() if c != 'none']} or 'none'")
    return name


def _cost(scs: Sequence[Scenario], per_step: float, period: float | None = None) -> float:
    """A piece's rough cost in seconds of one core: measured here, the inner path costs about 5 ms
    per simulated second of an episode, and an env path about 4 ms plus ``per_step`` per agent step."""
    sim_s = sum(sc.sim.duration for sc in scs)
    return sim_s * (5e-3 if period is None else 4e-3 + per_step / period)


def _run(args: argparse.Namespace, groups: list[tuple[str, list[Scenario]]], agents: list,
         kwargs: dict[str, Any] | None = None, workers: _Workers | None = None) -> int:
    """Score every job (controller or agent) on ``groups``; print the table and write the outputs."""
    run = _Run(args, groups, agents, kwargs or {}, workers)
    run.plan()
    if args.out is not None:  # before anything is written: an earlier complete set's manifest goes
        begin_output_set(args.out, run.meta_out.get("command"))
    run.open_bar()
    try:
        _execute(run.ctx, run.pieces, workers, run.done, run.started)
    except KeyboardInterrupt:
        print("\nblf-eval: interrupted" + (f"; finished records were saved to {args.out / 'results.json'}, "
                                           "and manifest.json marks the set incomplete" if args.out else ""),
              file=sys.stderr)
        return 130
    finally:
        if run.bar is not None:
            run.bar.close()
    run.report()
    return 0


class _Run:
    """One blf-eval run in pieces: the jobs, the pieces that score them (:meth:`plan`), and the
    records, each finished once the law (and the reference) it is scored against is known."""

    def __init__(self, args: argparse.Namespace, groups: list[tuple[str, list[Scenario]]], agents: list,
                 kwargs: dict[str, Any], workers: _Workers | None) -> None:
        from blf_gym.results.metrics import provenance

        self.args, self.groups, self.kwargs = args, groups, kwargs
        self.meta_out = provenance(command=getattr(args, "command", None))
        jobs: list[tuple[str, str, Any]] = [(c, "baseline", None) for c in args.controllers]
        jobs += [(meta.get("name") or Path(p).parent.name, meta["mode"], (p, model, meta, norm))
                 for p, model, meta, norm in agents]
        self.jobs = jobs
        self.n_jobs = 1 if workers is None else getattr(args, "jobs", 1)
        self.ctx = _Context(groups=groups, observer=args.observer,
                            # the workers share the cores: one thread each unless told
                            threads=args.threads if args.threads is not None or self.n_jobs <= 1 else 1,
                            fresh=bool(getattr(args, "fresh_law", False)), save_traj=bool(args.save_traj),
                            out=args.out, want_first=args.out is not None and not args.no_plots,
                            residual_filter=getattr(args, "residual_filter", None), law_folder=lawcache.folder(),
                            accept_changed_files=bool(getattr(args, "accept_changed_files", False)),
                            reference=_reference_name(getattr(args, "reference", None)))
        # the pieces, and which law each record is scored against: ("inner", g) for a baseline, (tag, g)
        # for an agent, tag naming the agent's env set-up; laws[...] fills as pieces finish
        self.pieces: list[_Piece] = []
        self.laws: dict[tuple[str, int], list[Any]] = {}
        self.own_law = "proposed" in args.controllers and args.observer == "leso"
        self.law_tags: dict[int, str] = {}
        # the second yardstick: the reference's own rows serve when it is scored, else its episodes alone
        self.ref_scored = self.ctx.reference is not None and self.ctx.reference in args.controllers
        self.refs: dict[int, list[Any]] = {}
        # (job, group, record, [the group's first episode, for the plots]); the table lists them in the
        # order of the jobs and groups, whatever order they ran in
        self.results: list[tuple[int, int, dict[str, Any], list[Any]]] = []
        self.traj_files: list[Path] = []
        self.waiting: list[tuple[int, int, dict[str, Any], tuple[str, int]]] = []  # records waiting for their law
        self.running: list[str] = []
        self.bar: Any = None

    def plan(self) -> None:
        """The pieces: each baseline per group, each agent (with its law's episodes where the law
        cache lacks them), and the law's and the reference's own episodes where no row gives them."""
        groups, jobs = self.groups, self.jobs
        # the proposed law's own row runs first: it is every other baseline's reference too
        order = sorted(range(len(jobs)),
                       key=lambda j: not (jobs[j][0] == "proposed" and jobs[j][2] is None and self.own_law))
        for j in order:
            name, _, agent = jobs[j]
            if agent is None:
                for g, (label, scs) in enumerate(groups):
                    self.pieces.append(_Piece("baseline", (name, g), _cost(scs, 0.0), f"{name} / {label}", j))
            else:
                self._plan_agent(j, name, agent)
        if any(agent is None for _, _, agent in jobs) and not self.own_law:
            for g, (label, scs) in enumerate(groups):
                self.pieces.append(_Piece("inner_law", (g,), _cost(scs, 0.0), f"the law / {label}"))
        if self.ctx.reference is not None and not self.ref_scored:
            for g, (label, scs) in enumerate(groups):
                self.pieces.append(_Piece("reference", (g,), _cost(scs, 0.0),
                                          f"{self.ctx.reference} (the reference) / {label}"))

    def _plan_agent(self, j: int, name: str, agent: tuple) -> None:
        path, model, meta, norm = agent
        groups = self.groups
        period = float(meta["env_kwargs"].get("control_period", 0.01))
        # the law on the same episodes and noise as this agent's: one piece for every agent that
        # shares its env set-up (control period, noise draws), all groups the cache lacks in one go
        kw, tag = law_env_kwargs(meta), _law_tag(meta)
        first_of_tag = tag not in self.law_tags.values()
        self.law_tags[j] = tag
        if first_of_tag:
            keys = [law_key("env", kw.get("observer", "leso"), scs, _noise_seeds(scs), kw) for _, scs in groups]
            missing = []
            for g, (_, scs) in enumerate(groups):
                hit = None if self.ctx.fresh else load_law(keys[g], len(scs))
                if hit is not None:
                    self.laws[(tag, g)] = hit[0]
                else:
                    missing.append(g)
            if missing:
                self.pieces.append(_Piece("law_env", (meta, missing, [keys[g] for g in missing]),
                                          _cost([sc for g in missing for sc in groups[g][1]], 0.0, period),
                                          f"{name} / the law's reference"))
        whole = [sc for _, scs in groups for sc in scs]
        self.pieces.append(_Piece("agent", (name, path if self.n_jobs > 1 else (model, meta, norm)),
                                  _cost(whole, 8e-5, period), name, j))

    def open_bar(self) -> None:
        """The progress bar (after compiling the kernels the run needs), unless --no-progress."""
        if self.args.no_progress:
            return
        from tqdm import tqdm

        ctx = self.ctx
        _ready_kernels(self.jobs, self.groups, self.args.observer,
                       laws_needed=any(p.kind in ("law_env", "inner_law") for p in self.pieces) or self.own_law,
                       extra=[ctx.reference] if ctx.reference is not None and not self.ref_scored else [])
        self.bar = tqdm(total=len(self.jobs) * len(self.groups), unit="run", desc="blf-eval", file=sys.stderr,
                        leave=False)

    def finish(self, j: int, g: int, part: dict[str, Any], law: list[Any]) -> None:
        """Summarize job ``j``'s episodes of group ``g`` into a record, against ``law``."""
        args, ctx = self.args, self.ctx
        name, kind, agent = self.jobs[j]
        label, scs = self.groups[g]
        prov = _group_provenance(label, scs, self.kwargs, getattr(args, "level", DEFAULT_LEVEL))
        if part.get("reused"):  # the episodes were kept from an earlier identical run (agents/lawcache.py)
            prov.update(law_reused=True)
        if agent is not None:
            meta = agent[2]
            prov.update(env_kwargs=meta.get("env_kwargs"), train_seed=meta.get("seed"),
                        observer=(meta.get("env_kwargs") or {}).get("observer", "leso"))
            if meta.get("policy"):  # a registered policy: its name and its own account of the run
                prov.update(registered_policy=meta["policy"], policy_report=part.get("report"))
        else:
            prov.update(observer=args.observer)
        own = agent is None and name == ctx.reference  # the reference is not scored against itself
        rec = summarize(part["stats"], name, kind, label, scs[0].sim.dt, wall_s=part["wall"], law=law,
                        provenance=prov, reference=None if own else self.refs.get(g),
                        reference_name=ctx.reference)
        self.results.append((j, g, rec, part["first"]))
        self.results.sort(key=lambda r: r[:2])
        if self.bar is not None:
            self.bar.update(1)
        if args.out is not None:  # finished records are kept if the run is interrupted
            write_results([r[2] for r in self.results], args.out, self.meta_out)

    def _ref_ready(self, w: tuple[int, int, dict[str, Any], tuple[str, int]]) -> bool:
        j, g = w[0], w[1]
        return g in self.refs or (self.jobs[j][2] is None and self.jobs[j][0] == self.ctx.reference)

    def settle(self) -> None:
        """Finish every record whose law (and reference) is known now."""
        for item in [w for w in self.waiting
                     if w[3] in self.laws and (self.ctx.reference is None or self._ref_ready(w))]:
            self.waiting.remove(item)
            self.finish(item[0], item[1], item[2], self.laws[item[3]])

    def started(self, piece: _Piece) -> None:
        self.running.append(piece.label)
        if self.bar is not None:
            self.bar.set_postfix_str(", ".join(self.running[-2:]) if self.n_jobs > 1 else piece.label)

    def done(self, piece: _Piece, result: Any) -> None:
        """Take a finished piece's result: a record waiting for its law, or a law or reference."""
        if piece.label in self.running:
            self.running.remove(piece.label)
        if piece.kind == "baseline":
            name, g = piece.args
            if name == "proposed" and self.own_law:
                self.laws.setdefault(("inner", g), result["stats"])  # the law is this row itself
            if self.ref_scored and name == self.ctx.reference:
                self.refs.setdefault(g, result["stats"])  # the reference is this row itself
            self.traj_files.extend(result["files"])
            self.waiting.append((piece.job, g, result, ("inner", g)))
        elif piece.kind == "inner_law":
            self.laws[("inner", piece.args[0])] = result
        elif piece.kind == "reference":
            self.refs[piece.args[0]] = result
        elif piece.kind == "law_env":
            for g, stats in zip(piece.args[1], result):
                self.laws[(_law_tag(piece.args[0]), g)] = stats
        else:
            j = piece.job
            self.traj_files.extend(result["files"])
            for g, (stats, first) in enumerate(result["per"]):
                self.waiting.append((j, g, {"stats": stats, "first": first, "wall": result["walls"][g],
                                            "report": result.get("report")}, (self.law_tags[j], g)))
        self.settle()

    def report(self) -> None:
        """Print the table and its legend; write the results, plots and manifest under --out."""
        args = self.args
        records = [r[2] for r in self.results]
        print(_table(records))
        print("\n" + textwrap.fill(_LEGEND, 100))
        if args.out is not None:
            files = list(write_results(records, args.out, self.meta_out))
            written = [] if args.no_plots else _plots([(r[2], r[3]) for r in self.results], args.out)
            files += written + self.traj_files
            # last, so that a complete manifest means every file above is in place
            manifest = finish_output_set(args.out, files, self.meta_out.get("command"))
            print(f"wrote {args.out / 'results.json'}, {args.out / 'results.csv'}"
                  + (f", {len(written)} plots" if written else "")
                  + (f", {len(files) - 2 - len(written)} trajectory files" if args.save_traj else "")
                  + f" and, last, {manifest}")


_LEGEND = (
    "RMSE per joint, pooled over the group's episodes, in degrees; score: score_vs_law, the geometric mean "
    "over joints of the law's RMSE over the policy's (1 = the law, higher is better), on the pooled RMSEs "
    "(per episode in results.json). viol: violating 1 ms samples summed over joints and episodes; frac: the "
    "worst joint's violating fraction; fail: share of episodes with a violation or divergence; cert: "
    "certificate_broken, the share of episodes where the policy violates and the law alone, on the same "
    "scenario and noise, does not. CVaR: mean RMSE (averaged over joints) of the worst half of the episodes; "
    "excess (largest distance beyond a bound) and margin (closest approach to a bound, negative when "
    "beyond): worst joint, in degrees; 1st viol: earliest violation (s); torques in N m per joint; div: yes "
    "when an episode's simulation diverged (results.json: diverged). Names longer than "
    f"{TABLE_NAME_MAX} characters are shortened here, not in results.json.")
"""The printed table's legend."""


if __name__ == "__main__":
    raise SystemExit(main())
