"""The proposed law on every member of the task family (docs/family.md, "The law on each member"):
its gains carried from the paper's arm (baselines.params), with the LESO, on the member's two
presets and eight training-suite draws (training seeds 0-7; no held-out episode is read), whole
30 s episodes, violations counted rather than ended. Writes docs/family/law.json atomically, with
what produced it.

    python docs/family/run.py [--links 2 3 4 5 6 7] [--out docs/family/law.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from blf_gym.envs.scenarios import sample_suite
from blf_gym.kernel.simulate import simulate_batch
from blf_gym.model.family import FAMILY_LINKS, family_arm, family_base, family_preset, family_presets
from blf_gym.envs.envcore import named_block
from blf_gym.results.io import atomic_write_text
from blf_gym.results.metrics import episode_stats, provenance

DRAWS = 8
"""Training-suite draws per member (training seeds 0 .. DRAWS - 1)."""


def member(n: int) -> list[dict]:
    """One record per episode of the n-link member: scenario, RMSE per joint (deg), the largest
    |u| per joint (N m), violating 1 ms samples, divergence."""
    arm = family_arm(n)
    law, obs = named_block("run.py:", "controller", "proposed", arm), named_block("run.py:", "observer", "leso", arm)
    scs = [family_preset(p) for p in family_presets(n)]
    scs += [sample_suite(np.random.default_rng(k), family_base(n), "randomized") for k in range(DRAWS)]
    labels = list(family_presets(n)) + [f"randomized/{k}" for k in range(DRAWS)]
    out = []
    for label, tr in zip(labels, simulate_batch(scs, law, obs, threads=1, lanes=1)):
        st = episode_stats(tr)
        out.append({"n": n, "scenario": label, "rmse_deg": [float(x) for x in st.rmse_deg],
                    "max_torque": [float(x) for x in np.abs(tr.signals["u"]).max(axis=0)],
                    "violating_samples": int(st.violating_samples), "diverged": bool(tr.diverged),
                    "K1": list(law.params.K1), "K2": list(law.params.K2)})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python docs/family/run.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--links", type=int, nargs="+", default=list(FAMILY_LINKS), help="members (default: all)")
    ap.add_argument("--out", type=Path, default=Path(__file__).with_name("law.json"), help="the results file")
    args = ap.parse_args(argv)
    records = []
    for n in args.links:
        records += member(n)
        print(f"n = {n}: {sum(r['violating_samples'] > 0 for r in records if r['n'] == n)} of "
              f"{sum(r['n'] == n for r in records)} episodes break a bound", flush=True)
    atomic_write_text(args.out, json.dumps({"provenance": provenance("python docs/family/run.py " + " ".join(
        sys.argv[1:] if argv is None else argv)), "draws": DRAWS, "records": records}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
