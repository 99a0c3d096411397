"""The training rates measured alone, back to back: a table from ``benchmarks/bench_train.py --json``.

    python benchmarks/bench_train.py --algo ppo --mode plain --timesteps 262144 --json ppo.json
    python benchmarks/bench_train.py --algo sbx_ppo --mode plain --timesteps 262144 --json sbx.json
    python benchmarks/bench_train.py --algo sbx_ppo --mode plain --timesteps 262144 \\
        --config agents/configs/budget/sbx_ppo_256.yaml --json sbx256.json
    # the shipped residual configuration on four paths (docs/budget.md, section 1)
    OMP_NUM_THREADS=1 python benchmarks/bench_train.py --algo ppo --mode residual --timesteps 262144 --json r1.json
    OMP_NUM_THREADS=2 python benchmarks/bench_train.py --algo ppo --mode residual --timesteps 262144 --json r2.json
    XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1" python benchmarks/bench_train.py \
        --algo sbx_ppo --mode residual --timesteps 262144 --config agents/configs/budget/sbx_ppo_residual.yaml --json r3.json
    python benchmarks/bench_train.py --algo sbx_ppo --mode residual --timesteps 262144 \
        --config agents/configs/budget/sbx_ppo_residual.yaml --json r4.json
    python docs/budget/rates.py ppo.json sbx.json sbx256.json r1.json r2.json r3.json r4.json [--out docs/budget/rates.md]

The JSON files of the shipped table are in docs/budget/rates/.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="bench_train.py --json outputs, in the order to show")
    p.add_argument("--out", type=Path, default=Path(__file__).with_name("rates.md"),
                   help="the Markdown table to write (default docs/budget/rates.md)")
    args = p.parse_args()
    keys = ("env", "normalize", "inference", "update", "curves", "bookkeeping", "rest")
    rows = []
    for path in args.runs:
        r = json.loads(path.read_text())
        cfg = r.get("config") or {}
        net = (cfg.get("policy_kwargs") or {}).get("net_arch")
        hp = cfg.get("hyperparams") or {}
        shape = (f"{cfg.get('n_envs')} x {hp.get('n_steps')}, batch {hp.get('batch_size')}, "
                 f"{hp.get('n_epochs')} epochs, {net}")
        wall = r["wall_s"]
        s = r["seconds"]
        th = r.get("threads") or {}
        if "torch" not in th:
            # measured before bench_train.py recorded them: blf-train then always gave torch one
            learner = "not recorded" if r["algo"].startswith("sbx") else "1"
        elif r["algo"].startswith("sbx"):
            learner = "1" if "intra_op_parallelism_threads=1" in th.get("XLA_FLAGS", "") else "all"
        else:
            learner = str(th["torch"])
        rows.append(f"| {r['algo']} | {r['mode']} | {shape} | {learner} | {r['steps']:,} | {r['steps'] / wall:,.0f} | "
                    f"{r['steps'] / (wall - s['curves']):,.0f} | "
                    + " | ".join(f"{100 * s[k] / wall:.0f}" for k in keys) + " |")
    text = "\n".join([
        "<!-- written by docs/budget/rates.py from benchmarks/bench_train.py --json; do not edit by hand -->",
        "| algorithm | mode | arms x steps per rollout, minibatch, epochs, network | learner threads | agent steps | "
        "agent steps/s | without curve evaluations | " + " | ".join(f"{k} %" for k in keys) + " |",
        "|---|---|---|---|---|---|---|" + "---|" * len(keys),
        *rows, "",
        "Measured alone, one after the other within each mode, over the first 262,144 steps of a run on the "
        "training suite (where the untrained policy's episodes are short and resets weigh most; whole runs are "
        "faster, see budget.md). Learner threads: torch's, or XLA's (1 when XLA_FLAGS sets one intra-op "
        "thread, else all); the env always steps on one. The shares are bench_train.py's exclusive times; sbx's rollout loop is "
        "its own, so its policy inference and rollout bookkeeping fall under rest, with JAX's compilation.",
        ""])
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
