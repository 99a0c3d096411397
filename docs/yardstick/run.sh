#!/usr/bin/env bash
# Every rliable report in docs/ written again: with the bootstrap seeded (agents.report seeds
# numpy's global generator, which rliable's bootstraps read whatever random_state they get; before,
# an interval's ends moved in the third or fourth digit between runs) and scored against the
# second yardstick (issue "Ask the question of the strongest controller", item 5). Their evaluations ran before records carried
# score_vs_reference, and some agents' folders are not kept, so the reports take PPC's records
# from runs on the same episodes instead: docs/protocol_control (the presets, the training suite's
# 20 and the stress suite's 50 episodes) and docs/protocol_reference (PPC on the training suite's
# 20 and on the certificate's 100 stress episodes, written by the first command below).
# agents.report checks that the proposed law's per-episode RMSEs agree between the runs.
set -euo pipefail
cd "$(dirname "$0")/../.."
[ -f docs/protocol_reference/results.json ] || blf-eval --controllers proposed ppc --agents --suite randomized stress --suite-seeds 20 100 \
    --out docs/protocol_reference --no-progress
refs="docs/protocol_control/results.json docs/protocol_reference/results.json"
report() {  # RESULTS JSON [MD]
    python -m agents.report "$1" --json "$2" ${3:+--out "$3"} --reference ppc --reference-results $refs > /dev/null
}
report docs/protocol/results.json docs/seeds_report.json docs/seeds_table.md
for d in protocol_certified protocol_certified_handback/barrier protocol_certified_handback/barrier_handback \
         protocol_learners budget/protocol_scale budget/protocol_sac budget/protocol_warm budget/offpolicy_select; do
    report docs/$d/results.json docs/$d/report.json docs/$d/seeds_table.md
done
