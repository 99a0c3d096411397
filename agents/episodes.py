"""blf-eval's episodes: the scenario groups it scores (the presets and the suites' held-out
draws), the batched episodes of a controller on the inner path and of agents in batched envs
(:class:`_Actor` acts for a batch), the law's reference on an agent's own env set-up, and the
residual filters an agent can be scored through. :mod:`agents.evaluate` re-exports the public names."""

from __future__ import annotations

import json
import time
from typing import Any, Iterator, Sequence

import numpy as np

from blf_gym.results.metrics import METRIC_CHANNELS, EpisodeStats, episode_stats
from blf_gym.envs.levels import DEFAULT_LEVEL, apply_level, check_level
from blf_gym.envs.envcore import named_block
from blf_gym.model.family import PAPER_LINKS, check_n_links, family_preset, family_presets, member_arm
from blf_gym.model.params import PRESETS, Scenario, preset
from blf_gym.envs.protocol import (CURVE_GROUPS, EVAL_SEED_OFFSET, PROTOCOL_SEEDS, REFERENCE, SUITES,  # noqa: F401 (re-exported)
                                   suite_seed_offset)
from blf_gym.envs.scenarios import apply_variations, sample_suite, variation_label

# the one agent loader, re-exported here
from .loading import scoring_env_kwargs

__all__ = ["registered_controllers", "curve_scenarios", "build_scenarios", "CONTROLLER_BATCH", "AGENT_BATCH",
           "member_blocks", "controller_episodes", "evaluate_controller", "LAW_HOLD_S", "agent_group_episodes", "agent_episodes",
           "evaluate_agent", "with_filter", "law_env_kwargs", "law_reference_groups", "law_reference"]



def registered_controllers() -> list[str]:
    """The inner controllers registered in the ``blf_gym.controllers`` entry-point group."""
    from blf_gym.plugins.registry import available_controllers

    return [c for c in available_controllers() if c != "none"]


def curve_scenarios(suite_seeds: int, duration: float | None = None, level: int = DEFAULT_LEVEL,
                    n_links: int | None = None) -> list[tuple[str, list[Scenario]]]:
    """The scenarios of :data:`CURVE_GROUPS`, labelled by group: the paper presets and
    ``suite_seeds`` held-out episodes of the training suite, ``duration`` seconds each (None: the
    presets' 30 s), at difficulty ``level`` (an agent's curve is drawn at the level it trains at).
    On another member of the task family (``n_links``, the agent's) the groups are its own, under
    the same labels, which name roles (the 0.1 Hz preset, the 0.5 Hz preset, the training suite):
    the curve file's ``env_kwargs`` say which arm."""
    groups = build_scenarios(list(PRESETS), suite_seeds, {}, duration, level=level, n_links=n_links)
    return [(role, scs) for role, (_, scs) in zip(CURVE_GROUPS, groups)]


def build_scenarios(
    presets: Sequence[str], suite_seeds: "int | Sequence[int]", kwargs: dict[str, Any], duration: float | None,
    suite: "str | Sequence[str]" = "randomized", level: int = DEFAULT_LEVEL, n_links: int | None = None,
) -> list[tuple[str, list[Scenario]]]:
    """[(scenario label, episodes)]: each preset is one episode; each suite in ``suite`` has its
    ``suite_seeds`` episodes (one count for all suites, or one per suite).

    With variations (``kwargs``) every label gains them (:func:`variation_label`: ``+frequency=0.5``,
    or ``+custom`` when they do not fit in a short label), so a varied result is never mistaken for
    the plain one; the variations themselves are recorded in each record's provenance by blf-eval.
    Below the full benchmark (``level`` 3, blf_gym.envs.levels) every episode is taken to that level after
    its draw and its variations, and every label gains ``@L<level>``.

    With ``n_links`` (2 to 7, :mod:`blf_gym.model.family`) the groups are that member's: a paper
    preset's name stands for the member's preset of the same frequency (``paper-0.1hz`` is
    ``n5-0.1hz`` at 5 links), the suites are drawn around its 0.1 Hz preset with the same seeds, and
    a suite's label names the member (``n5-randomized``); at 3 links, or None, the paper's groups."""
    level = check_level("blf-eval: --level", level)
    if n_links is not None:
        n_links = check_n_links("blf-eval: --n-links", n_links)
    member = n_links is not None and n_links != PAPER_LINKS
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
        sc = family_preset(family_presets(n_links)[list(PRESETS).index(name)], **sim_over) if member else preset(
            name, **sim_over)
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
            base = family_preset(family_presets(n_links)[0], **sim_over) if member else preset("paper-0.1hz", **sim_over)
            sc = sample_suite(np.random.default_rng(offset + k), base, name)
            if kwargs:
                sc = apply_variations(sc, kwargs)
            eps.append(apply_level(sc, level))
        groups.append(((f"n{n_links}-" if member else "") + name + variation_label(kwargs) + tag, eps))
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


def member_blocks(name: Any, observer: Any, scenarios: Sequence[Scenario]) -> tuple[Any, Any]:
    """The controller and observer for episodes of one arm: the names as they are on the paper's 3
    links; on another arm, built with it as their model (the task family's member it is a draw of,
    else the scenario's own arm) and their gains carried to it (blf_gym.envs.envcore.named_block),
    or one ValueError naming the block that cannot serve it."""
    n = scenarios[0].arm.n_links if scenarios else PAPER_LINKS
    if n == PAPER_LINKS:
        return name, observer
    arm = member_arm(scenarios[0].arm) or scenarios[0].arm
    return (named_block("blf-eval:", "controller", name, arm), named_block("blf-eval:", "observer", observer, arm))


def controller_episodes(name: str, scenarios: Sequence[Scenario], threads: int | None = None,
                        observer: str = "leso", batch: int = CONTROLLER_BATCH) -> Iterator[Any]:
    """A baseline controller's trajectories on the inner path, one per scenario, in order, computed
    ``batch`` episodes at a time (episode i has noise seed ``EVAL_SEED_OFFSET + i``), so a caller
    that reduces each one as it comes keeps at most a batch of 1 ms records in memory. Episodes on
    an arm of the task family other than the paper's take the member's blocks (:func:`member_blocks`)."""
    from blf_gym.kernel.simulate import LANES, simulate_batch

    name, observer = member_blocks(name, observer, scenarios)
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
    """The proposed law alone as an agent stepped period by period would be: a zero residual of
    ``n`` entries, one per joint (the tests check the law's held runs, ``agent_group_episodes(None,
    ...)``, against it). Without ``n``, the paper presets' arm's (every preset is the paper's arm)."""

    def __init__(self, n: int | None = None) -> None:
        self.n = preset("paper-0.1hz").arm.n_links if n is None else int(n)

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
