#!/usr/bin/env bash
# Learning on top of the best (issue "Ask the question of the strongest controller", item 4): the
# fifteen residual runs of docs/budget/residual_best.sh scored on the whole protocol (the presets,
# the training suite's 20 held-out episodes, the stress suite's 50) beside their bases and the
# paper-gain law, then pooled over seeds by rliable (agents.report), which scores each residual
# against the paper-gain law, against PPC (the second yardstick) and against its own base.
#
#   docs/protocol_best/run.sh [RUNS]      # RUNS default /work/runs/best, or docs/budget/runs
set -euo pipefail
runs=${1:-/work/runs/best}
cd "$(dirname "$0")/../.."
blf-eval --controllers proposed proposed_tuned ppc \
    --agents "$runs"/res_proposed_tuned_s? "$runs"/cert_proposed_tuned_s? "$runs"/res_ppc_s? \
    --out docs/protocol_best --no-progress
python -m agents.report docs/protocol_best/results.json --out docs/protocol_best/seeds_table.md > /dev/null
# the best seed of each residual over a stronger base, shipped as an agent (never read: the stress suite)
python docs/protocol_best/ship.py "$runs"
