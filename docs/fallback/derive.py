"""The look-ahead hand-back's two numbers, from the training suite only (docs/model.md section 11,
"The look-ahead hand-back"; blf_gym.envs.lookahead):

* ``horizon_s``: how long the law alone takes to shrink a difference of state a hundredfold. Each
  of 16 training-suite draws is run twice by the law alone, noise-free, from the reference and
  from an initial error of 0.01 rad on every joint; the first time |e1 - e1'| (largest over joints)
  falls below 1 % of its start is read per draw; the horizon is the largest, rounded up to 50 ms.
  The difference does not vanish afterwards: friction's and the dead-zone's switching leave a
  floor, which later events (folds, force steps) can amplify; its largest value after the horizon
  is reported (``after_horizon_max_rad``; ``after_horizon_where_stressed_max_rad`` where the law
  uses more than half of a bound), since the guarantee holds only up to it.
* ``demand_star``: the smallest reference demand (``blf_gym.envs.lookahead.reference_demand``) found
  within ``horizon`` before a sample where the law alone, on 80 training-suite draws, used more
  than half of a bound's width (normalized margin below 0.5, the barrier filter's m1), leaving out
  the second after a force step (which no look-ahead foresees).

    python docs/fallback/derive.py          # writes docs/fallback/derive.json (about 2 min)

The draws come from generators seeded 0-79 (the training suite's own; the held-out episodes use
seeds from 10,000, the stress suite 20,000, the certificate cases 30,000).
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from blf_gym.results.io import atomic_write_json
from blf_gym.envs.lookahead import reference_demand
from blf_gym.results.metrics import provenance
from blf_gym.envs.scenarios import sample_suite
from blf_gym.kernel.simulate import simulate_batch

OUT = Path(__file__).with_name("derive.json")
DRAWS, PAIRS, DELTA, M1 = 80, 16, 0.01, 0.5


def _margin(tr) -> tuple[np.ndarray, np.ndarray]:
    s = tr.signals
    t, e = np.asarray(s["t"]), np.asarray(s["e1"])
    ka, kb = np.asarray(s["k_a"]).reshape(len(t), -1), np.asarray(s["k_b"]).reshape(len(t), -1)
    return t, np.where(e >= 0, (ka - e) / ka, (kb + e) / kb).min(axis=1)


def main() -> int:
    scs = [sample_suite(np.random.default_rng(s)) for s in range(DRAWS)]
    # the horizon: a hundredfold decay of a difference of state under the law alone
    base = [replace(sc, initial_error=(0.0,) * 3) for sc in scs[:PAIRS]]
    moved = [replace(sc, initial_error=(DELTA,) * 3) for sc in scs[:PAIRS]]
    trs = simulate_batch(base + moved, "proposed")
    t100, floor, margins = [], [], []
    for a, b in zip(trs[:PAIRS], trs[PAIRS:]):
        t = np.asarray(a.signals["t"])
        d = np.abs(np.asarray(a.signals["e1"]) - np.asarray(b.signals["e1"])).max(axis=1)
        below = np.flatnonzero(d <= 0.01 * DELTA)
        t100.append(float(t[below[0]]) if len(below) else float("inf"))
        floor.append(d)
        margins.append(_margin(a)[1])
    horizon = math.ceil(max(t100) / 0.05 - 1e-9) * 0.05
    # what is left after it: friction and the dead-zone keep a floor that events can amplify
    late = np.asarray(trs[0].signals["t"]) >= horizon
    rest = [float(np.max(d[late])) for d in floor]
    stress_diff = [float(np.max(d[late & (m < M1)], initial=0.0)) for d, m in zip(floor, margins)]
    # the demand: the smallest one found within the horizon before the law's stressed samples
    law = simulate_batch(scs, "proposed")
    found = []
    for sc, tr in zip(scs, law):
        t, m = _margin(tr)
        dt = float(t[1] - t[0])
        D = reference_demand(t, sc)
        w = int(round(horizon / dt))
        back = np.array([D[max(0, i - w): i + 1].max() for i in range(len(t))])
        onset = sc.force.onset
        stressed = (m < M1) & ~((t >= onset) & (t <= onset + 1.0))
        if stressed.any():
            i = np.flatnonzero(stressed)[np.argmin(back[stressed])]
            found.append({"draw": scs.index(sc), "frequency": sc.reference.frequency, "t": float(t[i]),
                          "margin": float(m[i]), "demand": float(back[i])})
    star = min(f["demand"] for f in found)
    report = {"horizon_s": horizon, "t100_s": t100, "after_horizon_max_rad": rest,
              "after_horizon_where_stressed_max_rad": stress_diff, "demand_star": star, "stressed_draws": len(found),
              "draws": DRAWS, "pairs": PAIRS, "delta_rad": DELTA, "m1": M1, "per_draw": found,
              "provenance": provenance(" ".join(["python", *sys.argv]))}
    atomic_write_json(OUT, report)
    print(f"horizon {horizon:.2f} s (slowest hundredfold decay {max(t100):.3f} s over {PAIRS} draws; "
          f"afterwards at most {max(rest):.1e} rad, "
          f"{max(stress_diff):.1e} where the law used over half a bound); "
          f"demand* {star:.1f} 1/s^2 ({len(found)} of {DRAWS} draws stressed); wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
