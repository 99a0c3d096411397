#!/usr/bin/env bash
# The choice of the off-policy learner (docs/budget.md, section 3's amendment): seed 0 of sbx's
# SAC and of sbx's CrossQ, each after one hour of wall clock, scored beside the law on the presets
# and the training suite's 20 held-out episodes (never the stress suite), into OUT (default
# docs/budget/offpolicy_select). The higher training-suite IQM score_vs_law is chosen; when the two
# 95 % intervals overlap, the higher mean score over the two presets decides. The runs are the
# kept ones (keep.sh); blf-eval needs the jax extra.
#
#   docs/budget/offpolicy_select.sh [OUT]
set -euo pipefail
out=${1:-docs/budget/offpolicy_select}
runs=()
for a in sac crossq; do
    run=docs/budget/runs/sbx_${a}_s0
    [ -f "$run/model.zip" ] || { echo "$run: no model yet (train it, then keep it with docs/budget/keep.sh)" >&2; exit 1; }
    runs+=("$run")
done
blf-eval --controllers proposed --agents "${runs[@]}" --suite randomized --jobs 1 --out "$out" --no-plots --no-progress
python -m agents.report "$out/results.json" --out "$out/seeds_table.md"
python - "$out/report.json" <<'PY'
import json
import sys

stats = json.load(open(sys.argv[1]))["statistics"]
row = {(s["policy"], s["scenario"]): s for s in stats}
names = ("sbx_sac", "sbx_crossq")
for n in names:
    r = row[(n, "randomized")]
    presets = [row[(n, p)]["iqm"] for p in ("paper-0.1hz", "paper-0.5hz")]
    print(f"{n}: training suite IQM {r['iqm']:.4f} [{r['ci95'][0]:.4f}, {r['ci95'][1]:.4f}], "
          f"presets {presets[0]:.4f} / {presets[1]:.4f}")
a, b = (row[(n, "randomized")] for n in names)
overlap = a["ci95"][0] <= b["ci95"][1] and b["ci95"][0] <= a["ci95"][1]
if overlap:
    key = {n: sum(row[(n, p)]["iqm"] for p in ("paper-0.1hz", "paper-0.5hz")) / 2 for n in names}
    how = "the intervals overlap, so the presets' mean score decides"
else:
    key = {n: row[(n, "randomized")]["iqm"] for n in names}
    how = "the intervals do not overlap, so the training-suite IQM decides"
print(f"chosen: {max(names, key=key.get)} ({how})")
PY
