"""The equivalence test of docs/budget.md: does a faster configuration learn as well per step?

    python docs/budget/equivalence.py RUNS_DIR [--out docs/budget/equivalence.md]

Scores every 2^21-step run of the three configurations (``RUNS_DIR/ppo_s*`` for the replaced one,
``RUNS_DIR/equal/<candidate>_s*`` for the candidates, as docs/budget/plan.sh leaves them) with
``blf-eval`` on the paper presets and the training suite's 20 held-out episodes, never the stress
suite; pools each configuration's three seeds with rliable (``agents.report.seed_statistics``:
the IQM of ``score_vs_law`` and its 95 % stratified-bootstrap interval) and applies the rule: a
candidate passes on a scenario group when its IQM lies inside the replaced configuration's
interval. Writes the table (Markdown) and, beside it, the statistics and the rule's verdicts
(JSON), and keeps blf-eval's own results in ``RUNS_DIR/equivalence_eval``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPLACED = "ppo"
CANDIDATES = ("sbx_ppo", "sbx_ppo_256")
GROUPS = ("randomized", "paper-0.1hz", "paper-0.5hz")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", type=Path, help="the runs folder of docs/budget/plan.sh")
    p.add_argument("--out", type=Path, default=Path(__file__).with_name("equivalence.md"),
                   help="the Markdown table to write (default docs/budget/equivalence.md)")
    args = p.parse_args()

    from agents.report import seed_statistics

    agents = sorted(args.runs.glob(f"{REPLACED}_s[0-9]")) + [
        a for c in CANDIDATES for a in sorted((args.runs / "equal").glob(f"{c}_s[0-9]"))]
    if not agents:
        sys.exit(f"equivalence.py: no runs in {args.runs}")
    ev = args.runs / "equivalence_eval"
    if not (ev / "manifest.json").is_file() or not json.loads((ev / "manifest.json").read_text()).get("complete"):
        subprocess.run(["blf-eval", "--agents", *map(str, agents), "--controllers", "proposed",
                        "--suite", "randomized", "--no-plots", "--no-progress", "--out", str(ev)], check=True)
    records = json.loads((ev / "results.json").read_text())["records"]
    stats = {(s["policy"], s["scenario"]): s for s in seed_statistics(records)}
    rows, verdicts = [], []
    for group in GROUPS:
        ref = stats[(REPLACED, group)]
        lo, hi = ref["ci95"]
        for name in (REPLACED, *CANDIDATES):
            s = stats.get((name, group))
            if s is None:
                continue
            inside = None if name == REPLACED else bool(lo <= s["iqm"] <= hi)
            if inside is not None:
                verdicts.append({"candidate": name, "group": group, "iqm": s["iqm"], "replaced_ci95": [lo, hi],
                                 "passes": inside})
            rows.append(f"| {group} | {name} | {len(s['seeds'])} | {s['episodes']} | {s['iqm']:.4f} "
                        f"[{s['ci95'][0]:.4f}, {s['ci95'][1]:.4f}] | {s['failure_rate']:.2f} | "
                        f"{'-' if inside is None else ('inside' if inside else 'outside')} |")
    passed = {c: all(v["passes"] for v in verdicts if v["candidate"] == c) for c in CANDIDATES}
    # the training rates, from each run's own record of the process that trained it to 2^21 steps
    rates = []
    for name in (REPLACED, *CANDIDATES):
        runs = [a for a in agents if a.name.rsplit("_s", 1)[0] == name]
        metas = [json.loads((a / "metadata.json").read_text()) for a in runs]
        per = [m["timesteps"] / m["wall_s"] for m in metas]
        cfg = (metas[0].get("config_file") or "-").split("agents/configs/")[-1]
        rates.append(f"| {name} | {cfg} | {len(per)} | {metas[0]['timesteps']:,} | "
                     f"{min(per):,.0f} - {max(per):,.0f} | {sum(m['wall_s'] for m in metas) / len(metas) / 60:.1f} |")
    text = "\n".join([
        "<!-- written by docs/budget/equivalence.py; do not edit by hand -->",
        "| scenario group | configuration | seeds | episodes per seed | IQM score_vs_law [95 % CI] | "
        "failure rate | IQM inside the replaced configuration's CI |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Training rates, end to end (environment, learner, learning-curve evaluations and checkpoints "
        "included), from each run's metadata; two runs trained at once, one per core:",
        "",
        "| configuration | config file | seeds | agent steps | agent steps/s (range over seeds) | "
        "mean wall time, min |",
        "|---|---|---|---|---|---|",
        *rates,
        "",
        *(f"- **{c}**: {'passes' if ok else 'fails'} the test (inside the interval on "
          f"{sum(v['passes'] for v in verdicts if v['candidate'] == c)} of "
          f"{sum(1 for v in verdicts if v['candidate'] == c)} groups)." for c, ok in passed.items()),
        "",
    ])
    args.out.write_text(text)
    args.out.with_suffix(".json").write_text(json.dumps(
        {"statistics": [stats[k] for k in sorted(stats)], "verdicts": verdicts, "passed": passed}, indent=1))
    print(text)


if __name__ == "__main__":
    main()
