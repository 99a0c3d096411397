"""Wall time of one sweep of 8 short trials (agents/configs/sweeps/scaling.yaml) three ways, one
run each: 1 trial at a time and 2 at a time on a local Ray instance, and 2 at a time on a two-node
Ray cluster simulated on this machine (``ray.cluster_utils.Cluster``: a head and a worker node,
1 CPU each, both on 127.0.0.1), which shows where the trials were placed.

Run:  python benchmarks/sweep_scaling.py [--out DIR] [--json docs/sweeps/scaling.json]

Each sweep writes into its own fresh folder. Per trial it reports the blf-train process's own
wall time (metadata.json) so the overhead of Ray and of process start-up is visible beside it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SWEEP = ROOT / "agents" / "configs" / "sweeps" / "scaling.yaml"


def _sweep(out: Path, *extra: str) -> dict:
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "agents.sweep", str(SWEEP), "--out", str(out), *extra],
                       capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"sweep failed ({p.returncode}):\n{p.stderr[-3000:]}")
    res = json.loads((out / "sweep.json").read_text())
    trials = []
    for t in res["trials"]:
        meta = json.loads((out / "runs" / t["run"] / "metadata.json").read_text())
        trials.append({"run": t["run"], "node_id": t["node_id"], "train_wall_s": meta["wall_s"]})
    return {"wall_s": round(wall, 1), "inside_fit_s": res.get("wall_s"), "done": res["counts"].get("done", 0),
            "nodes": res["ray"]["nodes"], "concurrency": res["ray"]["concurrency"], "trials": trials,
            "median_train_wall_s": round(statistics.median(t["train_wall_s"] for t in trials), 1),
            "sum_train_wall_s": round(sum(t["train_wall_s"] for t in trials), 1),
            "best": res["configs"][0]["objective"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = ap.parse_args()
    scratch = args.out or Path(tempfile.mkdtemp(prefix="blf-sweep-scaling-"))
    for d in ("c1", "c2", "cluster"):
        shutil.rmtree(scratch / d, ignore_errors=True)
    res = {"c1": _sweep(scratch / "c1", "--concurrency", "1"), "c2": _sweep(scratch / "c2", "--concurrency", "2")}
    # one trial's blf-train as a plain process, start to exit (imports, kernel cache, curve points)
    first = json.loads((scratch / "c1" / "runs" / res["c1"]["trials"][0]["run"] / "trial.json").read_text())
    cmd = first["command"].split()
    cmd[cmd.index("--out") + 1] = str(scratch / "direct")
    shutil.rmtree(scratch / "direct", ignore_errors=True)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "agents.train", *cmd[1:]], check=True, capture_output=True, cwd=ROOT)
    res["direct_process_s"] = round(time.perf_counter() - t0, 1)
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    try:
        res["cluster"] = _sweep(scratch / "cluster", "--address", cluster.address)
    finally:
        cluster.shutdown()
    res["cluster"]["trials_per_node"] = {}
    for t in res["cluster"]["trials"]:
        k = (t["node_id"] or "?")[:8]
        res["cluster"]["trials_per_node"][k] = res["cluster"]["trials_per_node"].get(k, 0) + 1
    res["speedup_c2_over_c1"] = round(res["c1"]["wall_s"] / res["c2"]["wall_s"], 2)
    res["speedup_cluster_over_c1"] = round(res["c1"]["wall_s"] / res["cluster"]["wall_s"], 2)
    for k in ("c1", "c2", "cluster"):
        r = res[k]
        print(f"{k:8s} {r['nodes']} node(s), {r['concurrency']} at a time: {r['wall_s']:6.1f} s for {r['done']} "
              f"trials (median trial's blf-train {r['median_train_wall_s']} s, sum {r['sum_train_wall_s']} s)")
    print(f"one trial as a plain blf-train process, start to exit: {res['direct_process_s']} s "
          f"(x 8 = {8 * res['direct_process_s']:.0f} s)")
    print(f"speed-up, 2 at a time over 1: {res['speedup_c2_over_c1']}x; two-node cluster over 1: "
          f"{res['speedup_cluster_over_c1']}x")
    print(f"cluster placement (trials per node id): {res['cluster']['trials_per_node']}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
