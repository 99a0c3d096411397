"""How the env's threads and torch's share the cores: agent steps per second of a CleanRL-style
loop (the native vector env, a torch MLP acting every step and a gradient step on each batch) for
several (env threads, torch threads) pairs, each in its own process, medians over rounds.

Run:  python benchmarks/bench_threads.py [--rounds 3] [--num-envs 8] [--json docs/speed/threads.json]
``--json FILE`` writes every round and the medians to FILE (``benchmarks/results_json.py``), from
which ``python docs/tables.py`` writes the threads table of docs/conventions.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

_PROBE = r"""
import json, sys, time
import numpy as np, torch, gymnasium as gym
import blf_gym
env_threads, torch_threads, N = (None if sys.argv[1] == "default" else int(sys.argv[1])), sys.argv[2], int(sys.argv[3])
if torch_threads != "default":
    torch.set_num_threads(int(torch_threads))
kw = {} if env_threads is None else {"threads": env_threads}
envs = gym.make_vec("PlanarBLFResidual-v0", num_envs=N, scenario="paper-0.1hz", **kw)
obs, _ = envs.reset(seed=0)
net = torch.nn.Sequential(torch.nn.Linear(obs.shape[1], 64), torch.nn.Tanh(), torch.nn.Linear(64, 64),
                          torch.nn.Tanh(), torch.nn.Linear(64, 3))
opt = torch.optim.Adam(net.parameters(), lr=1e-4)
buf = []
def run(steps):
    global obs
    for k in range(steps):
        with torch.no_grad():
            a = torch.tanh(net(torch.as_tensor(obs))).numpy() * 0.01
        obs, r, te, tr, info = envs.step(a)
        buf.append(obs)
        if len(buf) == 128:
            x = torch.as_tensor(np.concatenate(buf))
            loss = net(x).pow(2).mean()
            opt.zero_grad(); loss.backward(); opt.step(); buf.clear()
run(200)
t0 = time.perf_counter(); run(1000); dt = time.perf_counter() - t0
print(json.dumps({"steps_per_s": 1000 * N / dt, "env_threads": envs.unwrapped.core.loop.threads,
                  "torch_threads": torch.get_num_threads()}))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--num-envs", type=int, default=8)
    ap.add_argument("--json", type=Path, default=None, metavar="FILE",
                    help="also write the rounds and medians to FILE (e.g. docs/speed/threads.json)")
    args = ap.parse_args()
    import results_json

    start = results_json.context()
    pairs = [("default", "default"), ("2", "default"), ("1", "default"), ("1", "1"), ("2", "1")]
    res = {p: [] for p in pairs}
    info = {}
    for _ in range(args.rounds):
        for p in pairs:
            out = subprocess.run([sys.executable, "-c", _PROBE, p[0], p[1], str(args.num_envs)], check=True,
                                 capture_output=True, text=True, env={**os.environ}).stdout
            d = json.loads(out.strip().splitlines()[-1])
            res[p].append(d["steps_per_s"])
            info[p] = (d["env_threads"], d["torch_threads"])
    print(f"{os.cpu_count()} CPUs, num_envs={args.num_envs}, medians of {args.rounds} rounds (agent steps/s, all arms):")
    for p in pairs:
        print(f"  env threads {p[0]:>7s} -> {info[p][0]}, torch threads {p[1]:>7s} -> {info[p][1]}: "
              f"{statistics.median(res[p]):8.0f}")
    if args.json:
        results_json.write(args.json, "benchmarks/bench_threads.py", {
            "rounds": args.rounds, "num_envs": args.num_envs,
            "pairs": [{"env_threads": p[0], "torch_threads": p[1], "env_threads_used": info[p][0],
                       "torch_threads_used": info[p][1], "steps_per_s": statistics.median(res[p]),
                       "rounds_steps_per_s": res[p]} for p in pairs]}, start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
