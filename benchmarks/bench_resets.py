"""Resets under the default reward: the plain random-action loop and the cost of each reset.

Plain ``PlanarBLF-v0`` on the training suite under uniform random torques: episodes end after
about 1.3 steps (a violation), so the loop is mostly resets, each drawing a new scenario. The score
reward's reference (the law alone on that scenario) comes lazily, with the episode, so a reset
simulates nothing. Prints the loop's steps per second and each reset's cost, in milliseconds and
in residual ``env.step`` calls of a long episode (the step's median, measured first). Each reset
is timed twice: wall time, and the calling thread's CPU time, which leaves out the moments the
operating system gave the core to another process (on this shared 2-core machine, one reset in
tens of thousands waits that way for several milliseconds).

Run:  python benchmarks/bench_resets.py [--seconds 15] [--no-gc] [--json docs/speed/resets.json]
``--no-gc`` turns Python's cyclic garbage collector off, to tell its pauses from the env's own cost.
``--json FILE`` adds this run's figures to FILE (``benchmarks/results_json.py``), from which
``python docs/tables.py`` writes the table of docs/speed.md.
"""

from __future__ import annotations

import argparse
import gc
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import blf_gym  # noqa: F401  (registers the ids)
from bench_env import env_step_us  # the residual step's median, as bench_env measures it


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--no-gc", action="store_true")
    ap.add_argument("--json", type=Path, default=None, metavar="FILE",
                    help="also add this run's figures to FILE (e.g. docs/speed/resets.json)")
    args = ap.parse_args()
    import results_json

    start = results_json.context()
    if args.no_gc:
        gc.disable()
    step = env_step_us("PlanarBLFResidual-v0", 1500, scenario="randomized") / 1e6

    env = gym.make("PlanarBLF-v0", scenario="randomized")
    env.reset(seed=0)
    space, rng = env.action_space, np.random.default_rng(0)
    for _ in range(300):  # warm-up
        _, _, te, tr, _ = env.step(rng.uniform(space.low, space.high).astype(np.float32))
        if te or tr:
            env.reset()
    resets, cpu, steps, t0 = [], [], 0, time.perf_counter()
    while time.perf_counter() - t0 < args.seconds:
        _, _, te, tr, _ = env.step(rng.uniform(space.low, space.high).astype(np.float32))
        steps += 1
        if te or tr:
            r0, c0 = time.perf_counter(), time.thread_time()
            env.reset()
            resets.append(time.perf_counter() - r0)
            cpu.append(time.thread_time() - c0)
    wall = time.perf_counter() - t0
    r, c = np.array(resets), np.array(cpu)
    print(f"residual env.step, long episode: median {step * 1e6:.0f} us")
    print(f"plain random-action loop, default reward: {steps / wall:,.0f} steps/s, {len(r):,} resets "
          f"({steps / max(len(r), 1):.2f} steps per episode)   target >= 1,000 steps/s")
    print(f"reset: median {np.median(r) * 1e3:.2f} ms ({np.median(r) / step:.1f} steps), "
          f"p99 {np.percentile(r, 99) * 1e3:.2f} ms ({np.percentile(r, 99) / step:.1f} steps), "
          f"max {r.max() * 1e3:.2f} ms ({r.max() / step:.1f} steps)   target <= 20 steps"
          + ("   [garbage collector off]" if args.no_gc else ""))
    print(f"reset, CPU time of the calling thread: median {np.median(c) * 1e3:.2f} ms, p99 "
          f"{np.percentile(c, 99) * 1e3:.2f} ms, max {c.max() * 1e3:.2f} ms ({c.max() / step:.1f} steps)")
    if args.json:
        def stats(x: np.ndarray) -> dict[str, float]:
            return {"median": float(np.median(x)) * 1e3, "p99": float(np.percentile(x, 99)) * 1e3,
                    "max": float(x.max()) * 1e3}

        results_json.add_run(args.json, "benchmarks/bench_resets.py", {
            "seconds": args.seconds, "gc": not args.no_gc, "residual_step_us": step * 1e6,
            "steps_per_s": steps / wall, "steps": steps, "resets": len(r),
            "reset_ms": stats(r), "reset_cpu_ms": stats(c)}, start)


if __name__ == "__main__":
    main()
