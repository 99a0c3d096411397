#!/usr/bin/env bash
# Keep a long run across machines (docs/budget.md, "Running it"): only what is committed survives
# the end of a job.
#
#   docs/budget/keep.sh RUN [KEPT]             # RUN -> KEPT (default docs/budget/runs/<RUN's name>)
#   docs/budget/keep.sh --restore KEPT RUN     # KEPT -> RUN (unless RUN is as far already), then
#                                              # repeat the stage's run.sh command
#
# Keeping copies RUN's metadata.json, its learning curve (eval/curve.json, as curve.json) and its
# newest complete checkpoint folder (checkpoints/step_<N>: a step_ folder is complete by
# construction, agents/checkpoints.py) into KEPT, replacing the checkpoint kept before, so that a
# commit holds one checkpoint per run. The run's model.zip (and vecnormalize.pkl when it has one)
# is kept too, so that `blf-eval --agents KEPT` scores it as it is; for a run stopped mid-way that
# is its last segment's model, and docs/budget/scale_eval.sh scores completed runs only. Restoring copies
# the metadata, curve and checkpoint back into RUN's layout.
#
# Weights leave the tree (docs/weights.py): once a keep is committed, `python docs/weights.py shelve
# KEPT` stages the removal of its weights (recorded in docs/weights.json with the commit that holds
# them); commit that too. --restore brings shelved weights back first (`docs/weights.py fetch KEPT`),
# and a keep forgets the manifest's entries of the files it replaces.
#
# An off-policy checkpoint's replay buffer (replay_buffer.pkl, about 270 MB at 1M samples) is not
# kept: it is too large to commit. The kept state.json no longer lists it, so the set is complete
# without it, and blf-train, resuming from it, lets the policy refill the buffer before updating
# again (recorded in the segment's "replay_buffer").
set -euo pipefail
weights="$(dirname "$0")/../weights.py"
newest() {  # the newest step_<N> folder under $1/checkpoints, or nothing
    local best="" n d
    for d in "$1"/checkpoints/step_*; do
        [ -d "$d" ] || continue
        n=${d##*/step_}
        case "$n" in ''|*[!0-9]*) continue ;; esac
        if [ -z "$best" ] || [ "$n" -gt "${best##*/step_}" ]; then best=$d; fi
    done
    echo "$best"
}
if [ "${1:-}" = "--restore" ]; then
    [ "$#" -eq 3 ] || { echo "usage: $0 --restore KEPT RUN" >&2; exit 2; }
    kept=$2 run=$3
    python3 "$weights" fetch --quiet "$kept" >/dev/null  # shelved weights back (nothing if none)
    ck=$(newest "$kept")
    [ -n "$ck" ] || { echo "$kept: no checkpoints/step_<N> folder to restore" >&2; exit 1; }
    have=$(newest "$run")
    if [ -n "$have" ] && [ "${have##*/step_}" -ge "${ck##*/step_}" ]; then
        echo "$run: already at ${have##*/} (kept: ${ck##*/}); nothing restored"
        exit 0
    fi
    mkdir -p "$run/checkpoints" "$run/eval"
    cp "$kept/metadata.json" "$run/metadata.json"
    [ ! -f "$kept/curve.json" ] || cp "$kept/curve.json" "$run/eval/curve.json"
    rm -rf "$run/checkpoints/${ck##*/}"
    cp -r "$ck" "$run/checkpoints/"
    echo "$run: restored ${ck##*/} from $kept"
    exit 0
fi
[ "$#" -ge 1 ] && [ "$#" -le 2 ] || { echo "usage: $0 RUN [KEPT]  |  $0 --restore KEPT RUN" >&2; exit 2; }
run=${1%/}
kept=${2:-docs/budget/runs/$(basename "$run")}
ck=$(newest "$run")
[ -n "$ck" ] || { echo "$run: no complete checkpoint yet (checkpoints/step_<N>)" >&2; exit 1; }
mkdir -p "$kept/checkpoints"
tmp=$(mktemp -d "$kept/checkpoints/.keep.XXXXXX")
mkdir "$tmp/${ck##*/}"
for f in "$ck"/*; do [ "${f##*/}" = replay_buffer.pkl ] || cp -r "$f" "$tmp/${ck##*/}/"; done
if [ -f "$ck/replay_buffer.pkl" ]; then
    python3 - "$tmp/${ck##*/}/state.json" <<'PY'
import json, sys
path = sys.argv[1]
with open(path) as f:
    state = json.load(f)
state["files"] = [f for f in state["files"] if f != "replay_buffer.pkl"]
state["replay_buffer"] = "not kept (docs/budget/keep.sh); a resume refills it"
with open(path, "w") as f:
    f.write(json.dumps(state, indent=2) + "\n")
PY
fi
cp "$run/metadata.json" "$tmp/metadata.json"
[ ! -f "$run/eval/curve.json" ] || cp "$run/eval/curve.json" "$tmp/curve.json"
for f in model.zip vecnormalize.pkl; do [ ! -f "$run/$f" ] || cp "$run/$f" "$tmp/$f"; done
# the new checkpoint is whole before the old one goes
for d in "$kept"/checkpoints/step_*; do [ -d "$d" ] || continue; rm -rf "$d"; python3 "$weights" forget "$d" >/dev/null; done
mv "$tmp/${ck##*/}" "$kept/checkpoints/"
mv "$tmp/metadata.json" "$kept/metadata.json"
[ ! -f "$tmp/curve.json" ] || mv "$tmp/curve.json" "$kept/curve.json"
for f in model.zip vecnormalize.pkl; do
    [ -f "$tmp/$f" ] || continue
    mv "$tmp/$f" "$kept/$f"
    python3 "$weights" forget "$kept/$f" >/dev/null
done
rmdir "$tmp"
echo "$kept: kept ${ck##*/} of $run"
