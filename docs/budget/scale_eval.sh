#!/usr/bin/env bash
# The scale runs' verdict (docs/budget.md, section 2): plain PPO (sbx, budget/sbx_ppo_256.yaml) at
# 50M agent steps (seed 0) and 20M (seeds 1 and 2), each scored on the protocol beside the law (the
# presets, the training suite's 20 held-out episodes and the stress suite's 50), and the three
# seeds pooled with rliable's statistics (python -m agents.report), into OUT (default
# docs/budget/protocol_scale). The runs are the kept ones in docs/budget/runs (keep.sh), which
# blf-eval loads as they are; it needs the jax extra (pip install -e ".[jax]").
#
#   docs/budget/scale_eval.sh [OUT]
set -euo pipefail
out=${1:-docs/budget/protocol_scale}
runs=()
for s in 0 1 2; do
    run=docs/budget/runs/sbx_ppo_256_s$s
    if [ ! -f "$run/model.zip" ]; then
        echo "$run: no finished model yet (train it with docs/budget/run.sh, then keep it with docs/budget/keep.sh)" >&2
        exit 1
    fi
    runs+=("$run")
done
blf-eval --controllers proposed --agents "${runs[@]}" --jobs 1 --out "$out" --no-plots --no-progress
python -m agents.report "$out/results.json" --out "$out/seeds_table.md"
