#!/usr/bin/env bash
# certificate_broken on the held-out certificate suite (blf_gym.scenarios, "certificate"): 120
# episodes (early forces, corners and uniform draws of the documented safe ranges, seeds from
# 30,000), the shipped certified residual through each filter, beside the law alone. A report:
# nothing is selected from it.
#
#   docs/certificate_cases/run.sh [OUT] [more blf-eval options]     # OUT defaults to docs/certificate_cases
set -euo pipefail
out=${1:-docs/certificate_cases}
shift || true
for filter in barrier cbf; do
    blf-eval --controllers proposed --agents agents/pretrained/ppo_residual_certified --residual-filter "$filter" \
        --scenarios --suite certificate --suite-seeds 120 --no-progress --out "$out/$filter" "$@"
done
