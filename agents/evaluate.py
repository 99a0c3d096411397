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
import sys
from pathlib import Path
from typing import Any, Sequence


from blf_gym.results.io import check_out_dir, help_text, os_error_message
from blf_gym.envs.levels import DEFAULT_LEVEL
from blf_gym.model.params import PRESETS
from blf_gym.envs.protocol import (CURVE_GROUPS, EVAL_SEED_OFFSET, PROTOCOL_SEEDS, REFERENCE, SUITES,  # noqa: F401 (re-exported)
                                   suite_seed_offset)

# the one agent loader, re-exported here
from .loading import POLICY_PREFIX, PRETRAINED, load_agent, load_policy
from .episodes import (AGENT_BATCH, CONTROLLER_BATCH, LAW_HOLD_S, agent_episodes,  # noqa: F401 (re-exported)
                       agent_group_episodes, build_scenarios, controller_episodes, curve_scenarios,
                       evaluate_agent, evaluate_controller, law_env_kwargs, law_reference, law_reference_groups,
                       registered_controllers, with_filter)
from .eval_runner import MAX_DEFAULT_JOBS, WorkerLost, Workers, default_jobs, run  # noqa: F401 (re-exported)
from .eval_tables import TABLE_NAME_MAX  # noqa: F401 (re-exported)
from blf_gym.envs.scenarios import variation_label  # noqa: F401 (re-exported)

__all__ = ["main", "evaluate_controller", "evaluate_agent", "controller_episodes", "agent_episodes",
           "agent_group_episodes", "law_env_kwargs", "law_reference", "law_reference_groups",
           "build_scenarios", "load_agent"]



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
    p.add_argument("--n-links", type=int, nargs="+", default=None, metavar="N",
                   help="score on these members of the task family (2 to 7 links, docs/family.md): each N's presets "
                        "(named like the paper's, n5-0.1hz ...) and suites (n5-randomized ...), drawn by the same "
                        "rules and seeds; laws take each arm as their model, with their gains carried to it; an "
                        "agent is scored on the groups of the arm it was trained on (default: the paper's 3 links)")
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


def _check_arms(agent_paths: list[Path], groups: list[tuple[str, list[Any]]]) -> None:
    """Every agent acts on the arm every group has (an observation and action of n entries per
    joint signal), read from its metadata before it is loaded: ValueError naming the agent and the
    arms otherwise. A folder without readable metadata is left to the loader to report."""
    arms = sorted({scs[0].arm.n_links for _, scs in groups if scs})
    for path in agent_paths:
        folder = path if path.is_dir() else path.parent
        try:
            meta = json.loads((folder / "metadata.json").read_text())
        except (OSError, ValueError):
            continue
        n = (meta.get("env_kwargs") or {}).get("n_links") or 3
        if arms != [n]:
            raise ValueError(f"--n-links: {path} acts on an arm of {n} links, and the groups are of {arms}: score it "
                             f"with --n-links {n} alone (an agent trained without n_links acts on the paper's 3)")


def main(argv: Sequence[str] | None = None) -> int:
    import shlex

    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    args.command = shlex.join(["blf-eval", *argv])
    workers: Workers | None = None
    try:
        kwargs = _checked_args(args)
        seeds = args.suite_seeds if args.suite_seeds is not None else [PROTOCOL_SEEDS[s] for s in args.suite]
        groups = [g for n in (args.n_links or [None])
                  for g in build_scenarios(args.scenarios, seeds, kwargs, args.duration, args.suite, args.level, n)]
        if not groups:
            raise ValueError("no scenarios: give --scenarios and/or --suite-seeds")
        # the shipped agents act on the paper's arm: with --n-links they are scored only when asked for
        agent_paths = ((sorted(PRETRAINED.glob("*/model.zip")) if args.n_links is None else [])
                       if args.agents is None else [Path(a) for a in args.agents])
        if args.jobs > 1:  # they boot while the agents load below
            workers = Workers(args.jobs, bool(agent_paths))
        _check_arms(agent_paths, groups)
        agents = _load_agents(args, agent_paths)
        if not args.controllers and not agents:
            raise ValueError("nothing to evaluate: give --controllers and/or --agents")
    except ValueError as exc:
        if workers is not None:
            workers.close(now=True)
        print(f"blf-eval: error: {exc}", file=sys.stderr)
        return 2
    try:
        return run(args, groups, agents, kwargs, workers)
    except ValueError as exc:  # e.g. a --duration that is no whole number of an agent's control periods
        print(f"blf-eval: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except WorkerLost as exc:
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


if __name__ == "__main__":
    raise SystemExit(main())
