"""Speed of PlanarBLF-v0 through ``gym.make`` and of the native vector env (issue: env, item 12).

Prints medians measured in this run, beside Gymnasium's Pendulum-v1 measured in the same run, and
the targets: residual ``env.step`` (10 ms simulated = 100 closed-loop steps) <= 100 us median;
vector env in residual mode >= 15,000 agent steps/s at N = 64.

Run:  python benchmarks/bench_env.py [--steps 2000] [--json docs/speed/env.json]
``--json FILE`` adds this run's figures to FILE (``benchmarks/results_json.py``), from which
``python docs/tables.py`` writes the table of docs/speed.md.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import blf_gym  # noqa: F401  (registers the ids)


def env_step_us(env_id: str, steps: int, **kwargs) -> float:
    env = gym.make(env_id, **kwargs)
    env.reset(seed=0)
    a = np.zeros(env.action_space.shape, dtype=np.float32)
    for _ in range(20):  # warm-up (kernel load)
        env.step(a)
    env.reset(seed=0)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        _, _, term, trunc, _ = env.step(a)
        times.append(time.perf_counter() - t0)
        if term or trunc:
            env.reset()
    env.close()
    return statistics.median(times) * 1e6


def _fresh_env_step_us(steps: int, kwargs: dict) -> float:
    """The residual env.step median in a new process (so no other kernel shares it)."""
    import json
    import subprocess
    import sys

    code = ("import json, sys; sys.path.insert(0, %r); import bench_env; "
            "print(bench_env.env_step_us('PlanarBLFResidual-v0', %d, **json.loads(%r)))"
            % (str(__import__('pathlib').Path(__file__).parent), steps, json.dumps(kwargs)))
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def _vector_rate(num_envs: int, steps: int, threads: int | None) -> float:
    venv = gym.make_vec("PlanarBLFResidual-v0", num_envs=num_envs, threads=threads)
    venv.reset(seed=0)
    a = np.zeros((num_envs, 3), dtype=np.float32)
    for _ in range(3):
        venv.step(a)
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        venv.step(a)
        times.append(time.perf_counter() - t0)
    venv.close()
    return num_envs / statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--json", type=Path, default=None, metavar="FILE",
                    help="also add this run's figures to FILE (e.g. docs/speed/env.json)")
    args = ap.parse_args()
    import results_json

    start = results_json.context()
    pend = env_step_us("Pendulum-v1", args.steps)
    plain = env_step_us("PlanarBLF-v0", args.steps)
    resid = env_step_us("PlanarBLFResidual-v0", args.steps)
    # the barrier filter (docs/model.md section 11), against the unfiltered env, each in a fresh
    # process, alternating (in one process a second kernel slows the first one's env down)
    filt, unf = [], []
    for _ in range(2):
        unf.append(_fresh_env_step_us(args.steps, {}))
        filt.append(_fresh_env_step_us(args.steps, {"residual_filter": "barrier"}))
    print(f"env.step through gym.make, median of {args.steps}:")
    print(f"  Pendulum-v1            {pend:8.1f} us")
    print(f"  PlanarBLF-v0 (plain)   {plain:8.1f} us   ({plain / pend:.1f}x Pendulum)")
    print(f"  PlanarBLFResidual-v0   {resid:8.1f} us   ({resid / pend:.1f}x Pendulum)   "
          f"target <= 100 us  ratio {resid / 100:.2f}x")
    f, u = statistics.median(filt), statistics.median(unf)
    print(f"  residual, fresh processes: unfiltered {u:8.1f} us, barrier filter {f:8.1f} us   ({f / u:.3f}x; "
          f"target <= 1.10x)")
    print("\nvector env, residual mode, agent steps per second (median step):")
    rates = []
    for n in (1, 16, 64):
        for threads in (1, 2):
            if n == 1 and threads == 2:
                continue
            rate = _vector_rate(n, max(20, args.steps // (4 * n)), threads)
            rates.append({"num_envs": n, "threads": threads, "steps_per_s": rate})
            tgt = f"   target >= 15000  ratio {rate / 15000:.2f}x" if n == 64 else ""
            print(f"  N = {n:3d}  threads = {threads}  {rate:9.0f} /s{tgt}")
    if args.json:
        results_json.add_run(args.json, "benchmarks/bench_env.py", {
            "steps": args.steps,
            "env_step_us": {"Pendulum-v1": pend, "PlanarBLF-v0": plain, "PlanarBLFResidual-v0": resid},
            "fresh_process_residual_us": {"unfiltered": unf, "barrier": filt},
            "vector": rates}, start)


if __name__ == "__main__":
    main()
