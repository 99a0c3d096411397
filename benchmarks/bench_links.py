"""The closed loop's cost per arm-step against the number of links (docs/family.md, "Cost against n").

For each member of the task family: the proposed law with its carried gains and the LESO on the
member's 0.1 Hz preset, one arm on one thread (the one-lane build), ``--steps`` ODE3 steps per
compiled call; the figure is the minimum over ``--repeats`` calls of the wall time per step (the
minimum, not the median: what the code costs, without what else ran on the machine). The model's
parts are O(n^2) (the mass matrix, its LDL factor and solve, the Coriolis product), with O(n)
parts beside them, so the fit is t(n) = a + b n + c n^2 by least squares, and the log-log slope
between the smallest and the largest n is printed with it.

    python benchmarks/bench_links.py [--steps 20000] [--repeats 9] [--json docs/speed/links.json]
                                     [--plot docs/family/cost.png]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from blf_gym.kernel.simulate import ClosedLoop
from blf_gym.model.family import FAMILY_LINKS, family_arm, family_preset, family_presets
from blf_gym.envs.envcore import named_block
from blf_gym.results.io import atomic_write_text
from blf_gym.results.metrics import provenance


def per_step(n: int, steps: int, repeats: int) -> float:
    """The n-link member's minimum wall time per arm-step, s."""
    arm = family_arm(n)
    loop = ClosedLoop([family_preset(family_presets(n)[0])], named_block("bench_links:", "controller", "proposed", arm),
                      named_block("bench_links:", "observer", "leso", arm), threads=1, lanes=1)
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        loop.advance(steps, record_samples=0)
        best = min(best, (time.perf_counter() - t) / steps)
    return float(best)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/bench_links.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=20000, help="ODE3 steps per timed call (default 20000: 2 s)")
    ap.add_argument("--repeats", type=int, default=9, help="timed calls per member; the minimum is kept")
    ap.add_argument("--json", type=Path, default=None, help="write the figures and the fit here")
    ap.add_argument("--plot", type=Path, default=None, help="write the cost against n here (PNG)")
    args = ap.parse_args(argv)
    ns = list(FAMILY_LINKS)
    us = []
    for n in ns:
        us.append(per_step(n, args.steps, args.repeats) * 1e6)
        print(f"n = {n}: {us[-1]:.3f} us per arm-step", flush=True)
    x, y = np.asarray(ns, dtype=float), np.asarray(us)
    coef = np.linalg.lstsq(np.stack([np.ones_like(x), x, x * x], axis=1), y, rcond=None)[0]
    slope = float(np.log(y[-1] / y[0]) / np.log(x[-1] / x[0]))
    print(f"fit: t(n) = {coef[0]:.3f} + {coef[1]:.3f} n + {coef[2]:.4f} n^2 us; log-log slope {slope:.2f}")
    if args.json:
        atomic_write_text(args.json, json.dumps({"provenance": provenance("python benchmarks/bench_links.py"),
                                                 "steps": args.steps, "repeats": args.repeats, "n": ns,
                                                 "us_per_arm_step": us, "fit_a_b_c": [float(c) for c in coef],
                                                 "loglog_slope": slope}, indent=1) + "\n")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3.4))
        fine = np.linspace(x[0], x[-1], 100)
        ax.plot(x, y, "o", label="measured (minimum of repeats)")
        ax.plot(fine, coef[0] + coef[1] * fine + coef[2] * fine ** 2, "-", lw=1, label="a + b n + c n$^2$ fit")
        ax.set_xlabel("links n")
        ax.set_ylabel("us per arm-step (ODE3, 0.1 ms)")
        ax.set_title("Closed loop's cost against n (one arm, one thread)", fontsize=9)
        ax.legend(fontsize=8)
        fig.tight_layout()
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.plot.with_name(f".{args.plot.name}.tmp.png")
        fig.savefig(tmp, dpi=120)
        tmp.replace(args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
