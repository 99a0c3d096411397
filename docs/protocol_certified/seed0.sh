#!/usr/bin/env bash
# The shipped certified agent (agents/pretrained/ppo_residual_certified) as seed 0 of the certified
# residual's five, in RUNS/ppo_residual_certified_s0, unless it is there already: named like seeds
# 1-4 and with the filter they were all trained with (the shipped metadata deploys it with the
# hand-back), so that a --residual-filter names all five alike and the report pools them.
#
#   docs/protocol_certified/seed0.sh RUNS
set -euo pipefail
s0=$1/ppo_residual_certified_s0
if [ ! -f "$s0/model.zip" ]; then
    mkdir -p "$s0"
    cp agents/pretrained/ppo_residual_certified/model.zip agents/pretrained/ppo_residual_certified/vecnormalize.pkl "$s0/"
    python -c "import json, sys; m = json.load(open(sys.argv[1])); m['name'] = 'ppo_residual_certified_s0'; m['env_kwargs']['residual_filter'] = 'barrier'; json.dump(m, open(sys.argv[2], 'w'), indent=2)" \
        agents/pretrained/ppo_residual_certified/metadata.json "$s0/metadata.json"
fi
