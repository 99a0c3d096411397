"""``blf-tune`` (also ``python -m agents.tune``): a small, resumable hyperparameter search.

Each candidate is one ``blf-train`` config file (a YAML with the keys of ``agents/configs``). Every
candidate is trained for the same budget and seeds on the randomized suite, then scored by the last
point of its learning curve (``eval/curve.json``: blf-eval's metrics on both paper presets and
held-out training-suite episodes; never the stress suite). The table ranks candidates by the
benchmark's score, ``score_vs_law`` on each group's pooled RMSEs (the geometric mean over joints of
the law's RMSE over the candidate's), combined over the three groups by their geometric mean, and
shows each joint's RMSE over the law's beside it. A candidate with a violation ranks below every
candidate without one.

Examples::

    blf-tune agents/configs/tuning/*.yaml --algo ppo --timesteps 300000 --out runs/tune --jobs 2
    blf-tune agents/configs/tuning/*.yaml --algo ppo --timesteps 300000 --out runs/tune --seeds 0 1 2

Runs that already finished are kept and not trained again, so an interrupted search resumes where
it stopped. Writes ``OUT/tune.json`` and ``OUT/tune.md``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from blf_gym.io import atomic_write_json, atomic_write_text

__all__ = ["main", "law_levels", "score_run"]

GROUPS = ("paper-0.1hz", "paper-0.5hz", "randomized")


def law_levels(suite_seeds: int, duration: float | None = None, controller: str = "proposed") -> dict[str, list[float]]:
    """RMSE (deg, per joint) of a baseline controller on the learning-curve scenarios."""
    from blf_gym.metrics import summarize

    from .evaluate import build_scenarios, evaluate_controller

    out = {}
    for label, scs in build_scenarios(["paper-0.1hz", "paper-0.5hz"], suite_seeds, {}, duration):
        rec = summarize(evaluate_controller(controller, scs, threads=1), controller, "baseline", label, scs[0].sim.dt)
        out[label] = [float(v) for v in rec["rmse_deg"]]
    return out


def score_run(run: Path, law: dict[str, list[float]]) -> dict[str, Any]:
    """The last learning-curve point of a run, with RMSE ratios to the law (1 = the law's level)."""
    curve = json.loads((run / "eval" / "curve.json").read_text())
    last = curve["points"][-1]
    row: dict[str, Any] = {"run": run.name, "timesteps": last["timesteps"], "wall_s": last["wall_s"]}
    ratios = []
    for g in GROUPS:
        rmse = np.asarray(last[g]["rmse_deg"], dtype=float)
        r = rmse / np.asarray(law[g], dtype=float)
        ratios.extend(r.tolist())
        row[g] = {"rmse_deg": rmse.tolist(), "ratio": r.tolist(), "violations": last[g]["violations"],
                  "failure_rate": last[g]["failure_rate"]}
    from blf_gym.metrics import score_vs_law

    row["worst_ratio"] = float(np.max(ratios))
    row["mean_ratio"] = float(np.exp(np.mean(np.log(ratios))))
    row["score"] = {g: score_vs_law(row[g]["rmse_deg"], law[g]) for g in GROUPS}
    # the geometric mean of the groups' scores (equal to 1 / the geometric mean of the 9 ratios)
    row["score_vs_law"] = float(np.exp(np.mean(np.log([row["score"][g] for g in GROUPS]))))
    row["violations"] = int(sum(sum(row[g]["violations"]) for g in GROUPS))
    return row


def rank(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Best first: no violation before any violation, then higher score_vs_law."""
    return sorted(rows, key=lambda r: (r["violations"] > 0, -r["score_vs_law"]))


def _markdown(rows: list[dict[str, Any]], law: dict[str, list[float]]) -> str:
    lines = ["| run | steps | wall (s) | score_vs_law | score 0.1 Hz / 0.5 Hz / suite | RMSE / law, 0.1 Hz (j1 j2 j3) "
             "| 0.5 Hz | suite | viol | worst ratio |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rank(rows):
        cells = [" ".join(f"{v:.3f}" for v in r[g]["ratio"]) for g in GROUPS]
        scores = " / ".join(f"{r['score'][g]:.3f}" for g in GROUPS)
        lines.append(f"| {r['run']} | {r['timesteps']} | {r['wall_s']:.0f} | {r['score_vs_law']:.3f} | {scores} | "
                     + " | ".join(cells) + f" | {r['violations']} | {r['worst_ratio']:.3f} |")
    lines.append("")
    lines.append("Law level (proposed, RMSE deg j1 j2 j3): " + "; ".join(
        f"{g}: " + " ".join(f"{v:.4f}" for v in law[g]) for g in GROUPS))
    return "\n".join(lines) + "\n"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-tune", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("configs", nargs="+", type=Path, help="candidate blf-train config files (YAML)")
    p.add_argument("--algo", default="ppo", help="SB3 algorithm for every candidate (default ppo)")
    p.add_argument("--mode", default="residual", choices=("plain", "residual"),
                   help="plain: the action is the torque; residual: added to the proposed law (default residual)")
    p.add_argument("--timesteps", type=int, default=300_000, metavar="N",
                   help="budget per run, in agent steps (default 300000)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], metavar="S",
                   help="training seeds per candidate (default 0)")
    p.add_argument("--scenario", default="randomized", metavar="NAME",
                   help="training scenario (default randomized, the randomized suite)")
    p.add_argument("--out", type=Path, default=Path("runs/tune"), metavar="DIR",
                   help="folder for the runs, tune.json and tune.md (default runs/tune)")
    p.add_argument("--jobs", type=int, default=1, metavar="J",
                   help="runs trained at the same time, one core each (default 1)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from .train import load_config

    try:
        cfgs = [load_config(c) for c in args.configs]
        if args.timesteps < 1 or args.jobs < 1:
            raise ValueError("--timesteps and --jobs must be >= 1")
        if args.scenario == "stress":
            raise ValueError("the stress suite is held out and never trained or tuned on; use randomized")
        # every candidate is scored against the law on the same scenarios
        scoring = {(c.get("curve_suite_seeds", 4), (c.get("env") or {}).get("duration")) for c in cfgs}
        if len(scoring) > 1:
            raise ValueError("all candidates must share curve_suite_seeds and env.duration (they are "
                             f"scored on the same scenarios); got {sorted(scoring, key=str)}")
    except ValueError as exc:
        print(f"blf-tune: error: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    todo = []
    runs = []
    for c in args.configs:
        for seed in args.seeds:
            run = args.out / (f"{c.stem}" + (f"_s{seed}" if len(args.seeds) > 1 else ""))
            runs.append(run)
            meta = run / "metadata.json"
            if meta.is_file() and json.loads(meta.read_text()).get("completed"):
                continue
            cmd = [sys.executable, "-m", "agents.train", "--algo", args.algo, "--mode", args.mode,
                   "--scenario", args.scenario, "--timesteps", str(args.timesteps), "--seed", str(seed),
                   "--config", str(c), "--out", str(run), "--no-progress"]
            if meta.is_file():
                cmd.append("--resume")
            todo.append((run, cmd))
    print(f"blf-tune: {len(runs) - len(todo)} run(s) done, {len(todo)} to train", file=sys.stderr)
    running: list[tuple[Path, subprocess.Popen]] = []
    failed = []
    try:
        while todo or running:
            while todo and len(running) < args.jobs:
                run, cmd = todo.pop(0)
                print(f"blf-tune: training {run.name}", file=sys.stderr)
                running.append((run, subprocess.Popen(cmd)))
            run, proc = running[0]
            proc.wait()
            running.pop(0)
            if proc.returncode != 0:
                failed.append(run.name)
    except KeyboardInterrupt:
        for _, proc in running:
            proc.wait()
        print("\nblf-tune: interrupted; finished runs are kept, run the same command to resume", file=sys.stderr)
        return 130
    suite_seeds, duration = scoring.pop()
    law = law_levels(int(suite_seeds), duration)
    rows = [score_run(r, law) for r in runs if (r / "eval" / "curve.json").is_file()]
    atomic_write_json(args.out / "tune.json", {"law": law, "rows": rows})
    table = _markdown(rows, law)
    atomic_write_text(args.out / "tune.md", table)
    print(table)
    if failed:
        print(f"blf-tune: failed runs: {failed}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
