#!/usr/bin/env bash
# Issue "Ask the question of the strongest controller", item 4: the shipped residual's set-up
# (PPO, 1M agent steps, 8 envs, randomized scenario, seeds 0-4 chosen before training) over the
# strongest bases instead of the paper-gain law. Same config, budget and seeds as the shipped
# residuals; only the base (--controller) differs:
#   res_proposed_tuned_s*   agents/configs/ppo_PlanarBLFResidual-v0.yaml over the tuned law
#   res_ppc_s*              the same over PPC (no filter applies: the barrier filter needs the
#                           proposed law's z1 and z2_hat, which PPC does not have)
#   cert_proposed_tuned_s*  agents/configs/ppo_residual_certified.yaml (the barrier filter) over the
#                           tuned law, the filter the certified residual uses over the paper-gain law
#
#   docs/budget/residual_best.sh [ROOT]      # ROOT default /work/runs/best; two runs at a time
#
# Each run is one docs/budget/run.sh stage, so repeating the command resumes every run from its
# newest complete checkpoint and skips finished ones; keep them across jobs with
# docs/budget/keep.sh ROOT/<run>.
set -euo pipefail
root=${1:-/work/runs/best}
here=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$root"
for run in res_proposed_tuned res_ppc cert_proposed_tuned; do
    for seed in 0 1 2 3 4; do
        echo "$run $seed"
    done
done | xargs -P "${JOBS:-2}" -L 1 bash -c '
    run=$0 seed=$1 base=${run#*_} config=agents/configs/ppo_PlanarBLFResidual-v0.yaml
    case "$run" in cert_*) config=agents/configs/ppo_residual_certified.yaml ;; esac
    out='"$root"'/${run}_s${seed}
    nice -n "${NICE:-10}" '"$here"'/run.sh "$out" 1000000 --algo ppo --mode residual \
        --controller "$base" --scenario randomized --seed "$seed" --config "$config" --name ${run}_s${seed} \
        >> "$out.log" 2>&1 && echo "done $run $seed" || echo "FAILED $run $seed"'
