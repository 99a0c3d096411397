#!/usr/bin/env bash
# The gain searches on the task family's members (docs/family.md, "Gains"): for each LAW and member,
# `python -m baselines.gains LAW --n-links N` over the paper arm's grid carried to the member (K1 over
# the same eight values; K2 the proposed law's carried first-joint gain times 1/8, 1/4, 1/2, 1 and 2,
# as the paper arm's 5.625 to 90 is 45 times those), on the member's two presets and training-suite
# seeds 0-7 only, the same torque budget. A search whose gains.json exists is skipped, so the script
# resumes; each writes atomically when it ends.
#
#   docs/gains/family/run.sh [LAW ...]      # LAWs default: ppc proposed; members 2 4 5 6 7
set -euo pipefail
cd "$(dirname "$0")/../../.."
laws=("$@")
[ ${#laws[@]} -eq 0 ] && laws=(ppc proposed)
for law in "${laws[@]}"; do
    for n in ${LINKS:-2 4 5 6 7}; do
        out="docs/gains/family/${law}_n$n"
        if [ -f "$out/gains.json" ]; then echo "$law, $n links: done already"; continue; fi
        k2=$(python -c "
from blf_gym.model.family import family_arm
from blf_gym.plugins.registry import make_controller
g = make_controller('proposed', nominal=family_arm($n)).params.K2[0]
print(','.join(repr(g * f) for f in (0.125, 0.25, 0.5, 1.0, 2.0)))")
        python -m baselines.gains "$law" --n-links "$n" --grid K1=20,40,80,160,320,640,1280,2560 --grid "K2=$k2" \
            --out "$out" --no-progress
    done
done
