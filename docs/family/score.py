"""Score against the number of links (docs/family.md, "Score against n"): from the protocol run on
every member (docs/family/protocol/results.json), the learners' runs on members where they exist
(docs/family/learners/results.json, ``blf-eval --n-links 2 7 --agents ...``) and the learners'
runs on the paper's arm (:data:`SOURCES`), rliable's IQM of the
per-episode ``score_vs_law`` with its stratified-bootstrap 95 % interval (agents.report, over seeds x
episodes for a learner, over episodes for a controller), per member, policy and group. Writes
docs/family/score.json (the statistics, with what produced them) and docs/family/score.png (the
training suite and the stress suite against n, one line per policy, the law at 1).

    python docs/family/score.py [--reps 5000]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SOURCES = (("family/protocol", False), ("family/learners", False), ("protocol_learners", True),
           ("protocol_best", True))
"""The results folders under docs/ that the figure reads, in this order (absent ones skipped), and
whether only their learners are read: the protocol run on every member, the learners' runs on the
members, and the paper's arm's learner runs (its shipped agents and the residuals over the tuned
laws, scored on the same 3-link episodes as the members' protocol run's 3-link rows)."""
GROUPS = ("randomized", "stress")
"""The suites the figure shows: the training suite's held-out episodes and the stress suite."""


def member_of(scenario: str) -> tuple[int, str]:
    """(n, group) of a family record's scenario label: ``n5-stress`` -> (5, "stress"); the paper's arm
    keeps its own labels (``randomized``, ``paper-0.1hz``) -> 3."""
    if scenario.startswith("n") and scenario[1:2].isdigit():
        n, _, rest = scenario.partition("-")
        return int(n[1:]), rest
    return 3, scenario


def iqm_interval(scores: np.ndarray, reps: int) -> tuple[float, list[float]]:
    """rliable's IQM of a (seeds x episodes) score matrix with its stratified-bootstrap 95 % interval
    (agents.report's statistic without the probability of improvement, whose Mann-Whitney test per
    resample would take most of an hour over the family's groups). rliable draws its resampling
    indices from numpy's global generator: seeded here, and the caller's state put back."""
    import warnings

    from rliable import library as rly
    from rliable import metrics as rm

    saved = np.random.get_state()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # arch's notice about the RandomState rliable passes
            np.random.seed(0)
            point, interval = rly.get_interval_estimates(
                {"x": scores}, lambda s: np.array([rm.aggregate_iqm(s)]), reps=reps,
                random_state=np.random.RandomState(0))
    finally:
        np.random.set_state(saved)
    return float(point["x"][0]), [float(interval["x"][0][0]), float(interval["x"][1][0])]


def statistics(reps: int) -> list[dict]:
    """One row per (member, policy pooled over seeds, group) of :data:`GROUPS`. A learner's interval
    is rliable's over its seeds (resampled within each episode, the episodes being the tasks); one run
    (a controller, whose episodes are its only spread) has its episodes resampled instead, as runs
    of one task, so its interval is the suite's sampling spread."""
    from agents.report import seed_group

    rows = []
    for src, learners_only in SOURCES:
        path = HERE.parent / src / "results.json"
        if not path.is_file():
            continue
        pooled: dict[tuple[str, str], list[dict]] = {}
        for r in json.loads(path.read_text())["records"]:
            if learners_only and r["kind"] == "baseline":
                continue
            if member_of(r["scenario"])[1] in GROUPS and r.get("per_episode_score") is not None:
                pooled.setdefault((seed_group(r["policy"])[0], r["scenario"]), []).append(r)
        for (policy, scenario), recs in pooled.items():
            scores = np.array([[np.nan if v is None else v for v in r["per_episode_score"]] for r in recs], dtype=float)
            if np.isnan(scores).any() or len({len(r["per_episode_score"]) for r in recs}) != 1:
                raise ValueError(f"docs/{src}: {policy} on {scenario}: scores missing or of unequal lengths")
            # one run (a controller, or one seed): its episodes resampled, as runs of one task
            iqm, ci = iqm_interval(scores if len(recs) > 1 else scores.T, reps)
            n, group = member_of(scenario)
            rows.append({"n": n, "group": group, "source": src, "policy": policy, "kind": recs[0]["kind"],
                         "seeds": [r.get("train_seed", seed_group(r["policy"])[1]) for r in recs],
                         "episodes": int(scores.shape[1]), "iqm": iqm, "ci95": ci,
                         "failure_rate": float(np.mean([r["failure_rate"] for r in recs]))})
    rows.sort(key=lambda r: (r["n"], r["group"], r["source"], r["policy"]))
    return rows


def best_lines(rows: list[dict]) -> dict[str, list[dict]]:
    """The figure's lines: each controller, and per member the best learner of each kind (residual,
    plain) by its training-suite IQM (never the stress suite's), its rows on both groups."""
    lines: dict[str, list[dict]] = {}
    for r in rows:
        if r["kind"] == "baseline":
            lines.setdefault(r["policy"], []).append(r)
    for kind in ("residual", "plain"):
        for n in sorted({r["n"] for r in rows}):
            train = [r for r in rows if r["n"] == n and r["kind"] == kind and r["group"] == "randomized"]
            if train:
                best = max(train, key=lambda r: r["iqm"])["policy"]
                lines.setdefault(f"best {kind} learner", []).extend(
                    r for r in rows if r["n"] == n and r["policy"] == best)
    return lines


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(GROUPS), figsize=(10, 3.8), sharey=True)
    titles = {"randomized": "training suite (held-out episodes)", "stress": "stress suite"}
    lines = best_lines(rows)
    for ax, group in zip(axes, GROUPS):
        for k, (pol, rs) in enumerate(lines.items()):
            rs = sorted((r for r in rs if r["group"] == group), key=lambda r: r["n"])
            if not rs:
                continue
            ns = [r["n"] + 0.06 * (k - (len(lines) - 1) / 2) for r in rs]  # side by side, not on top
            iqm = [max(r["iqm"], 1e-4) for r in rs]
            lo = [max(r["ci95"][0], 1e-4) for r in rs]
            hi = [max(r["ci95"][1], 1e-4) for r in rs]
            ax.errorbar(ns, iqm, yerr=[[a - b for a, b in zip(iqm, lo)], [b - a for a, b in zip(iqm, hi)]],
                        marker="o", capsize=3, label=pol)
        ax.axhline(1.0, color="0.5", lw=0.8, ls="--")
        ax.set_yscale("log")
        ax.set_xlabel("links n")
        ax.set_title(titles[group])
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("score_vs_law, IQM and 95 % interval")
    axes[-1].legend(fontsize=8, loc="best")
    fig.tight_layout()
    tmp = out.with_name(f".{out.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python docs/family/score.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=5000, help="bootstrap resamples for the intervals (default 5000)")
    ap.add_argument("--out", type=Path, default=HERE / "score.json", help="the statistics (the figure beside it)")
    a = ap.parse_args(argv)
    if a.reps < 100:
        raise SystemExit("python docs/family/score.py: error: --reps must be at least 100")
    from blf_gym.results.io import atomic_write_text
    from blf_gym.results.metrics import provenance

    rows = statistics(a.reps)
    if not rows:
        raise SystemExit("python docs/family/score.py: error: none of the results files of SOURCES exists")
    atomic_write_text(a.out, json.dumps({"reps": a.reps, "rows": rows, "provenance": provenance(
        command="python docs/family/score.py" + "".join(f" {x}" for x in (argv or sys.argv[1:])))}, indent=1) + "\n")
    plot(rows, a.out.with_suffix(".png"))
    print(f"wrote {a.out} and {a.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parents[1]))
    raise SystemExit(main())
