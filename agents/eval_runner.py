"""blf-eval's run in pieces: a baseline on one scenario group, an agent on every group, the law's
and the reference's own episodes where no row gives them (:class:`_Piece`); :func:`run` plans
them, runs them (in this process or in :class:`Workers`, the costliest first) and finishes each
record once the law it is scored against is known (:class:`_Run`)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence


from blf_gym.results.io import begin_output_set, finish_output_set
from blf_gym.results.metrics import METRIC_CHANNELS, episode_stats, summarize, write_results
from blf_gym.envs.levels import DEFAULT_LEVEL
from blf_gym.model.params import Scenario
from blf_gym.envs.protocol import (CURVE_GROUPS, EVAL_SEED_OFFSET, PROTOCOL_SEEDS, REFERENCE, SUITES,  # noqa: F401 (re-exported)
                                   suite_seed_offset)

from . import lawcache
from .lawcache import law_key, load_law, store_law
# the one agent loader, re-exported here
from .loading import load_agent, load_policy
from .episodes import (agent_group_episodes, controller_episodes, member_blocks, law_env_kwargs, law_reference,
                       law_reference_groups, with_filter)
from .eval_tables import LEGEND, PlotTrace, plots, table

__all__ = ["run", "Workers", "WorkerLost", "default_jobs", "MAX_DEFAULT_JOBS"]



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
        first.append(PlotTrace(tr))
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
            first.append(PlotTrace(next(controller_episodes(name, scs[:1], ctx.threads))))
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


class Workers:
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


class WorkerLost(RuntimeError):
    """A worker process ended without its result (killed, out of memory, or never started)."""


def _execute(ctx: _Context, pieces: list[_Piece], workers: Workers | None, done: Any, started: Any) -> None:
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
                raise WorkerLost(
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
    firsts = {scs[0].arm.n_links: scs[0] for _, scs in groups if scs}  # one build per member of the family
    if not firsts:
        return
    names = [name for name, _, agent in jobs if agent is None] + (["proposed"] if laws_needed else []) + list(extra)
    for name in dict.fromkeys(names):
        for sc in firsts.values():
            ClosedLoop([sc, sc], *member_blocks(name, observer, [sc]))  # a batch build, as the baselines' batches step
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


def run(args: argparse.Namespace, groups: list[tuple[str, list[Scenario]]], agents: list,
         kwargs: dict[str, Any] | None = None, workers: Workers | None = None) -> int:
    """Score every job (controller or agent) on ``groups``; print the table and write the outputs."""
    job = _Run(args, groups, agents, kwargs or {}, workers)
    job.plan()
    if args.out is not None:  # before anything is written: an earlier complete set's manifest goes
        begin_output_set(args.out, job.meta_out.get("command"))
    job.open_bar()
    try:
        _execute(job.ctx, job.pieces, workers, job.done, job.started)
    except KeyboardInterrupt:
        print("\nblf-eval: interrupted" + (f"; finished records were saved to {args.out / 'results.json'}, "
                                           "and manifest.json marks the set incomplete" if args.out else ""),
              file=sys.stderr)
        return 130
    finally:
        if job.bar is not None:
            job.bar.close()
    job.report()
    return 0


class _Run:
    """One blf-eval run in pieces: the jobs, the pieces that score them (:meth:`plan`), and the
    records, each finished once the law (and the reference) it is scored against is known."""

    def __init__(self, args: argparse.Namespace, groups: list[tuple[str, list[Scenario]]], agents: list,
                 kwargs: dict[str, Any], workers: Workers | None) -> None:
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
        print(table(records))
        print("\n" + textwrap.fill(LEGEND, 100))
        if args.out is not None:
            files = list(write_results(records, args.out, self.meta_out))
            written = [] if args.no_plots else plots([(r[2], r[3]) for r in self.results], args.out)
            files += written + self.traj_files
            # last, so that a complete manifest means every file above is in place
            manifest = finish_output_set(args.out, files, self.meta_out.get("command"))
            print(f"wrote {args.out / 'results.json'}, {args.out / 'results.csv'}"
                  + (f", {len(written)} plots" if written else "")
                  + (f", {len(files) - 2 - len(written)} trajectory files" if args.save_traj else "")
                  + f" and, last, {manifest}")
