#!/usr/bin/env bash
# One stage of a long training run that may span several jobs (docs/budget.md).
#
#   docs/budget/run.sh OUT STEPS [blf-train options ...]
#
# Starts the run in OUT when OUT holds none; otherwise resumes it from its newest complete
# checkpoint and trains it up to STEPS agent steps in total (a run already at STEPS is left as it
# is). The options are passed on both times: on a resume they must agree with the run's own
# (blf-train refuses a contradiction), and --time-budget S ends the run once its model has taken S
# seconds of wall clock over all its segments ("as many steps as S seconds allow", with a large
# STEPS; a run whose budget is spent is left as it is).
# Repeat the same command in the next job until it reports the run complete. A job that is killed
# loses at most the steps since its last checkpoint (the config's checkpoint_freq).
#
# Each job should give the run whole cores: the env and the learner each use one thread here, set
# by the variables below (two runs at once on two cores).
set -euo pipefail
if [ "$#" -lt 2 ]; then
    echo "usage: $0 OUT STEPS [blf-train options]" >&2
    exit 2
fi
out=$1
steps=$2
shift 2
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
export XLA_FLAGS=${XLA_FLAGS:-"--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
newest=""  # the newest complete checkpoint's steps (its folder is checkpoints/step_<steps>)
if [ -d "$out/checkpoints" ]; then
    for d in "$out"/checkpoints/step_*; do
        n=${d##*/step_}
        case "$n" in ''|*[!0-9]*) continue ;; esac
        if [ -z "$newest" ] || [ "$n" -gt "$newest" ]; then newest=$n; fi
    done
fi
if [ -n "$newest" ] && [ "$newest" -ge "$steps" ]; then
    echo "$out: its newest checkpoint has $newest steps (>= $steps); this stage is done" >&2
    exit 0
fi
if [ -f "$out/metadata.json" ] || [ -d "$out/checkpoints" ]; then
    exec blf-train --resume --out "$out" --timesteps "$steps" --no-progress "$@"
else
    exec blf-train --out "$out" --timesteps "$steps" --no-progress "$@"
fi
