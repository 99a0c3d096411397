#!/usr/bin/env bash
# The floor (baselines/floor.py) on every difficulty level (docs/levels.md), at the agent's 10 ms
# period and at 1 ms (the same gains), beside the proposed law, on the whole protocol of each level:
# the presets, the training suite's 20 held-out episodes and the stress suite's 50.
set -euo pipefail
cd "$(dirname "$0")/../.."
for level in 0 1 2 3; do
    blf-eval --controllers proposed --agents --policies floor "floor:control_period=0.001" --level "$level" \
        --out "docs/floor/L$level" --no-plots --no-progress > /dev/null
done
