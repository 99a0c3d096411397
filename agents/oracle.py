"""``python -m agents.oracle``: how much can a residual over the LESO-BLF law gain at all?

A residual agent sees the same outputs as the law, so a useful upper reference is a residual that
knows what the law cannot: the *true* lumped disturbance. At every agent step this oracle reads
the privileged x3 (docs/model.md section 1) and the LESO's x3_hat from ``info`` and holds

    u_residual = -M(q) (x3 - x3_hat)

for the next control period, which cancels the observer's disturbance error at the sampling
instants (the law already applies -M x3_hat). Whatever this oracle cannot remove (the error
that changes within a period, and the part not caused by the disturbance estimate) a learned
residual with output feedback cannot remove either, short of predicting it. The script prints
the oracle's RMSE beside the law's for each control period, per joint, on the given scenarios.

Example::

    python -m agents.oracle --control-periods 0.01 0.002 --suite-seeds 4
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

import numpy as np

from blf_gym.results.io import help_text
from blf_gym.model.params import PRESETS

__all__ = ["main", "oracle_rmse"]


def oracle_rmse(scenarios, control_period: float = 0.01, oracle: bool = True,
                residual_scale: float = 100.0) -> np.ndarray:
    """Pooled RMSE (deg, per joint) of the law plus the oracle residual (or a zero residual) over
    ``scenarios``, all stepped together in one batched env."""
    from blf_gym.envs.envcore import EnvCore
    from blf_gym.model.dynamics import mass_matrix
    from blf_gym.results.metrics import summarize

    core = EnvCore(len(scenarios), controller="proposed", residual_scale=residual_scale, reward_weights={},
                   control_period=control_period, record=True, terminate_on_violation=False, threads=1)
    for i in range(len(scenarios)):
        core.rngs[i] = np.random.default_rng(10_000 + i)
    core.reset_envs(range(len(scenarios)), scenarios=list(scenarios))
    steps = int(round(scenarios[0].sim.duration / control_period))
    a = np.zeros((len(scenarios), core.n))
    info = None
    for _ in range(steps):
        if oracle and info is not None:
            for i in range(len(scenarios)):
                M = mass_matrix(core.loop.X[i, : core.n], scenarios[i].arm)
                a[i] = -M @ (info["x3"][i] - info["x3_hat"][i]) / residual_scale
        _, _, _, _, info = core.step(np.clip(a, -1.0, 1.0))
    rec = summarize([core.trajectory(i) for i in range(len(scenarios))], "oracle", "residual", "x",
                    scenarios[0].sim.dt)
    return np.asarray(rec["rmse_deg"])


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agents.oracle", description=help_text(__doc__),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--control-periods", type=float, nargs="+", default=[0.01, 0.005, 0.002])
    p.add_argument("--suite-seeds", type=int, default=4, help="held-out randomized-suite episodes")
    args = p.parse_args(argv)
    from .evaluate import build_scenarios

    try:
        groups = build_scenarios(list(PRESETS), args.suite_seeds, {}, None)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    n = groups[0][1][0].arm.n_links if groups and groups[0][1] else 0
    print(f"RMSE (deg, joints {' '.join(str(j + 1) for j in range(n))}); ratio = oracle / law (below 1: the "
          "oracle helps)")
    for label, scs in groups:
        law = oracle_rmse(scs, 0.01, oracle=False)
        print(f"\n{label}: law alone {' '.join(f'{v:.4f}' for v in law)}")
        for cp in args.control_periods:
            orc = oracle_rmse(scs, cp)
            print(f"  oracle, control period {cp * 1e3:4.1f} ms: {' '.join(f'{v:.4f}' for v in orc)}   "
                  f"ratio {' '.join(f'{v:.3f}' for v in orc / law)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
