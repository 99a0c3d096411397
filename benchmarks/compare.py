"""Speed of two source trees, measured back to back and interleaved (A B A B ...).

This machine's speed drifts by several per cent between runs, so a change is judged against the
previous commit in the same session: each round runs one short measurement of each tree in its
own process (``PYTHONPATH`` points at the tree), alternating, and the medians over rounds are
compared. The figures, each measured within its process:

* ``step_us``: one closed-loop step (plant + LESO + proposed law, ODE3 at 0.1 ms), amortised over
  a 30 s run in one compiled call;
* ``env_us``: the residual ``env.step`` through ``gym.make`` (100 integration steps);
* ``vec64``: agent steps per second of the residual vector env at N = 64 on 2 threads (the median
  step of 300; two threads share this machine's two cores with whatever else runs, so a short
  sample swung by a third between rounds);
* ``env_fresh_us``: the residual ``env.step``'s mean over the first 300 steps of a fresh process
  (after ``gym.make`` and ``reset``, which load the kernel);
* ``env_mean_us``, ``env_rand_us``, ``env_plain_us``: the mean ``env.step`` over two 30 s episodes
  (resets included, and on the training suite the law reference each new episode computes lazily
  for the score term): residual on the 0.1 Hz preset, residual on ``scenario="randomized"``, plain
  on the preset;
* ``batch64_us``: one closed-loop step per arm, amortised over a batch of 64 mixed training-suite
  scenarios with measurement noise on, on one thread (100-step calls, the env's control period),
  in blocks of 4 lanes where the tree has them.

Run:  python benchmarks/compare.py BASE_TREE NEW_TREE [--rounds 5] [--json docs/speed/compare.json]
e.g.  git worktree add /tmp/base HEAD~1 && python benchmarks/compare.py /tmp/base .
``--json FILE`` writes every round, the medians and each tree's commit to FILE
(``benchmarks/results_json.py``), from which ``python docs/tables.py`` writes the comparison
table of docs/speed.md.

Each tree compiles its own kernels on first use (numba's cache lives next to its sources); a
warm-up round that is not counted does that.
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
import json, statistics, time, sys
import numpy as np
import gymnasium as gym
import os
import blf_gym
# import by the tree's own layout: the flat modules before blf_gym's sub-packages, the sub-packages
# after (asked of the files: an editable install would answer a new path in an old tree)
if os.path.isdir(os.path.join(os.path.dirname(blf_gym.__file__), "model")):
    from blf_gym.model.params import preset
    from blf_gym.kernel.simulate import ClosedLoop
    from blf_gym.envs.scenarios import sample_suite
else:
    from blf_gym.params import preset
    from blf_gym.simulate import ClosedLoop
    from blf_gym.scenarios import sample_suite

def mean_step_us(env, steps):  # the mean of `steps` env steps, resets (and a lazy law reference) included
    a = np.zeros(env.action_space.shape, dtype=np.float32)
    t0 = time.perf_counter()
    for _ in range(steps):
        _, _, te, tr, _ = env.step(a)
        if te or tr:
            env.reset()
    return (time.perf_counter() - t0) / steps * 1e6

# first thing in this fresh process: the residual env's first 300 steps after gym.make and reset
env = gym.make("PlanarBLFResidual-v0")
env.reset(seed=0)
fresh = mean_step_us(env, 300)

sc = preset("paper-0.1hz")
loop = ClosedLoop([sc], "proposed", threads=1)
loop.advance(10)
steps = []
for _ in range(3):
    loop.set_scenarios([sc])
    t0 = time.perf_counter()
    loop.advance(sc.sim.n_steps, record_samples=sc.sim.n_samples)
    steps.append((time.perf_counter() - t0) / sc.sim.n_steps * 1e6)

env = gym.make("PlanarBLFResidual-v0")
env.reset(seed=0)
a = np.zeros(3, dtype=np.float32)
for _ in range(20):
    env.step(a)
env.reset(seed=0)
ts = []
for _ in range(1500):
    t0 = time.perf_counter()
    _, _, te, tr, _ = env.step(a)
    ts.append(time.perf_counter() - t0)
    if te or tr:
        env.reset()

venv = gym.make_vec("PlanarBLFResidual-v0", num_envs=64, threads=2)
venv.reset(seed=0)
A = np.zeros((64, 3), dtype=np.float32)
for _ in range(10):
    venv.step(A)
vs = []
for _ in range(300):
    t0 = time.perf_counter()
    venv.step(A)
    vs.append(time.perf_counter() - t0)

mixed = [sample_suite(np.random.default_rng(s)) for s in range(64)]
try:
    batch = ClosedLoop(mixed, "proposed", threads=1, lanes=4)
except TypeError:  # a tree from before the lanes
    batch = ClosedLoop(mixed, "proposed", threads=1)
noise = np.random.default_rng(0).normal(size=(64, 100, 3)) * np.radians(0.01)
batch.advance(100, noise=noise, record_samples=0)
bs = []
for _ in range(5):
    batch.set_scenarios(mixed)
    t0 = time.perf_counter()
    for _ in range(20):
        batch.advance(100, noise=noise, record_samples=0)
    bs.append((time.perf_counter() - t0) / (20 * 100 * 64) * 1e6)
means = {}
for key, env_id, scenario in (("env_mean_us", "PlanarBLFResidual-v0", "paper-0.1hz"),
                              ("env_rand_us", "PlanarBLFResidual-v0", "randomized"),
                              ("env_plain_us", "PlanarBLF-v0", "paper-0.1hz")):
    e = gym.make(env_id, scenario=scenario)
    e.reset(seed=0)
    mean_step_us(e, 50)
    e.reset(seed=0)
    means[key] = mean_step_us(e, 6000)  # two 30 s episodes: two resets, and on the suite two law references
print(json.dumps({"step_us": statistics.median(steps), "env_us": statistics.median(ts) * 1e6,
                  "vec64": 64 / statistics.median(vs), "batch64_us": statistics.median(bs),
                  "env_fresh_us": fresh, **means}))
"""


def _measure(tree: Path) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, check=True, capture_output=True, text=True,
                         cwd=tree)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("base", type=Path, help="the reference tree (e.g. a worktree of the previous commit)")
    ap.add_argument("new", type=Path, help="the tree under test")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds counted (default 5)")
    ap.add_argument("--json", type=Path, default=None, metavar="FILE",
                    help="also write the rounds and medians to FILE (e.g. docs/speed/compare.json)")
    args = ap.parse_args()
    import results_json

    start = results_json.context()
    trees = {"base": args.base.resolve(), "new": args.new.resolve()}
    for t in trees.values():
        _measure(t)  # warm-up: compile or load the kernels
    runs: dict[str, list[dict[str, float]]] = {"base": [], "new": []}
    for r in range(args.rounds):
        for name in ("base", "new") if r % 2 == 0 else ("new", "base"):
            runs[name].append(_measure(trees[name]))
            print(f"round {r + 1} {name}: " + ", ".join(f"{k} {v:.3f}" for k, v in runs[name][-1].items()),
                  flush=True)
    print(f"\nmedians of {args.rounds} interleaved rounds (lower is better for us, higher for /s):")
    medians: dict[str, dict[str, float]] = {"base": {}, "new": {}}
    for key, unit, better in (("step_us", "us", "lower"), ("env_us", "us", "lower"), ("vec64", "/s", "higher"),
                              ("batch64_us", "us", "lower"), ("env_fresh_us", "us", "lower"),
                              ("env_mean_us", "us", "lower"), ("env_rand_us", "us", "lower"),
                              ("env_plain_us", "us", "lower")):
        if not all(key in x for x in runs["base"] + runs["new"]):
            continue
        b = statistics.median(x[key] for x in runs["base"])
        n = statistics.median(x[key] for x in runs["new"])
        medians["base"][key], medians["new"][key] = b, n
        print(f"  {key:<8} base {b:10.3f} {unit}   new {n:10.3f} {unit}   new/base {n / b:.3f} ({better} is better)")
    if args.json:
        results_json.write(args.json, "benchmarks/compare.py", {
            "rounds": args.rounds,
            "trees": {name: {"path": str(t), "commit": results_json.commit(t)} for name, t in trees.items()},
            "medians": medians, "runs": runs}, start)


if __name__ == "__main__":
    main()
