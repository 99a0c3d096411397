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
``report.json`` beside the results). The same statistics are given against the reference
controller (the second yardstick, ``vs_reference``) and, for a residual agent over another law than
the proposed one, against its own base (``vs_base``), where those were scored on the same episodes:
in the same run, or in the run ``--reference-results`` names.

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

from blf_gym.results.io import help_text

__all__ = ["main", "pool_seeds", "reference_records", "seed_statistics"]

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


def _same_episodes(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two records were scored on the same episodes: scenario group, integration step,
    suite seeds, noise seeds, variations and episode count."""
    return all(a.get(k) == b.get(k) for k in ("scenario", "dt", "suite", "suite_seeds", "noise_seeds",
                                              "scenario_kwargs", "episodes"))


def reference_records(records: Sequence[dict[str, Any]], others: Sequence[dict[str, Any]],
                      where: str = "the reference results") -> list[dict[str, Any]]:
    """Records from another blf-eval run (``others``) usable beside ``records``: each one kept where
    ``records`` has a group on the same episodes, after checking that the proposed law, scored in
    both runs, gave the same per-episode RMSEs there (to 1e-9 relative): the episodes are then the
    same, so a controller of the other run is a valid yardstick for the policies of this one.
    Raises ValueError where the law differs or is missing from either run."""
    law = [r for r in records if r["policy"] == "proposed"]
    law_o = [r for r in others if r["policy"] == "proposed"]
    kept = []
    for r in others:
        mine = next((q for q in law if _same_episodes(q, r)), None)
        if mine is None:
            continue
        theirs = next((q for q in law_o if _same_episodes(q, r)), None)
        if theirs is None:
            raise ValueError(f"{where}: no record of the proposed law on {r['policy']}'s episodes of {r['scenario']} "
                             "to check them against")
        a = np.asarray(mine["per_episode_rmse_deg"], dtype=float)
        b = np.asarray(theirs["per_episode_rmse_deg"], dtype=float)
        if a.shape != b.shape or not np.allclose(a, b, rtol=1e-9, atol=0.0):
            raise ValueError(f"{where}: the proposed law's per-episode RMSEs on {r['scenario']} differ from this "
                             "run's, so its episodes are not the same")
        kept.append(r)
    return kept


def _iqm(scores: np.ndarray, reps: int, pi_reps: int) -> dict[str, Any]:
    """rliable's IQM with its stratified-bootstrap 95 % interval, and P(score > 1) with its interval,
    of a (seeds x episodes) score matrix."""
    import warnings

    from rliable import library as rly
    from rliable import metrics as rm

    law = np.ones((1, scores.shape[1]))
    # rliable's stratified bootstraps draw their indices from numpy's global generator
    # (np.random.choice in update_indices), whatever random_state they are given: the global
    # state is seeded for each call, and the caller's restored afterwards, so that a report is
    # the same on every run
    saved = np.random.get_state()
    try:
        with warnings.catch_warnings():
            # rliable hands arch a seeded RandomState, which arch 7 marks as deprecated
            warnings.simplefilter("ignore", FutureWarning)
            np.random.seed(0)
            point, interval = rly.get_interval_estimates(
                {"x": scores}, lambda s: np.array([rm.aggregate_iqm(s)]), reps=reps,
                random_state=np.random.RandomState(0))
            np.random.seed(0)
            pi_point, pi_interval = rly.get_interval_estimates(
                {"x,law": (scores, law)}, rm.probability_of_improvement, reps=pi_reps,
                random_state=np.random.RandomState(0))
    finally:
        np.random.set_state(saved)
    return {"iqm": float(point["x"][0]), "ci95": [float(interval["x"][0][0]), float(interval["x"][1][0])],
            "prob_improvement": float(np.squeeze(pi_point["x,law"])),
            "prob_improvement_ci95": [float(np.squeeze(pi_interval["x,law"][0])),
                                      float(np.squeeze(pi_interval["x,law"][1]))]}


def _scores_against(recs: Sequence[dict[str, Any]], yardstick: dict[str, Any]) -> np.ndarray | None:
    """Each seed's per-episode score against another policy's record on the same episodes (the
    geometric mean over joints of its RMSE over the seed's, as ``score_vs_law`` is), or None when
    an episode has no RMSE on either side."""
    from blf_gym.results.metrics import score_vs_law

    ref = yardstick["per_episode_rmse_deg"]
    rows = []
    for r in recs:
        if not _same_episodes(r, yardstick):
            return None
        row = [score_vs_law(p, q) for p, q in zip(r["per_episode_rmse_deg"], ref)]
        if any(v is None for v in row):
            return None
        rows.append(row)
    return np.array(rows, dtype=float)


def seed_statistics(records: Sequence[dict[str, Any]], reps: int = BOOTSTRAP_REPS,
                    pi_reps: int = PI_BOOTSTRAP_REPS, reference: str | None = None,
                    yardsticks: Sequence[dict[str, Any]] = ()) -> list[dict[str, Any]]:
    """rliable's IQM, 95 % stratified-bootstrap interval and probability of improvement over the
    law, of ``score_vs_law`` per (policy pooled over seeds, scenario group).

    Beside it, under ``vs_reference`` and ``vs_base`` (each with ``against``, ``iqm``, ``ci95``,
    ``prob_improvement`` and its interval), the same statistics of the score against two other
    yardsticks where the records allow: the reference controller (the records' own
    ``per_episode_score_vs_reference``, or ``reference``'s record on the same episodes, in
    ``records`` or ``yardsticks``: see :func:`reference_records`), and for a residual agent its
    own base law (its ``env_kwargs['controller']``, when that is not the proposed law and was
    scored on the same episodes)."""
    try:
        import rliable  # noqa: F401
    except ImportError as exc:
        raise ValueError('the seed statistics need rliable: pip install -c constraints-cpu.txt -e ".[stats]"') from exc

    pool = {}
    for r in [*yardsticks, *records]:  # this run's records win over another run's
        if seed_group(r["policy"])[1] is None:
            pool[(r["policy"], r["scenario"])] = r
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
        seeds = []
        for r in recs:
            seeds.append(r.get("train_seed", seed_group(r["policy"])[1]))
        stat = {"policy": policy, "scenario": scenario, "kind": recs[0]["kind"], "seeds": seeds,
                "episodes": int(scores.shape[1]), **_iqm(scores, reps, pi_reps),
                "failure_rate": float(np.mean([r["failure_rate"] for r in recs])),
                "certificate_broken": (float(np.mean([r["certificate_broken"] for r in recs]))
                                       if all(r.get("certificate_broken") is not None for r in recs) else None)}
        ref_names = {r.get("reference") for r in recs}
        native = (len(ref_names) == 1 and None not in ref_names
                  and all(r.get("per_episode_score_vs_reference") is not None for r in recs))
        if native and (reference is None or reference in ref_names):
            m = np.array([[np.nan if v is None else v for v in r["per_episode_score_vs_reference"]] for r in recs])
            if not np.isnan(m).any():
                stat["vs_reference"] = {"against": ref_names.pop(), **_iqm(m, reps, pi_reps)}
        elif reference is not None and reference != policy and (reference, scenario) in pool:
            m = _scores_against(recs, pool[(reference, scenario)])
            if m is not None:
                stat["vs_reference"] = {"against": reference, **_iqm(m, reps, pi_reps)}
        bases = {(r.get("env_kwargs") or {}).get("controller") for r in recs} if recs[0]["kind"] == "residual" else set()
        base = bases.pop() if len(bases) == 1 else None
        if base is not None and base != "proposed" and (base, scenario) in pool:
            m = _scores_against(recs, pool[(base, scenario)])
            if m is not None:
                stat["vs_base"] = {"against": base, **_iqm(m, reps, pi_reps)}
        out.append(stat)
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
    more = [(s, k) for s in stats for k in ("vs_reference", "vs_base") if k in s]
    if more:
        out += ["", "The same statistics against other yardsticks (the reference controller, and a residual "
                "agent's own base law), on the same episodes:", "",
                "| policy | scenario group | against | IQM score [95 % CI] | P(improvement) [95 % CI] |",
                "|---|---|---|---|---|"]
        for s, k in more:
            v = s[k]
            out.append(f"| {s['policy']} | {s['scenario']} | {v['against']} ({k[3:]}) | {v['iqm']:.3f} "
                       f"[{v['ci95'][0]:.3f}, {v['ci95'][1]:.3f}] | {v['prob_improvement']:.2f} "
                       f"[{v['prob_improvement_ci95'][0]:.2f}, {v['prob_improvement_ci95'][1]:.2f}] |")
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
    if not rows:
        return "No records to pool.\n"
    n = len(rows[0]["rmse_mean"])  # joints
    joints = " ".join(f"j{j + 1}" for j in range(n))
    out = ["| policy | kind | scenario | seeds | RMSE j1 (deg) | " + "".join(f"j{j + 1} | " for j in range(1, n))
           + f"mean / law ({joints}) | violating samples | worst failure rate | seeds beating the law in every "
           "joint |",
           "|" + "---|" * (n + 8)]
    for r in rows:
        cells = []
        for j in range(n):
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
    p.add_argument("--reference", default=None, metavar="NAME",
                   help="the controller the second yardstick's statistics are against (default: the records' "
                        "own reference, where blf-eval scored one)")
    p.add_argument("--reference-results", type=Path, nargs="+", default=[], metavar="JSON",
                   help="other blf-eval results.json files holding --reference's records (and a residual's base "
                        "law's) on the same episodes, for results scored before the second yardstick existed; "
                        "the proposed law's per-episode RMSEs in each must agree with RESULTS' (default: none)")
    args = p.parse_args(argv)
    if args.windows is not None:
        try:
            text = windows(args.results.parent / "traj", *args.windows)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(text)
        if args.out is not None:
            from blf_gym.results.io import atomic_write_text

            atomic_write_text(args.out, text)
        return 0
    from blf_gym.results.io import atomic_write_text
    from blf_gym.results.metrics import read_results

    try:
        records = read_results(args.results)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from blf_gym.results.io import MANIFEST, verify_output_set

    if (args.results.parent / MANIFEST).exists():  # sets written before manifests existed have none
        problem = verify_output_set(args.results.parent)
        if problem is not None:
            print(f"warning: {problem}; this report may not cover the whole run", file=sys.stderr)
    rows = pool_seeds(records)
    try:
        others = [r for f in args.reference_results for r in reference_records(records, read_results(f), str(f))]
        stats = seed_statistics(records, reference=args.reference, yardsticks=others)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    table = _markdown(rows) + ("\n" + _stats_markdown(stats) if stats else "")
    print(table)
    from blf_gym.results.io import atomic_write_json

    json_path = args.json if args.json is not None else args.results.parent / "report.json"
    atomic_write_json(json_path, {"results": str(args.results), "pooled": rows, "statistics": stats,
                                  **({"reference_results": [str(f) for f in args.reference_results]}
                                     if args.reference_results else {})})
    if args.out is not None:
        atomic_write_text(args.out, table)
    print(f"wrote {json_path}" + (f" and {args.out}" if args.out is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
