"""``python -m agents.report``: pool a blf-eval ``results.json`` over training seeds.

Agents trained with several seeds are named ``<name>_s<seed>`` (``blf-tune --seeds``). This groups
their records by ``<name>`` and scenario group and prints, per joint, the mean RMSE over seeds with
its spread (min-max), the violations summed over seeds and the worst failure rate, beside the
baselines, as a Markdown table. It also says, per scenario, in how many seeds the agent beats the
proposed law in every joint.

Few-seed statistics come from rliable (Agarwal et al., NeurIPS 2021), on the benchmark's score
``score_vs_law`` per episode: a (seeds x episodes) matrix per policy and group. Per group it
gives the interquartile mean (``iqm``) with a stratified-bootstrap 95 % confidence interval
(``ci95``), and the probability of improvement over the law (``prob_improvement``: P(score > 1),
averaged over episodes, with its interval), and writes them to a JSON file (``--json``, by default
``report.json`` beside the results).

With ``--windows SCENARIO AGENT`` it instead says where in time an agent gains or loses against
the law, from the trajectories ``blf-eval --save-traj`` wrote.

Example::

    blf-eval --agents runs/final/*/model.zip --suite-seeds 20 --out runs/final_eval --save-traj
    python -m agents.report runs/final_eval/results.json --out docs/seeds_table.md
    python -m agents.report runs/final_eval/results.json --windows paper-0.1hz ppo_residual_s0
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.io import help_text

__all__ = ["main", "pool_seeds", "seed_statistics"]

BOOTSTRAP_REPS = 5000
"""Bootstrap resamples for the IQM's interval (rliable's default is 50,000; 5,000 moves the interval
ends by well under 1 % here and keeps the command quick). The resampling is seeded."""
PI_BOOTSTRAP_REPS = 500
"""Resamples for the probability of improvement's interval: rliable runs a Mann-Whitney test per
episode per resample, so 50 episodes x 5,000 resamples would take minutes; 500 keep it to seconds."""

_SEED = re.compile(r"^(?P<name>.+)_s(?P<seed>\d+)(?P<suffix>\+.+)?$")
"""A seeded agent's name, ``<name>_s<seed>``, with the ``+<filter>`` blf-eval adds when
``--residual-filter`` runs every agent through a filter."""


def seed_group(policy: str) -> tuple[str, int | None]:
    """The group a policy's seeds pool into and its seed: ``("ppo_residual+barrier", 3)`` for
    ``ppo_residual_s3+barrier``; ``(policy, None)`` for a name without a seed."""
    m = _SEED.match(policy)
    if m is None:
        return policy, None
    return m.group("name") + (m.group("suffix") or ""), int(m.group("seed"))


def pool_seeds(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (policy, scenario); seeded agents pooled over their seeds."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    order: list[tuple[str, str]] = []
    for r in records:
        key = (seed_group(r["policy"])[0], r["scenario"])
        if key not in groups:
            order.append(key)
        groups[key].append(r)
    law = {r["scenario"]: np.asarray(r["rmse_deg"]) for r in records if r["policy"] == "proposed"}
    rows = []
    for key in order:
        recs = groups[key]
        rmse = np.array([r["rmse_deg"] for r in recs])
        row = {
            "policy": key[0], "scenario": key[1], "kind": recs[0]["kind"], "seeds": len(recs),
            "rmse_mean": rmse.mean(axis=0).tolist(), "rmse_min": rmse.min(axis=0).tolist(),
            "rmse_max": rmse.max(axis=0).tolist(),
            "violations": int(sum(sum(r["violations"]) for r in recs)),
            "failure_rate": float(max(r["failure_rate"] for r in recs)),
        }
        if key[1] in law:
            row["seeds_beating_law"] = int(sum(bool(np.all(np.asarray(r["rmse_deg"]) < law[key[1]])) for r in recs))
            row["ratio_mean"] = (rmse.mean(axis=0) / law[key[1]]).tolist()
        rows.append(row)
    return rows


def seed_statistics(records: Sequence[dict[str, Any]], reps: int = BOOTSTRAP_REPS,
                    pi_reps: int = PI_BOOTSTRAP_REPS) -> list[dict[str, Any]]:
    """rliable's IQM, 95 % stratified-bootstrap interval and probability of improvement over the
    law, of ``score_vs_law`` per (policy pooled over seeds, scenario group)."""
    try:
        from rliable import library as rly
        from rliable import metrics as rm
    except ImportError as exc:
        raise ValueError('the seed statistics need rliable: pip install -c constraints-cpu.txt -e ".[stats]"') from exc
    import warnings

    groups: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        if r.get("per_episode_score") is None:
            continue
        groups[(seed_group(r["policy"])[0], r["scenario"])].append(r)
    out = []
    for (policy, scenario), recs in groups.items():
        lengths = {len(r["per_episode_score"]) for r in recs}
        if len(lengths) != 1:
            raise ValueError(f"{policy} on {scenario}: the seeds were scored on different numbers of episodes "
                             f"{sorted(lengths)}")
        scores = np.array([[np.nan if s is None else s for s in r["per_episode_score"]] for r in recs], dtype=float)
        if np.isnan(scores).any():
            continue
        law = np.ones((1, scores.shape[1]))
        with warnings.catch_warnings():
            # rliable hands arch a seeded RandomState, which arch 7 marks as deprecated
            warnings.simplefilter("ignore", FutureWarning)
            point, interval = rly.get_interval_estimates(
                {"x": scores}, lambda s: np.array([rm.aggregate_iqm(s)]), reps=reps,
                random_state=np.random.RandomState(0))
            pi_point, pi_interval = rly.get_interval_estimates(
                {"x,law": (scores, law)}, rm.probability_of_improvement, reps=pi_reps,
                random_state=np.random.RandomState(0))
        seeds = []
        for r in recs:
            seeds.append(r.get("train_seed", seed_group(r["policy"])[1]))
        out.append({
            "policy": policy, "scenario": scenario, "kind": recs[0]["kind"], "seeds": seeds,
            "episodes": int(scores.shape[1]), "iqm": float(point["x"][0]),
            "ci95": [float(interval["x"][0][0]), float(interval["x"][1][0])],
            "prob_improvement": float(np.squeeze(pi_point["x,law"])),
            "prob_improvement_ci95": [float(np.squeeze(pi_interval["x,law"][0])),
                                      float(np.squeeze(pi_interval["x,law"][1]))],
            "failure_rate": float(np.mean([r["failure_rate"] for r in recs])),
            "certificate_broken": (float(np.mean([r["certificate_broken"] for r in recs]))
                                   if all(r.get("certificate_broken") is not None for r in recs) else None),
        })
    return out


def _stats_markdown(stats: list[dict[str, Any]]) -> str:
    out = ["| policy | kind | scenario group | seeds | episodes | IQM score_vs_law [95 % CI] | "
           "P(improvement over the law) [95 % CI] | failure rate | certificate_broken |",
           "|---|---|---|---|---|---|---|---|---|"]
    for s in stats:
        cb = "-" if s["certificate_broken"] is None else f"{s['certificate_broken']:.3f}"
        out.append(f"| {s['policy']} | {s['kind']} | {s['scenario']} | {len(s['seeds'])} | {s['episodes']} | "
                   f"{s['iqm']:.3f} [{s['ci95'][0]:.3f}, {s['ci95'][1]:.3f}] | {s['prob_improvement']:.2f} "
                   f"[{s['prob_improvement_ci95'][0]:.2f}, {s['prob_improvement_ci95'][1]:.2f}] | "
                   f"{s['failure_rate']:.3f} | {cb} |")
    out.append("")
    out.append("score_vs_law per episode: the geometric mean over joints of the proposed law's RMSE over the "
               "policy's, on the same scenario and noise (1 = the law's level). IQM and its stratified-bootstrap "
               f"interval ({BOOTSTRAP_REPS} resamples; {PI_BOOTSTRAP_REPS} for P) and P(score > 1) from rliable, over seeds x episodes (ties with the law "
               "count one half, so the law against itself gets 0.5); failure "
               "rate and certificate_broken (the policy violates where the law alone does not) averaged over seeds.")
    return "\n".join(out) + "\n"


def windows(traj_dir: Path, scenario: str, agent: str, law: str = "proposed", width: float = 0.5,
            top: int = 5) -> str:
    """Where an agent gains or loses against the law: the squared tracking error of each joint
    summed over ``width``-second windows, agent minus law, from ``blf-eval --save-traj`` files
    (``<scenario>__<policy>__0.npz``). Lists each joint's share of the MSE difference and the
    windows that contribute most to it, both ways."""
    def load(policy: str) -> tuple[np.ndarray, np.ndarray]:
        f = traj_dir / f"{scenario}__{policy}__0.npz"
        if not f.is_file():
            raise ValueError(f"{f} not found (run blf-eval with --save-traj --out)")
        with np.load(f) as d:
            return np.asarray(d["t"]), np.degrees(np.asarray(d["e1"]))
    t, e_law = load(law)
    t_a, e_ag = load(agent)
    k = min(len(t), len(t_a))
    t, e_law, e_ag = t[:k], e_law[:k], e_ag[:k]
    per = max(1, int(round(width / (t[1] - t[0]))))
    m = (k // per) * per
    d2 = (e_ag[:m] ** 2 - e_law[:m] ** 2).reshape(-1, per, e_law.shape[1]).sum(axis=1) / k
    mse_law = (e_law ** 2).mean(axis=0)
    lines = [f"{agent} against {law} on {scenario}: MSE difference per joint, as a share of the law's MSE, "
             f"and the {width:g} s windows contributing most (same share; + = the agent is worse)"]
    for j in range(e_law.shape[1]):
        total = d2[:, j].sum()
        lines.append(f"  joint {j + 1}: agent MSE / law MSE = {1 + total / mse_law[j]:.3f}")
        for label, order in (("worse", np.argsort(-d2[:, j])), ("better", np.argsort(d2[:, j]))):
            # windows that change the MSE by less than 0.1 % of the law's are not listed
            picks = [i for i in order[:top] if (d2[i, j] > 0) == (label == "worse")
                     and abs(d2[i, j]) >= 1e-3 * mse_law[j]]
            if picks:
                lines.append(f"    {label}: " + ", ".join(
                    f"{t[i * per]:.1f}-{t[i * per] + width:.1f} s ({d2[i, j] / mse_law[j]:+.3f})" for i in picks))
    return "\n".join(lines) + "\n"


def _markdown(rows: list[dict[str, Any]]) -> str:
    out = ["| policy | kind | scenario | seeds | RMSE j1 (deg) | j2 | j3 | mean / law (j1 j2 j3) | "
           "violating samples | worst failure rate | seeds beating the law in every joint |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = []
        for j in range(3):
            if r["seeds"] > 1:
                cells.append(f"{r['rmse_mean'][j]:.4f} ({r['rmse_min'][j]:.4f}-{r['rmse_max'][j]:.4f})")
            else:
                cells.append(f"{r['rmse_mean'][j]:.4f}")
        ratio = " ".join(f"{v:.3f}" for v in r.get("ratio_mean", [])) or "-"
        beat = f"{r['seeds_beating_law']} / {r['seeds']}" if r["kind"] != "baseline" and "seeds_beating_law" in r else "-"
        out.append(f"| {r['policy']} | {r['kind']} | {r['scenario']} | {r['seeds']} | " + " | ".join(cells)
                   + f" | {ratio} | {r['violations']:,} | {r['failure_rate']:.2f} | {beat} |")
    out.append("")
    out.append("RMSE: mean over training seeds, (min-max) across them; violating samples summed over "
               "seeds and joints; failure rate: the worst seed's share of episodes with a violation.")
    return "\n".join(out) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agents.report", description=help_text(__doc__),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results", type=Path, help="results.json written by blf-eval --out")
    p.add_argument("--out", type=Path, default=None, metavar="MD",
                   help="also write the tables to this Markdown file (default: print only)")
    p.add_argument("--json", type=Path, default=None, metavar="JSON",
                   help="where to write the pooled rows and the rliable statistics (default: report.json "
                        "beside RESULTS)")
    p.add_argument("--windows", nargs=2, metavar=("SCENARIO", "AGENT"), default=None,
                   help="instead: where AGENT gains or loses against the law on SCENARIO, from the "
                        "trajectories in the traj/ folder beside RESULTS (blf-eval --save-traj; default off)")
    args = p.parse_args(argv)
    if args.windows is not None:
        try:
            text = windows(args.results.parent / "traj", *args.windows)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(text)
        if args.out is not None:
            from blf_gym.io import atomic_write_text

            atomic_write_text(args.out, text)
        return 0
    from blf_gym.io import atomic_write_text
    from blf_gym.metrics import read_results

    try:
        records = read_results(args.results)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from blf_gym.io import MANIFEST, verify_output_set

    if (args.results.parent / MANIFEST).exists():  # sets written before manifests existed have none
        problem = verify_output_set(args.results.parent)
        if problem is not None:
            print(f"warning: {problem}; this report may not cover the whole run", file=sys.stderr)
    rows = pool_seeds(records)
    try:
        stats = seed_statistics(records)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    table = _markdown(rows) + ("\n" + _stats_markdown(stats) if stats else "")
    print(table)
    from blf_gym.io import atomic_write_json

    json_path = args.json if args.json is not None else args.results.parent / "report.json"
    atomic_write_json(json_path, {"results": str(args.results), "pooled": rows, "statistics": stats})
    if args.out is not None:
        atomic_write_text(args.out, table)
    print(f"wrote {json_path}" + (f" and {args.out}" if args.out is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
