"""The plain-learner audit (issue 61, item 4; docs/plain_audit.md): PPO with the candidate set-up
(agents/configs/ppo_plain_audit.yaml) and one variant per set-up choice, each a short run of one
seed on the training suite at the full benchmark (level 3), scored by its learning curve (the paper
presets and four held-out training-suite episodes; never the stress suite).

    python docs/plain_audit/run.py                 # every variant, two at a time, resumable
    python docs/plain_audit/run.py --only base noise0 --steps 200000 --out /tmp/audit

A finished run is skipped; an unfinished one resumes from its newest checkpoint. Each finished run's
metadata.json and eval/curve.json are copied to docs/plain_audit/runs/<variant>/ (no weights: the
audit's findings are its curves), from which ``python docs/plain_audit/report.py`` writes the
summary and the plot.
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

ROOT = Path(__file__).resolve().parents[2]
KEPT = ROOT / "docs" / "plain_audit" / "runs"
CONFIG = "agents/configs/ppo_plain_audit.yaml"
SEED = 0  # fixed before any run
STEPS = 1_000_000

VARIANTS: dict[str, tuple[str, list[str]]] = {
    "base": ("the candidate: action_scale law, log_std_init -2, start times 0-29 s, shaped reward, "
             "termination on, 10 ms, gamma 0.99, normalised observation", []),
    "scale_max": ("action scale max_torque (150 N m on every joint), as the earlier configs",
                  ["env.action_scale=null"]),
    "noise0": ("initial log-std 0 (the earlier configs')", ["policy_kwargs.log_std_init=0.0"]),
    "no_starts": ("every episode starts at t = 0", ["env.start_time=null"]),
    "no_termination": ("termination off, a violation cost of 10 per violating step (violation_rate)",
                       ["env.terminate_on_violation=false",
                        "env.reward_weights={tracking: 1.0, torque: 0.01, violation: 100.0, violation_rate: 10.0}"]),
    "curriculum": ("bounds 10x wider at first, narrowed to the benchmark's by 500k steps",
                   ["curriculum={bound_scale: 10.0, until: 500000}"]),
    "period_2ms": ("a 2 ms control period, gamma 0.998 (the same horizon in seconds)",
                   ["env.control_period=0.002", "hyperparams.gamma=0.998"]),
    "gamma_995": ("gamma 0.995 (a 2 s horizon instead of 1 s)", ["hyperparams.gamma=0.995"]),
    "no_normalize": ("no observation normalisation (VecNormalize off)", ["normalize=false"]),
    "preview": ("the reference's 30 ms preview added to the observation",
                ["env.observation_extras=[q_d_preview, qd_d_preview]"]),
    "score_reward": ("the score reward (the env's default; needs episodes from t = 0)",
                     ["env.reward_weights=null", "env.start_time=null"]),
    # run after the one-factor variants: the two that gained most at equal steps, together
    "period_2ms_curriculum": ("period_2ms and curriculum together (run after the others: their two best changes)",
                              ["env.control_period=0.002", "hyperparams.gamma=0.998",
                               "curriculum={bound_scale: 10.0, until: 500000}"]),
}
"""Each variant: what it changes against ``base``, and blf-train's ``--set`` overrides."""


def _complete(run: Path, steps: int) -> bool:
    meta = run / "metadata.json"
    if not meta.is_file():
        return False
    m = json.loads(meta.read_text())
    return bool(m.get("completed")) and int(m.get("timesteps_requested", 0)) >= steps


def _run(name: str, out: Path, steps: int) -> str:
    run = out / name
    if not _complete(run, steps):
        cmd = ["nice", "-n", "5", sys.executable, "-m", "agents.train", "--algo", "ppo", "--mode", "plain",
               "--scenario", "randomized", "--seed", str(SEED), "--config", CONFIG, "--timesteps", str(steps),
               "--out", str(run), "--name", f"audit_{name}", "--no-progress"]
        if (run / "metadata.json").is_file() or (run / "checkpoints").is_dir():
            cmd.append("--resume")
        else:
            for s in VARIANTS[name][1]:
                cmd += ["--set", s]
        run.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.time()
        with open(out / f"{name}.log", "a") as log:
            rc = subprocess.call(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        if rc != 0:
            return f"{name}: blf-train failed (exit {rc}); see {out / (name + '.log')}"
        print(f"{name}: done in {time.time() - t0:.0f} s", flush=True)
    dst = KEPT / name
    (dst / "eval").mkdir(parents=True, exist_ok=True)
    shutil.copy2(run / "metadata.json", dst / "metadata.json")
    shutil.copy2(run / "eval" / "curve.json", dst / "eval" / "curve.json")
    return f"{name}: kept in {dst}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "runs" / "plain_audit"), help="run folders (default runs/plain_audit)")
    ap.add_argument("--steps", type=int, default=STEPS, help=f"agent steps per run (default {STEPS})")
    ap.add_argument("--jobs", type=int, default=2, help="runs at a time (default 2, one per core)")
    ap.add_argument("--only", nargs="+", choices=list(VARIANTS), help="these variants (default all)")
    a = ap.parse_args(argv)
    names = a.only or list(VARIANTS)
    with ThreadPoolExecutor(max_workers=a.jobs) as pool:
        for msg in pool.map(lambda n: _run(n, Path(a.out), a.steps), names):
            print(msg, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
