"""``blf-eval``: score controllers and trained agents on the same scenarios and metrics.

Controllers (``bc``, ``lesobc``, ``proposed``) run on the fast inner path (the law at every ODE3
stage, all episodes of a controller in one threaded kernel call). Agents are SB3 model zips with
a metadata JSON beside them (written by ``blf-train``: algorithm, env arguments, plain or
residual); all their episodes step together in one batched env. Episodes always run their full
duration with termination off, and violations are counted.

Examples::

    blf-eval                                             # baselines + shipped agents, paper cases
    blf-eval --controllers proposed --agents runs/sac/model.zip --suite-seeds 20 --out results/
    blf-eval --scenario-kwargs '{"payload": 0.15}' --duration 10

Writes, with ``--out DIR``: ``results.json`` and ``results.csv`` (SPEC section 8) and PNG plots of
the tracking error with its bounds and of the torques, per scenario.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.io import check_out_dir, os_error_message
from blf_gym.metrics import summarize, write_results
from blf_gym.params import PRESETS, Scenario, preset
from blf_gym.scenarios import apply_variations, sample_suite

__all__ = ["main", "evaluate_controller", "evaluate_agent", "build_scenarios", "load_agent"]

CONTROLLERS = ("bc", "lesobc", "proposed")
PRETRAINED = Path(__file__).resolve().parent / "pretrained"
EVAL_SEED_OFFSET = 10_000
"""Randomized-suite evaluation seeds start here, apart from any training seed."""


def build_scenarios(
    presets: Sequence[str], suite_seeds: int, kwargs: dict[str, Any], duration: float | None
) -> list[tuple[str, list[Scenario]]]:
    """[(scenario label, episodes)]: each preset is one episode; the suite has ``suite_seeds``."""
    groups: list[tuple[str, list[Scenario]]] = []
    sim_over = {"duration": duration} if duration is not None else {}
    for name in presets:
        if name not in PRESETS:
            raise ValueError(f"unknown scenario {name!r}; accepted: {sorted(PRESETS)} (and --suite-seeds)")
        sc = preset(name, **sim_over)
        if kwargs:
            sc = replace(apply_variations(sc, kwargs), name=f"{name}+custom")
        groups.append((sc.name, [sc]))
    if suite_seeds > 0:
        eps = []
        for k in range(suite_seeds):
            sc = sample_suite(np.random.default_rng(EVAL_SEED_OFFSET + k), preset("paper-0.1hz", **sim_over))
            if kwargs:
                sc = apply_variations(sc, kwargs)
            eps.append(sc)
        groups.append(("randomized", eps))
    return groups


def evaluate_controller(name: str, scenarios: Sequence[Scenario], threads: int | None = None):
    """Trajectories of a baseline controller on the inner path, one per scenario."""
    from blf_gym.simulate import simulate_batch

    return simulate_batch(scenarios, name, noise_seeds=[EVAL_SEED_OFFSET + i for i in range(len(scenarios))],
                          threads=threads)


def load_agent(path: str | Path) -> tuple[Any, dict[str, Any], Any]:
    """(SB3 model, metadata, VecNormalize statistics or None) from a ``blf-train`` run folder or its
    model zip."""
    path = Path(path)
    if path.is_dir():
        if not (path / "model.zip").is_file():
            raise ValueError(f"{path}: no model.zip in this folder; give a blf-train run folder or its model zip")
        path = path / "model.zip"
    if not path.is_file():
        raise ValueError(f"agent model not found: {path}")
    meta_path = path.with_name("metadata.json")
    if not meta_path.is_file():
        raise ValueError(f"{path}: no metadata.json beside the model; was it written by blf-train?")
    meta = json.loads(meta_path.read_text())
    for key in ("algo", "mode", "env_kwargs"):
        if key not in meta:
            raise ValueError(f"{meta_path}: metadata lacks {key!r}")
    import stable_baselines3 as sb3

    algos = {"ppo": sb3.PPO, "sac": sb3.SAC, "td3": sb3.TD3}
    try:
        from sb3_contrib import TQC

        algos["tqc"] = TQC
    except ImportError:
        pass
    if meta["algo"] not in algos:
        raise ValueError(f"{path}: unknown algorithm {meta['algo']!r} in metadata; known: {sorted(algos)}")
    try:
        model = algos[meta["algo"]].load(path, device="cpu")
    except Exception as exc:  # SB3 raises several types for a corrupt or foreign zip
        raise ValueError(f"{path}: cannot be loaded as a {meta['algo'].upper()} model ({exc})") from exc
    norm = None
    stats = path.with_name("vecnormalize.pkl")
    if stats.is_file():
        import pickle

        with open(stats, "rb") as f:
            norm = pickle.load(f)
    return model, meta, norm


def evaluate_agent(model: Any, meta: dict[str, Any], norm: Any, scenarios: Sequence[Scenario],
                   threads: int | None = None):
    """Trajectories of a trained agent, all episodes stepped together in one batched env."""
    from blf_gym.core import EnvCore

    kw = dict(meta["env_kwargs"])
    # the scenarios are given; the reward is not needed (a relative one would simulate the law)
    for k in ("scenario", "variations", "angle_noise_std", "duration", "threads", "reward_weights"):
        kw.pop(k, None)
    core = EnvCore(len(scenarios), record=True, terminate_on_violation=False, threads=threads, **kw)
    for i in range(len(scenarios)):
        core.rngs[i] = np.random.default_rng(EVAL_SEED_OFFSET + i)
    core.reset_envs(range(len(scenarios)), scenarios=list(scenarios))
    obs = core.observe()
    steps = {int(round(sc.sim.duration / core.control_period)) for sc in scenarios}
    if len(steps) != 1:
        raise ValueError("all evaluation scenarios of an agent must share one duration")
    for _ in range(steps.pop()):
        o = norm.normalize_obs(obs) if norm is not None else obs
        action, _ = model.predict(o, deterministic=True)
        obs, *_ = core.step(action)
    return [core.trajectory(i) for i in range(len(scenarios))]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-eval", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--controllers", nargs="*", default=list(CONTROLLERS), metavar="NAME",
                   help=f"baseline controllers to score (default: {' '.join(CONTROLLERS)}; none with an empty list)")
    p.add_argument("--agents", nargs="*", default=None, metavar="RUN",
                   help="trained agents: blf-train run folders or their model zips (default: the shipped "
                        "ones in agents/pretrained; none with an empty list)")
    p.add_argument("--scenarios", nargs="*", default=sorted(PRESETS), metavar="NAME",
                   help=f"paper presets (default: {' '.join(sorted(PRESETS))}; none with an empty list)")
    p.add_argument("--suite-seeds", type=int, default=0, metavar="N",
                   help="also run N held-out episodes of the randomized suite (default 0)")
    p.add_argument("--scenario-kwargs", type=str, default="{}", metavar="JSON",
                   help='scenario variations applied to every episode, e.g. \'{"payload": 0.15, "force": 20}\' '
                        "(default: none)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="episode length in s (default 30)")
    p.add_argument("--threads", type=int, default=None, metavar="T",
                   help="threads for the batched simulations (default: one per CPU)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="folder for results.json, results.csv and plots (default: none, the table only)")
    p.add_argument("--save-traj", action="store_true",
                   help="with --out: also save trajectories as npz (default off)")
    p.add_argument("--no-plots", action="store_true", help="with --out: skip the PNG plots (default: drawn)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar (default: shown)")
    return p


def _table(records: Sequence[dict[str, Any]]) -> str:
    head = (f"{'policy':<16} {'kind':<8} {'scenario':<14} {'ep':>3} | {'RMSE j1':>8} {'j2':>8} {'j3':>8} | "
            f"{'viol':>6} {'frac':>7} {'fail':>5} | {'CVaR':>7} | {'excess':>7} {'margin':>7} | "
            f"{'1st viol':>8} | {'u rms':>16} {'u peak':>17}")
    lines = [head, "-" * len(head)]
    for r in records:
        def f3(v, p=4):
            return " ".join(("-" if x is None else f"{x:.{p}f}").rjust(8) for x in v)
        viol = sum(v for v in r["violations"] if v is not None)
        frac = max((v for v in r["violation_fraction"] if v is not None), default=0.0)
        exc = max((v for v in r["max_excursion_deg"] if v is not None), default=0.0)
        mar = min((v for v in r["min_margin_deg"] if v is not None), default=0.0)
        fv = "-" if r["first_violation_s"] is None else f"{r['first_violation_s']:.3f}"
        cvar = "-" if r["rmse_cvar_deg"] is None else f"{r['rmse_cvar_deg']:.4f}"
        urms = "/".join("-" if v is None else f"{v:.1f}" for v in r["torque_rms"])
        upk = "/".join("-" if v is None else f"{v:.1f}" for v in r["torque_peak"])
        lines.append(
            f"{r['policy']:<16} {r['kind']:<8} {r['scenario']:<14} {r['episodes']:>3} | {f3(r['rmse_deg'])} | "
            f"{viol:>6} {frac:>7.4f} {r['failure_rate']:>5.2f} | {cvar:>7} | {exc:>7.3f} {mar:>7.3f} | "
            f"{fv:>8} | {urms:>16} {upk:>17}" + ("  DIVERGED" if r["diverged"] else ""))
    return "\n".join(lines)


def _plots(results: list[tuple[dict[str, Any], list[Any]]], out: Path) -> list[Path]:
    """Tracking error with bounds per joint (as the paper's Figures 6 and 10), and torques.

    Plain agents (the whole torque learned) get a column of their own: their errors are often
    tens of degrees, and on a shared axis they would flatten the laws' and residuals' curves."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blf_gym.io import atomic_path

    written = []
    scenarios = sorted({r["scenario"] for r, _ in results})
    for sc in scenarios:
        rows = [(r, trajs[0]) for r, trajs in results if r["scenario"] == sc and trajs and trajs[0].n_samples]
        if not rows:
            continue
        columns = [("baselines and residual agents", [x for x in rows if x[0]["kind"] != "plain"]),
                   ("plain agents (own scale)", [x for x in rows if x[0]["kind"] == "plain"])]
        columns = [c for c in columns if c[1]]
        for kind in ("error", "torque"):
            fig, axes = plt.subplots(3, len(columns), figsize=(9 if len(columns) == 1 else 14, 7),
                                     sharex=True, squeeze=False)
            for col, (title, members) in enumerate(columns):
                plain = members[0][0]["kind"] == "plain"
                for j in range(3):
                    ax = axes[j, col]
                    for r, tr in members:
                        y = np.degrees(tr.e1[:, j]) if kind == "error" else tr.u[:, j]
                        ax.plot(tr.t, y, lw=0.8, label=r["policy"])
                    if kind == "error":
                        tr = members[0][1]
                        ax.plot(tr.t, np.degrees(tr.k_a[:, j]), "k--", lw=0.8, label="bounds")
                        ax.plot(tr.t, -np.degrees(tr.k_b[:, j]), "k--", lw=0.8)
                        if not plain:
                            # zoom on the steady bounds (they start at 29-34 deg and decay to 1-2 deg)
                            ax.set_ylim(-3 * np.degrees(tr.k_b[-1, j]), 3 * np.degrees(tr.k_a[-1, j]))
                        ax.set_ylabel(f"e1_{j + 1} (deg)")
                    else:
                        ax.set_ylabel(f"u_{j + 1} (N m)")
                    ax.grid(alpha=0.3)
                axes[0, col].legend(loc="upper right", fontsize=8, ncol=4)
                axes[0, col].set_title(title, fontsize=9)
                axes[-1, col].set_xlabel("t (s)")
            fig.suptitle(f"{sc}: {'tracking error and its bounds' if kind == 'error' else 'commanded torque'}"
                         + (" (first episode)" if sc == "randomized" else ""), fontsize=11)
            fig.tight_layout()
            path = out / f"{kind}_{sc}.png"
            with atomic_path(path) as tmp:
                fig.savefig(tmp, dpi=110, format="png")
            plt.close(fig)
            written.append(path)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        try:
            kwargs = json.loads(args.scenario_kwargs)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--scenario-kwargs is not valid JSON ({exc}); example: "
                             '\'{"payload": 0.15}\'') from exc
        if not isinstance(kwargs, dict):
            raise ValueError("--scenario-kwargs must be a JSON object")
        for c in args.controllers:
            if c not in CONTROLLERS:
                raise ValueError(f"unknown controller {c!r}; accepted values: {list(CONTROLLERS)}")
        groups = build_scenarios(args.scenarios, args.suite_seeds, kwargs, args.duration)
        if not groups:
            raise ValueError("no scenarios: give --scenarios and/or --suite-seeds")
        agent_paths = (sorted(PRETRAINED.glob("*/model.zip")) if args.agents is None
                       else [Path(a) for a in args.agents])
        agents = [(p, *load_agent(p)) for p in agent_paths]
        if not args.controllers and not agents:
            raise ValueError("nothing to evaluate: give --controllers and/or --agents")
    except ValueError as exc:
        print(f"blf-eval: error: {exc}", file=sys.stderr)
        return 2
    if args.save_traj and args.out is None:
        print("blf-eval: error: --save-traj needs --out DIR", file=sys.stderr)
        return 2
    try:
        if args.out is not None:
            check_out_dir(args.out)  # a file, a read-only folder: said before the run, not after
        return _run(args, groups, agents)
    except OSError as exc:
        print(f"blf-eval: error: {os_error_message(exc, args.out)}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace, groups: list[tuple[str, list[Scenario]]], agents: list) -> int:
    jobs: list[tuple[str, str, Any]] = [(c, "baseline", None) for c in args.controllers]
    jobs += [(meta.get("name", p.parent.name), meta["mode"], (model, meta, norm)) for p, model, meta, norm in agents]
    bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs) * len(groups), unit="run", desc="blf-eval", file=sys.stderr, leave=False)
    results: list[tuple[dict[str, Any], list[Any]]] = []
    try:
        for name, kind, agent in jobs:
            for label, scs in groups:
                if bar is not None:
                    bar.set_postfix_str(f"{name} / {label}")
                t0 = time.perf_counter()
                trajs = (evaluate_controller(name, scs, args.threads) if agent is None
                         else evaluate_agent(*agent, scs, args.threads))
                rec = summarize(trajs, name, kind, label, scs[0].sim.dt, wall_s=time.perf_counter() - t0)
                results.append((rec, trajs))
                if bar is not None:
                    bar.update(1)
                if args.out is not None:  # finished records are kept if the run is interrupted
                    write_results([r for r, _ in results], args.out)
    except KeyboardInterrupt:
        print("\nblf-eval: interrupted" + ("; finished records were saved" if args.out else ""), file=sys.stderr)
        return 130
    finally:
        if bar is not None:
            bar.close()
    records = [r for r, _ in results]
    print(_table(records))
    print("\nRMSE, CVaR (mean RMSE of the worst half of the episodes), excess (largest distance "
          "beyond a bound) and margin (closest approach to a bound, negative when beyond) are in "
          "degrees; viol is the number of violating 1 ms samples summed over the joints, frac the "
          "worst joint's violating fraction, fail the share of episodes with a violation, 1st viol "
          "the earliest violation (s); torques in N m per joint.")
    if args.out is not None:
        write_results(records, args.out)
        written = [] if args.no_plots else _plots(results, args.out)
        if args.save_traj:
            for rec, trajs in results:
                for k, tr in enumerate(trajs):
                    tr.save_npz(args.out / "traj" / f"{rec['scenario']}__{rec['policy']}__{k}.npz")
        print(f"wrote {args.out / 'results.json'}, {args.out / 'results.csv'}"
              + (f" and {len(written)} plots" if written else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
