#!/usr/bin/env bash
# The certified residual retrained through the predictive hand-back (docs/certificate.md, "Judged by
# the falsifier"): the certified configuration (agents/configs/ppo_residual_certified.yaml)
# with the filter it is deployed with, barrier:handback=0.0033,lookahead=0.35,predict=0.5, seeds 0-4
# (the certified agent's own five, fixed before its first training), 1M agent steps each; then the
# five retrained seeds and the five trained without the hand-back, both deployed through it, on the
# protocol (the presets, the training suite's 20 held-out episodes, the stress suite), with the seed
# statistics of python -m agents.report. The predictive rule is the one retrained through because
# its training-suite IQM is the higher of the two hand-back rules (docs/fallback/protocol*); no
# falsifier result chose it.
#
#   docs/fallback/retrain.sh RUNS [OUT [STEP...]]   # OUT default docs/fallback/retrained
#
# STEPs, in this order by default: train (the five retrained seeds), before (the five trained without
# the hand-back, deployed through it: OUT/protocol_before), retrained (OUT/protocol).
#
# Resumable: a finished run is skipped, an interrupted one resumes from its newest checkpoint, and a
# finished protocol (its manifest complete) is not run again. The five seeds
# trained without the hand-back are taken from agents/pretrained (seed 0) and
# docs/protocol_certified/runs (seeds 1-4, their weights fetched from the history when absent).
set -euo pipefail
if [ "$#" -lt 1 ]; then
    echo "usage: $0 RUNS [OUT [STEP...]]   (STEPs: train before retrained)" >&2
    exit 2
fi
runs=$1
out=${2:-docs/fallback/retrained}
shift $(( $# < 2 ? $# : 2 ))
steps=" ${*:-train before retrained} "
spec="barrier:handback=0.0033,lookahead=0.35,predict=0.5"
flag() {  # 0 when the JSON file $1 has a true field $2 (a run's "completed", a manifest's "complete")
    python -c "import json, sys; sys.exit(0 if json.load(open(sys.argv[1])).get(sys.argv[2]) else 1)" "$1" "$2" \
        2>/dev/null
}
for s in 0 1 2 3 4; do
    [[ $steps == *" train "* ]] || break
    run=$runs/ppo_residual_predict_s$s
    if flag "$run/metadata.json" completed; then echo "seed $s: trained already"; continue; fi
    resume=()
    if [ -f "$run/metadata.json" ] || [ -d "$run/checkpoints" ]; then resume=(--resume); fi
    blf-train --algo ppo --mode residual --scenario randomized --timesteps 1000000 --seed "$s" \
        --config agents/configs/ppo_residual_certified.yaml --set "env.residual_filter=$spec" \
        --out "$run" --name "ppo_residual_predict_s$s" --no-progress "${resume[@]}"
done
# the five trained without the hand-back: seed 0 is the shipped agent, seeds 1-4 are kept in
# docs/protocol_certified/runs (weights shelved: fetched here when absent)
bash "$(dirname "$0")/../protocol_certified/seed0.sh" "$runs"
for s in 1 2 3 4; do
    kept=docs/protocol_certified/runs/ppo_residual_certified_s$s
    if [ ! -f "$runs/ppo_residual_certified_s$s/model.zip" ]; then
        [ -f "$kept/model.zip" ] || python docs/weights.py fetch "$kept"
        cp -r "$kept" "$runs/"
    fi
done
# each set on the protocol through the hand-back, in a folder of its own (so either can be rerun
# alone): protocol (retrained), protocol_before (trained without it); a finished one is kept
evaluate() {  # evaluate OUT AGENT...
    local dir=$1
    shift
    if ! flag "$dir/manifest.json" complete; then
        blf-eval --controllers proposed --agents "$@" --residual-filter "$spec" --out "$dir" --no-plots --no-progress \
            --jobs 1
    fi
    python -m agents.report "$dir/results.json" --out "$dir/seeds_table.md"
}
before=()
for s in 0 1 2 3 4; do before+=("$runs/ppo_residual_certified_s$s"); done
[[ $steps != *" before "* ]] || evaluate "$out/protocol_before" "${before[@]}"
retrained=()
for s in 0 1 2 3 4; do retrained+=("$runs/ppo_residual_predict_s$s"); done
[[ $steps != *" retrained "* ]] || evaluate "$out/protocol" "${retrained[@]}"
