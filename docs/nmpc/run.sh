#!/usr/bin/env bash
# The NMPC's rows on the protocol (docs/model.md section 15): the paper presets, 20 held-out
# episodes of the training suite and 50 of the stress suite, beside the proposed law, into
# docs/nmpc (or OUT). Not part of blf-eval's default set: it took 21 min on two cores (2026-12-04).
#
#   docs/nmpc/run.sh [OUT] [more blf-eval options]
#
# --jobs 1 keeps blf-eval in one process, so the NMPC's own two solver processes get the cores.
set -euo pipefail
out=${1:-docs/nmpc}
shift || true
exec blf-eval --controllers proposed --agents --policies nmpc --jobs 1 --out "$out" "$@"
