#!/usr/bin/env bash
# The runs of docs/budget.md, in order, as two chains of stages (one per core):
#
#   docs/budget/plan.sh A RUNS_DIR     # the replaced configuration: SB3 PPO, seeds 0-2, 2^21 steps
#   docs/budget/plan.sh B RUNS_DIR     # the large-batch candidate: seeds 0-2 to 2^21, then 50M / 20M
#
# Every stage resumes where the last job stopped (docs/budget/run.sh), so the same command is
# repeated in each job until the chain is done.
set -euo pipefail
chain=$1
runs=$2
here=$(dirname "$0")
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
    done
    "$here/run.sh" "$runs/sbx_ppo_s0" 50000000
    "$here/run.sh" "$runs/sbx_ppo_s1" 20000000
    "$here/run.sh" "$runs/sbx_ppo_s2" 20000000 ;;
*)
    echo "usage: $0 A|B RUNS_DIR" >&2
    exit 2 ;;
esac
