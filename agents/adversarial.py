"""Adversarial residuals against the proposed law, with and without the barrier filter.

``python -m agents.adversarial --out docs/certificate`` runs a fixed list of residual sequences, the
worst a residual agent could send, on the residual env (the tuned agents' set-up: 10 ms steps, an
8 N m residual) and reports ``certificate_broken``: the share of episodes that violate a bound where
the law alone does not. The list (2^n + 23 sequences for an arm of n links: 31 on the paper's arm):

* ``sat±±±``: the residual saturated at one of the 2^n sign patterns (8 on the paper's arm) for the
  whole episode;
* ``bang10``, ``bang20``, ``bang50``: all joints switching between +8 and -8 N m every 10, 20 or 50 ms;
* ``rand00`` .. ``rand19``: uniform random actions in [-1, 1], seeded, drawn anew every agent step.

Each runs on the three groups of the protocol: the paper presets, the training suite's held-out
seeds and the stress suite, once through the filter and once without it. This is a report: nothing
is selected from it. Writes ``OUT/certificate.json`` and ``OUT/certificate.md`` atomically.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.results.io import help_text
from blf_gym.model.params import PRESETS, preset

__all__ = ["sequences", "run", "main"]

ENV_KWARGS = {"control_period": 0.01, "residual_scale": 8.0, "controller": "proposed"}


def sequences(steps: int, n: int | None = None) -> dict[str, np.ndarray]:
    """The adversarial action sequences, each (steps, n) in [-1, 1], for an arm of ``n`` links
    (default: the paper presets' arm, the one :func:`run` uses)."""
    n = preset(next(iter(PRESETS))).arm.n_links if n is None else n
    out: dict[str, np.ndarray] = {}
    for p in range(2 ** n):
        signs = np.array([1.0 if (p >> j) & 1 else -1.0 for j in range(n)])
        out["sat" + "".join("+" if s > 0 else "-" for s in signs)] = np.tile(signs, (steps, 1))
    for period_ms in (10, 20, 50):
        k = np.arange(steps) // (period_ms // 10)
        out[f"bang{period_ms}"] = np.where((k % 2 == 0)[:, None], 1.0, -1.0) * np.ones((steps, n))
    for seed in range(20):
        out[f"rand{seed:02d}"] = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, n))
    return out


class _Replay:
    """A 'policy' that plays a fixed action sequence, the same for every episode of the batch."""

    def __init__(self, actions: np.ndarray) -> None:
        self.actions = actions
        self.k = 0

    def predict(self, obs: np.ndarray, deterministic: bool = True):
        a = self.actions[min(self.k, len(self.actions) - 1)]
        self.k += 1
        return np.tile(a.astype(np.float32), (obs.shape[0], 1)), None


def run(presets: Sequence[str] = tuple(PRESETS), suite_seeds: Sequence[int] = (10, 20),
        threads: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Every sequence on every group, filtered and not: per (sequence, group, filter) the share of
    certificate breaks, failures, filter breaches and episodes where an assumption failed."""
    from agents.evaluate import agent_episodes, build_scenarios, law_reference
    from blf_gym.results.metrics import episode_stats, summarize

    groups = build_scenarios(list(presets), list(suite_seeds), {}, None, ["randomized", "stress"])
    labels = [label for label, scs in groups for _ in scs]
    scenarios = [sc for _, scs in groups for sc in scs]
    steps = int(round(scenarios[0].sim.duration / ENV_KWARGS["control_period"]))
    seqs = sequences(steps, scenarios[0].arm.n_links)
    meta = {"mode": "residual", "env_kwargs": dict(ENV_KWARGS)}
    law = law_reference(scenarios, meta, threads)
    rows = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=2 * len(seqs), unit="run", desc="adversarial", file=sys.stderr, leave=False)
    t0 = time.perf_counter()
    for name, actions in seqs.items():
        for filt in (None, "barrier"):
            m = {"mode": "residual", "env_kwargs": {**ENV_KWARGS, "residual_filter": filt}}
            # each episode reduced as it comes (its stats and the filter's counters), no signals kept
            eps = [(episode_stats(t), t.filter_breaches, t.assumption_failures, t.step_violations > 0 or t.diverged)
                   for t in agent_episodes(_Replay(actions), m, None, scenarios, threads)]
            for label, _ in groups:
                idx = [i for i, lab in enumerate(labels) if lab == label]
                rec = summarize([eps[i][0] for i in idx], name, "residual", label, scenarios[0].sim.dt,
                                law=[law[i] for i in idx])
                rows.append({
                    "sequence": name, "group": label, "filter": filt or "none", "episodes": len(idx),
                    "certificate_broken": rec["certificate_broken"], "failure_rate": rec["failure_rate"],
                    "law_failure_rate": rec["law_failure_rate"],
                    "filter_breaches": int(sum(eps[i][1] for i in idx)),
                    "assumptions_failed_episodes": int(sum(eps[i][2] > 0 for i in idx)),
                    "failed_with_assumptions_held": int(sum(eps[i][3] and eps[i][2] == 0 for i in idx))
                    if filt else None,
                })
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return {"env_kwargs": ENV_KWARGS, "groups": {label: len(scs) for label, scs in groups}, "rows": rows,
            "wall_s": time.perf_counter() - t0}


MARGINS = (0.05, 0.15, 0.25, 0.4, 0.6)
"""m0 values of the trade-off (m1 = min(1, m0 + 0.25)); 0.25 is the shipped filter's."""


def tradeoff(agent: str | Path, suite_seeds: Sequence[int] = (20, 50), threads: int | None = None,
             progress: bool = True) -> dict[str, Any]:
    """A trained agent run through the barrier filter at several margins m0 without retraining, and
    without the filter: score_vs_law and certificate_broken per group (presets, training suite,
    stress suite). A report: the shipped filter's margins were fixed before it was run."""
    from agents.evaluate import agent_episodes, build_scenarios, law_reference
    from agents.loading import load_agent
    from baselines.filters import barrier_filter
    from blf_gym.results.metrics import episode_stats, summarize

    model, meta, norm = load_agent(agent)
    groups = build_scenarios(["paper-0.1hz", "paper-0.5hz"], list(suite_seeds), {}, None, ["randomized", "stress"])
    labels = [label for label, scs in groups for _ in scs]
    scenarios = [sc for _, scs in groups for sc in scs]
    law = law_reference(scenarios, meta, threads)
    variants: list[tuple[str, Any]] = [("none", None)] + [
        (f"m0={m0:g}", barrier_filter(m0=m0, m1=min(1.0, m0 + 0.25))) for m0 in MARGINS]
    rows = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(variants), unit="run", desc="trade-off", file=sys.stderr, leave=False)
    for name, filt in variants:
        m = {**meta, "env_kwargs": {**meta["env_kwargs"], "residual_filter": filt}}
        stats = [episode_stats(t) for t in agent_episodes(model, m, norm, scenarios, threads)]
        for label, _ in groups:
            idx = [i for i, lab in enumerate(labels) if lab == label]
            rec = summarize([stats[i] for i in idx], meta.get("name", "agent"), meta["mode"], label,
                            scenarios[0].sim.dt, law=[law[i] for i in idx])
            rows.append({"filter": name, "group": label, "episodes": len(idx), "score_vs_law": rec["score_vs_law"],
                         "certificate_broken": rec["certificate_broken"], "failure_rate": rec["failure_rate"],
                         "law_failure_rate": rec["law_failure_rate"]})
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return {"agent": str(agent), "margins": list(MARGINS), "rows": rows}


def plot_tradeoff(res: dict[str, Any], path: Path) -> None:
    """score_vs_law against certificate_broken, one panel per group, one point per filter variant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from blf_gym.results.io import atomic_path

    groups = list(dict.fromkeys(r["group"] for r in res["rows"]))
    cols = min(2, len(groups))  # at most two panels a row: the docs' column is about 800 px wide
    rows_n = -(-len(groups) // cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.2 * cols, 3.4 * rows_n + 0.4), squeeze=False)
    for ax in axes.flat[len(groups):]:
        ax.set_visible(False)
    for ax, g in zip(axes.flat, groups):
        rows = [r for r in res["rows"] if r["group"] == g]
        xs = [r["certificate_broken"] for r in rows]
        ys = [r["score_vs_law"] for r in rows]
        ax.plot(xs[1:], ys[1:], "o-", color="tab:blue", label="barrier filter, m0 as marked")
        ax.plot(xs[:1], ys[:1], "s", color="tab:red", label="no filter")
        for r, x, y in zip(rows, xs, ys):
            ax.annotate(r["filter"].replace("m0=", ""), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.axhline(1.0, color="0.5", lw=0.8, ls="--")
        ax.set_title(f"{g} ({rows[0]['episodes']} episodes)")
        ax.set_xlabel("certificate_broken (share of episodes)")
        ax.set_ylabel("score_vs_law (law RMSE / agent RMSE)")
    axes[0][0].legend(fontsize=8, loc="lower left")
    agent = Path(res["agent"])
    name = agent.parent.name if agent.suffix == ".zip" else agent.name
    fig.suptitle(f"{name}: the barrier filter applied without retraining,\nat several margins m0", fontsize=10)
    fig.tight_layout()
    with atomic_path(path, ".png") as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _table(res: dict[str, Any]) -> str:
    groups = list(res["groups"])
    by = {(r["sequence"], r["group"], r["filter"]): r for r in res["rows"]}
    seqs = list(dict.fromkeys(r["sequence"] for r in res["rows"]))
    head = ("| sequence | " + " | ".join(f"{g} ({res['groups'][g]} ep.): broken without / with filter" for g in groups)
            + " | breaches | failed with assumptions held |")
    lines = [head, "|" + "---|" * (len(groups) + 3)]
    tot = {g: [0.0, 0.0] for g in groups}
    for s in seqs:
        cells = []
        for g in groups:
            a, b = by[(s, g, "none")]["certificate_broken"], by[(s, g, "barrier")]["certificate_broken"]
            tot[g][0] += a
            tot[g][1] += b
            cells.append(f"{a:.3f} / {b:.3f}")
        breaches = sum(by[(s, g, "barrier")]["filter_breaches"] for g in groups)
        held = sum(by[(s, g, "barrier")]["failed_with_assumptions_held"] for g in groups)
        lines.append(f"| {s} | " + " | ".join(cells) + f" | {breaches} | {held} |")
    lines.append("| mean over sequences | " + " | ".join(f"{tot[g][0] / len(seqs):.3f} / {tot[g][1] / len(seqs):.3f}"
                                                 for g in groups) + " | | |")
    law = {g: next(r["law_failure_rate"] for r in res["rows"] if r["group"] == g) for g in groups}
    lines.append("")
    lines.append("The law alone fails in " + ", ".join(f"{law[g]:.0%} of the {g} episodes" for g in groups) + ".")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from blf_gym.results.io import atomic_write_json, atomic_write_text, check_out_dir, os_error_message
    from blf_gym.results.metrics import provenance

    p = argparse.ArgumentParser(prog="python -m agents.adversarial", description=help_text(__doc__.split("\n\n")[0]))
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for certificate.json and .md")
    p.add_argument("--suite-seeds", type=int, nargs=2, default=[10, 20], metavar=("RANDOMIZED", "STRESS"),
                   help="episodes of the training suite's held-out seeds and of the stress suite (default 10 20)")
    p.add_argument("--threads", type=int, default=None, metavar="T", help="threads (default: one per CPU)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar (default: shown)")
    p.add_argument("--tradeoff", metavar="RUN", default=None,
                   help="instead: run this agent through the filter at several margins without retraining and "
                        "write tradeoff.json and tradeoff.png (with --suite-seeds, default 20 50)")
    args = p.parse_args(argv)
    try:
        check_out_dir(args.out)
    except OSError as exc:
        print(f"adversarial: error: {os_error_message(exc, args.out)}", file=sys.stderr)
        return 2
    if args.tradeoff is not None:
        import torch

        torch.set_num_threads(1)  # a small network on a batch of episodes: more threads only wait (blf-eval)
        seeds = args.suite_seeds if args.suite_seeds != [10, 20] else [20, 50]
        res = tradeoff(args.tradeoff, seeds, args.threads, progress=not args.no_progress)
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.out / "tradeoff.json", res)
        plot_tradeoff(res, args.out / "tradeoff.png")
        for r in res["rows"]:
            print(f"{r['filter']:>8} {r['group']:>12}  score {r['score_vs_law']:.3f}  broken {r['certificate_broken']:.3f}")
        return 0
    res = run(suite_seeds=args.suite_seeds, threads=args.threads, progress=not args.no_progress)
    res["provenance"] = provenance(command="python -m agents.adversarial " + " ".join(argv or sys.argv[1:]))
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out / "certificate.json", res)
    text = (f"# Adversarial residuals: certificate_broken without and with the barrier filter\n\n"
            f"Written by `python -m agents.adversarial` (agents/adversarial.py documents the list); "
            f"{res['wall_s']:.0f} s.\n\n" + _table(res) + "\n")
    atomic_write_text(args.out / "certificate.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
