"""The training rates measured alone, back to back: a table from ``benchmarks/bench_train.py --json``.

    python benchmarks/bench_train.py --algo ppo --mode plain --timesteps 262144 --json ppo.json
    python benchmarks/bench_train.py --algo sbx_ppo --mode plain --timesteps 262144 --json sbx.json
    python benchmarks/bench_train.py --algo sbx_ppo --mode plain --timesteps 262144 \\
        --config agents/configs/budget/sbx_ppo_256.yaml --json sbx256.json
    python docs/budget/rates.py ppo.json sbx.json sbx256.json [--out docs/budget/rates.md]

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
        rows.append(f"| {r['algo']} | {shape} | {r['steps']:,} | {r['steps'] / wall:,.0f} | "
                    f"{r['steps'] / (wall - s['curves']):,.0f} | "
                    + " | ".join(f"{100 * s[k] / wall:.0f}" for k in keys) + " |")
    text = "\n".join([
        "<!-- written by docs/budget/rates.py from benchmarks/bench_train.py --json; do not edit by hand -->",
        "| algorithm | arms x steps per rollout, minibatch, epochs, network | agent steps | agent steps/s | "
        "without curve evaluations | " + " | ".join(f"{k} %" for k in keys) + " |",
        "|---|---|---|---|---|" + "---|" * len(keys),
        *rows, "",
        "Measured alone, one after the other, over the first 262,144 steps of a plain run on the training "
        "suite (where the untrained policy's episodes are short and resets weigh most; whole runs are "
        "faster, see budget.md). The shares are bench_train.py's exclusive times; sbx's rollout loop is "
        "its own, so its policy inference and rollout bookkeeping fall under rest, with JAX's compilation.",
        ""])
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
