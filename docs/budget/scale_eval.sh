#!/usr/bin/env bash
# A scale learner's verdict (docs/budget.md, sections 2 and 3): its three seeds' kept runs
# docs/budget/runs/NAME_s0, _s1 and _s2 (keep.sh), each scored on the protocol beside the law (the
# presets, the training suite's 20 held-out episodes and the stress suite's 50), and pooled with
# rliable's statistics (python -m agents.report), into OUT. NAME is sbx_ppo_256 (plain PPO at
# 50M/20M/20M agent steps; OUT docs/budget/protocol_scale) by default, or sbx_sac (SAC for 15,052 s
# per seed; OUT docs/budget/protocol_sac). blf-eval loads the kept runs as they are; it needs the
# jax extra (pip install -e ".[jax]").
#
#   docs/budget/scale_eval.sh [OUT [NAME]]
set -euo pipefail
out=${1:-docs/budget/protocol_scale}
name=${2:-sbx_ppo_256}
runs=()
for s in 0 1 2; do
    run=docs/budget/runs/${name}_s$s
    if [ ! -f "$run/model.zip" ]; then
        echo "$run: no finished model yet (train it with docs/budget/run.sh, then keep it with docs/budget/keep.sh)" >&2
        exit 1
    fi
    runs+=("$run")
done
blf-eval --controllers proposed --agents "${runs[@]}" --jobs 1 --out "$out" --no-plots --no-progress
python -m agents.report "$out/results.json" --out "$out/seeds_table.md"
