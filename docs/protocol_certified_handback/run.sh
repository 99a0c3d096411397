#!/usr/bin/env bash
# The certified residual's five training seeds on the protocol (the presets, the training suite's 20
# held-out episodes and the stress suite's 100), through the barrier filter without and with the
# hand-back (docs/certificate.md), each with the
# seed statistics of python -m agents.report, and with the hand-back on the 120 held-out
# certificate cases (the suite of docs/certificate_cases, never used for selection), into OUT
# (default docs/protocol_certified_handback):
#
#   docs/protocol_certified_handback/run.sh RUNS [OUT]
#
# RUNS holds ppo_residual_certified_s1 ... _s4 (the config agents/configs/ppo_residual_certified.yaml,
# seeds 1-4, 1M steps each; kept in docs/protocol_certified/runs). Seed 0 is the shipped agent,
# agents/pretrained/ppo_residual_certified: copied into RUNS as ppo_residual_certified_s0, with
# that name, so that the report pools it with the others.
set -euo pipefail
if [ "$#" -lt 1 ]; then
    echo "usage: $0 RUNS [OUT]" >&2
    exit 2
fi
runs=$1
out=${2:-docs/protocol_certified_handback}
bash "$(dirname "$0")/../protocol_certified/seed0.sh" "$runs"
agents=()
for s in 0 1 2 3 4; do agents+=("$runs/ppo_residual_certified_s$s"); done
for spec in barrier barrier:handback=0.0033; do
    dir=$out/$(echo "$spec" | cut -d: -f1)$(case $spec in *handback*) echo _handback ;; esac)
    blf-eval --controllers proposed --agents "${agents[@]}" --residual-filter "$spec" --suite randomized stress \
        --suite-seeds 20 100 --out "$dir" --no-plots --no-progress
    python -m agents.report "$dir/results.json" --out "$dir/seeds_table.md"
done
blf-eval --controllers proposed --agents "${agents[@]}" --residual-filter barrier:handback=0.0033 --scenarios \
    --suite certificate --suite-seeds 120 --out "$out/certificate_handback" --no-plots --no-progress
