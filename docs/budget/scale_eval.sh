#!/usr/bin/env bash
# A learner's verdict over its three seeds (docs/budget.md, sections 2-4): for each NAME, the kept
# runs docs/budget/runs/NAME_s0, _s1 and _s2 (keep.sh), each scored on the protocol beside the law
# (the presets, the training suite's 20 held-out episodes and the stress suite's 50), and each
# NAME's seeds pooled with rliable's statistics (python -m agents.report), into OUT. By default
# NAME is sbx_ppo_256 (plain PPO at 50M/20M/20M agent steps) and OUT docs/budget/protocol_scale;
# SAC's (15,052 s per seed) is `scale_eval.sh docs/budget/protocol_sac sbx_sac`, the warm-started
# runs' `scale_eval.sh docs/budget/protocol_warm ppo_lagrangian_warm ppo_warm`. blf-eval loads the
# kept runs as they are; it needs the jax extra (pip install -e ".[jax]") for sbx's learners.
#
#   docs/budget/scale_eval.sh [OUT [NAME...]]
set -euo pipefail
out=${1:-docs/budget/protocol_scale}
names=("${@:2}")
[ ${#names[@]} -gt 0 ] || names=(sbx_ppo_256)
runs=()
for name in "${names[@]}"; do
    for s in 0 1 2; do
        run=docs/budget/runs/${name}_s$s
        # a run kept mid-way has a model.zip too (its last job's), but is not the run the plan asks for
        if [ ! -f "$run/model.zip" ] || ! python -c 'import json, sys; sys.exit(not json.load(open(sys.argv[1])).get("completed"))' "$run/metadata.json" 2>/dev/null; then
            echo "$run: not a completed run yet (train it to its end with docs/budget/run.sh, then keep it with docs/budget/keep.sh)" >&2
            exit 1
        fi
        runs+=("$run")
    done
done
blf-eval --controllers proposed --agents "${runs[@]}" --jobs 1 --out "$out" --no-plots --no-progress
python -m agents.report "$out/results.json" --out "$out/seeds_table.md"
