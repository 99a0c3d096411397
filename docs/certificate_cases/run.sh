#!/usr/bin/env bash
# certificate_broken on the held-out certificate suite (blf_gym.envs.scenarios, "certificate"): 120
# episodes (early forces, corners and uniform draws of the documented safe ranges, seeds from
# 30,000), the shipped certified residual through each filter, without and with the hand-back
# monitor (handback = e2_max / (3 k0) = 3.3e-3 rad at the defaults), beside the law alone. A report:
# nothing is selected from it.
#
#   docs/certificate_cases/run.sh [OUT] [more blf-eval options]     # OUT defaults to docs/certificate_cases
set -euo pipefail
out=${1:-docs/certificate_cases}
shift || true
for filter in barrier cbf barrier:handback=0.0033 cbf:handback=0.0033; do
    blf-eval --controllers proposed --agents agents/pretrained/ppo_residual_certified --residual-filter "$filter" \
        --scenarios --suite certificate --suite-seeds 120 --no-progress --no-plots --out "$out/${filter/:/_}" "$@"
done
