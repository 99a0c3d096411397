"""The ladder's learners (issue 61, items 5-6; docs/levels.md, "The ladder"): plain learners trained
with the audited set-up on every difficulty level, three seeds each, resumable across sessions.

    python docs/ladder/run.py --stage ppo            # PPO, levels 0-3, seeds 0-2, 2M agent steps each
    python docs/ladder/run.py --stage sac            # SAC, levels 0 and 3, seeds 0-2, 2M steps each
    python docs/ladder/run.py --stage long           # the best set-up, 20M steps on the full benchmark
    python docs/ladder/run.py --stage bench          # PPO at levels 0 and 1 with the full benchmark's reward
    python docs/ladder/run.py --stage family_residual  # the tuned residual PPO on the 2- and 7-link arms, 1M steps
    python docs/ladder/run.py --stage family_plain   # the audited plain PPO on the 2- and 7-link arms, 2M steps
    python docs/ladder/run.py --keep                 # keep every run in docs/ladder/runs (at each commit)
    python docs/ladder/run.py --restore              # bring kept runs back into --out, to resume them

The family stages train on members of the task family (docs/family.md) with the same set-up and
budget as on the paper's arm: the residual PPO as shipped (its config, 1M agent steps) and the
plain PPO as on the ladder (2M steps, the full benchmark's level).

Seeds 0, 1 and 2 were fixed before any run; levels and configurations are never chosen on the
stress suite. A finished run is kept lean (its model, normalisation statistics, metadata and
learning curve); an unfinished one through docs/budget/keep.sh (its newest complete checkpoint),
from which ``--restore`` and a rerun of the stage continue it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[2]
KEPT = ROOT / "docs" / "ladder" / "runs"
SEEDS = (0, 1, 2)


class Run(NamedTuple):
    name: str
    algo: str
    config: str
    level: int
    seed: int
    steps: int
    sets: tuple[str, ...] = ()
    mode: str = "plain"


PPO_CONFIG = "agents/configs/ppo_plain_ladder.yaml"
RESIDUAL_CONFIG = "agents/configs/ppo_PlanarBLFResidual-v0.yaml"
FAMILY_LINKS = (2, 7)
"""The members the learners train on: the smallest and the largest of the task family."""
SAC_CONFIG = "agents/configs/sac_plain_ladder.yaml"

BENCH_REWARD = ("env.reward_weights={tracking: 100.0, torque: 0.01, alive: 1.0, violation: 1500000.0}",)
"""Levels 0 and 1 widen the bounds tenfold, so the shaped reward's tracking term, (e1 / bound)^2, is a
hundred times flatter there than on the full benchmark. These weights give back the full benchmark's
reward as a function of the error: 100 (e1 / (10 k))^2 = (e1 / k)^2 against an alive bonus of 1. The
bonus is then below the largest tracking cost inside the wide bounds (100), so the env asks that a
violation cost more than the rest of any episode could: (100 - 1) x 15,000 steps at 2 ms, 1.485M."""

STAGES: dict[str, list[Run]] = {
    # seed-major, so that an interrupted stage has every level at its first seeds
    "ppo": [Run(f"ppo_L{lv}_s{s}", "ppo", PPO_CONFIG, lv, s, 2_000_000) for s in SEEDS for lv in (0, 1, 2, 3)],
    "sac": [Run(f"sac_L{lv}_s{s}", "sbx_sac", SAC_CONFIG, lv, s, 2_000_000) for s in SEEDS for lv in (0, 3)],
    "long": [Run("ppo_long_L3_s0", "ppo", PPO_CONFIG, 3, 0, 20_000_000)],
    "bench": [Run(f"ppo_bench_L{lv}_s{s}", "ppo", PPO_CONFIG, lv, s, 2_000_000, BENCH_REWARD) for s in SEEDS for lv in (0, 1)],
    "family_residual": [Run(f"family_ppo_residual_n{n}_s{s}", "ppo", RESIDUAL_CONFIG, 3, s, 1_000_000, (f"env.n_links={n}",),
                            "residual") for s in SEEDS for n in FAMILY_LINKS],
    "family_plain": [Run(f"family_ppo_plain_n{n}_s{s}", "ppo", PPO_CONFIG, 3, s, 2_000_000, (f"env.n_links={n}",))
                     for s in SEEDS for n in FAMILY_LINKS],
}
"""Every ladder run, by stage: its folder name, algorithm, config, level, seed and agent steps."""


def _meta(run: Path) -> dict | None:
    p = run / "metadata.json"
    return json.loads(p.read_text()) if p.is_file() else None


def _complete(run: Path, steps: int) -> bool:
    m = _meta(run)
    return bool(m and m.get("completed") and int(m.get("timesteps_requested", 0)) >= steps)


def _train(r: Run, out: Path) -> str:
    run = out / r.name
    if _complete(run, r.steps):
        return f"{r.name}: finished already"
    cmd = ["nice", "-n", "5", sys.executable, "-m", "agents.train", "--algo", r.algo, "--mode", r.mode,
           "--scenario", "randomized", "--seed", str(r.seed), "--config", r.config, "--timesteps", str(r.steps),
           "--out", str(run), "--name", r.name, "--no-progress"]
    # the same --set on a resumed run: blf-train checks the file and overrides against the run's config
    cmd += ["--set", f"env.level={r.level}"]
    for kv in r.sets:
        cmd += ["--set", kv]
    if _meta(run) is not None or (run / "checkpoints").is_dir():
        cmd.append("--resume")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with open(out / f"{r.name}.log", "a") as log:
        rc = subprocess.call(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    if rc != 0:
        return f"{r.name}: blf-train failed (exit {rc}); see {out / (r.name + '.log')}"
    return f"{r.name}: trained in {time.time() - t0:.0f} s"


def keep(out: Path) -> None:
    """Every run folder under ``out`` into docs/ladder/runs: lean when finished, else its newest
    complete checkpoint (docs/budget/keep.sh)."""
    for run in sorted(p for p in out.iterdir() if p.is_dir() and (p / "metadata.json").is_file()):
        dst = KEPT / run.name
        m = _meta(run)
        if m.get("completed") and (run / "model.zip").is_file():
            tmp = KEPT / f".{run.name}.tmp"
            shutil.rmtree(tmp, ignore_errors=True)
            (tmp / "eval").mkdir(parents=True)
            for f in ("model.zip", "vecnormalize.pkl", "metadata.json"):
                if (run / f).is_file():
                    shutil.copy2(run / f, tmp / f)
            shutil.copy2(run / "eval" / "curve.json", tmp / "eval" / "curve.json")
            shutil.rmtree(dst, ignore_errors=True)
            tmp.rename(dst)
            print(f"{run.name}: kept (finished, {m['timesteps']:,} steps)")
        else:
            subprocess.call(["bash", str(ROOT / "docs" / "budget" / "keep.sh"), str(run), str(dst)], cwd=ROOT)


def restore(out: Path) -> None:
    """Each kept unfinished run back into ``out`` (docs/budget/keep.sh --restore)."""
    for dst in sorted(p for p in KEPT.iterdir() if p.is_dir() and (p / "checkpoints").is_dir()):
        subprocess.call(["bash", str(ROOT / "docs" / "budget" / "keep.sh"), "--restore", str(dst), str(out / dst.name)],
                        cwd=ROOT)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stage", choices=list(STAGES), help="train this stage's runs")
    ap.add_argument("--out", default=str(ROOT / "runs" / "ladder"), help="run folders (default runs/ladder)")
    ap.add_argument("--jobs", type=int, default=2, help="runs at a time (default 2, one per core)")
    ap.add_argument("--only", nargs="+", help="these run names of the stage (default all)")
    ap.add_argument("--keep", action="store_true", help="keep every run of --out in docs/ladder/runs")
    ap.add_argument("--restore", action="store_true", help="restore the kept unfinished runs into --out")
    a = ap.parse_args(argv)
    out = Path(a.out)
    if a.restore:
        restore(out)
    if a.stage:
        runs = [r for r in STAGES[a.stage] if not a.only or r.name in a.only]
        with ThreadPoolExecutor(max_workers=a.jobs) as pool:
            for msg in pool.map(lambda r: _train(r, out), runs):
                print(msg, flush=True)
    if a.keep:
        keep(out)
    if not (a.stage or a.keep or a.restore):
        ap.error("give --stage, --keep or --restore")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
