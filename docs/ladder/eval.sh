#!/usr/bin/env bash
# The ladder (issue 61, item 6; docs/levels.md, "The ladder"): on each difficulty level, the whole
# protocol of that level (the presets, the training suite's 20 held-out episodes, the stress suite's
# 50) for the law with the paper's and the tuned gains, PPC, the floor, the shipped residual agent
# over the tuned law (trained at level 3: at lower levels, its transfer), and every plain learner of
# docs/ladder/run.py kept for that level; then pooled over seeds by rliable (agents.report).
#
#   docs/ladder/eval.sh [KEPT]      # KEPT default docs/ladder/runs (a run is scored once finished)
#   LEVELS="3" docs/ladder/eval.sh  # only these levels (default 0 1 2 3)
set -euo pipefail
kept=${1:-docs/ladder/runs}
cd "$(dirname "$0")/../.."
for level in ${LEVELS:-0 1 2 3}; do
    agents=(agents/pretrained/ppo_residual_tuned)
    for run in "$kept"/*_L"$level"_s?; do
        [ -f "$run/model.zip" ] && grep -q '"completed": true' "$run/metadata.json" && agents+=("$run")
    done
    blf-eval --controllers proposed proposed_tuned ppc --policies floor --agents "${agents[@]}" --level "$level" \
        --out "docs/ladder/L$level" --no-plots --no-progress > /dev/null
    python -m agents.report "docs/ladder/L$level/results.json" --out "docs/ladder/L$level/seeds_table.md" > /dev/null
done
python docs/ladder/plot.py
