#!/usr/bin/env bash
# The runs of docs/budget.md, as chains of stages (at most two chains at once on two cores):
#
#   docs/budget/plan.sh A RUNS_DIR     # the replaced configuration: SB3 PPO, seeds 0-2, 2^21 steps
#   docs/budget/plan.sh B RUNS_DIR     # candidate 1 (sbx_ppo_PlanarBLF-v0.yaml): seeds 0-2, 2^21 steps
#   docs/budget/plan.sh C RUNS_DIR     # candidate 2 (budget/sbx_ppo_256.yaml): seeds 0-2, 2^21 steps
#   docs/budget/plan.sh D RUNS_DIR NAME  # the scale runs of the candidate NAME (sbx_ppo or sbx_ppo_256)
#                                        # chosen by the rule of docs/budget.md: seed 0 to 50M, 1-2 to 20M
#   docs/budget/plan.sh E RUNS_DIR [S...]  # section 3: sbx SAC, seeds S (default 0 1 2), 15,052 s of
#                                          # wall clock each (--time-budget)
#   docs/budget/plan.sh F RUNS_DIR [S...]  # section 4, sixth set-up: PPO-Lagrangian warm-started from
#                                          # plain PPO, then plain PPO likewise, seeds S (default 1 2)
#
# Every stage resumes where the last job stopped (docs/budget/run.sh), so the same command is
# repeated in each job until the chain is done.
set -euo pipefail
chain=$1
runs=$2
here=$(dirname "$0")
cfgs=agents/configs  # the configs as the runs' metadata name them: run from the repository's root
equal=2097152
# the run as it stands at 2^21 steps (before it is extended), for the equivalence test
keep() {
    if [ ! -f "$2/model.zip" ]; then
        mkdir -p "$2.tmp"
        cp "$1/model.zip" "$1/metadata.json" "$2.tmp/"
        if [ -f "$1/vecnormalize.pkl" ]; then cp "$1/vecnormalize.pkl" "$2.tmp/"; fi
        rm -rf "$2"
        mv "$2.tmp" "$2"
    fi
}

case "$chain" in
A)
    for s in 0 1 2; do
        "$here/run.sh" "$runs/ppo_s$s" $equal --algo ppo --mode plain --scenario randomized --seed $s --name "ppo_s$s"
    done ;;
B)
    for s in 0 1 2; do
        "$here/run.sh" "$runs/sbx_ppo_s$s" $equal --algo sbx_ppo --mode plain --scenario randomized --seed $s \
            --name "sbx_ppo_s$s"
        keep "$runs/sbx_ppo_s$s" "$runs/equal/sbx_ppo_s$s"
    done ;;
C)
    for s in 0 1 2; do
        "$here/run.sh" "$runs/sbx_ppo_256_s$s" $equal --algo sbx_ppo --mode plain --scenario randomized --seed $s \
            --config "$here/../../agents/configs/budget/sbx_ppo_256.yaml" --name "sbx_ppo_256_s$s"
        keep "$runs/sbx_ppo_256_s$s" "$runs/equal/sbx_ppo_256_s$s"
    done ;;
D)
    name=${3:?"plan.sh D needs the chosen candidate's name (sbx_ppo or sbx_ppo_256)"}
    for s in 0 1 2; do keep "$runs/${name}_s$s" "$runs/equal/${name}_s$s"; done
    "$here/run.sh" "$runs/${name}_s0" 50000000
    "$here/run.sh" "$runs/${name}_s1" 20000000
    "$here/run.sh" "$runs/${name}_s2" 20000000 ;;
E)
    seeds=("${@:3}"); [ ${#seeds[@]} -gt 0 ] || seeds=(0 1 2)
    for s in "${seeds[@]}"; do
        "$here/run.sh" "$runs/sbx_sac_s$s" 1000000000 --time-budget 15052 --algo sbx_sac --mode plain \
            --scenario randomized --seed "$s" --config "$cfgs/budget/sbx_sac.yaml" --name "sbx_sac_s$s"
    done ;;
F)
    seeds=("${@:3}"); [ ${#seeds[@]} -gt 0 ] || seeds=(1 2)
    for s in "${seeds[@]}"; do
        "$here/run.sh" "$runs/ppo_lagrangian_warm_s$s" 3000000 --algo ppo_lagrangian --mode plain \
            --scenario randomized --seed "$s" --config "$cfgs/ppo_lagrangian_PlanarBLF-v0.yaml" \
            --set init_from=agents/pretrained/ppo_plain --set normalize_reward=false \
            --set hyperparams.termination_cost=3000 --set hyperparams.cost_limit_start=2800 \
            --set hyperparams.cost_limit_steps=2000000 \
            --set "env.reward_weights={tracking: 1.0, torque: 0.01, violation: 100.0}" \
            --name "ppo_lagrangian_warm_s$s"
        "$here/run.sh" "$runs/ppo_warm_s$s" 3000000 --algo ppo --mode plain --scenario randomized --seed "$s" \
            --config "$cfgs/ppo_PlanarBLF-v0.yaml" --set init_from=agents/pretrained/ppo_plain \
            --name "ppo_warm_s$s"
    done ;;
*)
    echo "usage: $0 A|B|C RUNS_DIR, $0 D RUNS_DIR NAME, or $0 E|F RUNS_DIR [SEED...]" >&2
    exit 2 ;;
esac
