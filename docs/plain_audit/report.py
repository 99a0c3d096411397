"""The plain-learner audit's summary and plot (docs/plain_audit.md), from the runs kept by
docs/plain_audit/run.py in docs/plain_audit/runs/<variant>/.

    python docs/plain_audit/report.py      # writes summary.json and curves.png here

Every curve point is scored against the proposed law (paper gains) on the same episodes (the
paper presets and the four held-out training-suite episodes of the curve, at the runs' level), with
``agents.sweep.score_point``: ``score_vs_law`` is the geometric mean of the law's RMSE over the
policy's, per joint and group (1: the law's tracking; a failed episode's RMSE counts as it is), and
an episode fails if it leaves its bounds once. The law's RMSEs are computed here, once, and kept
in law.json. Nothing here reads the stress suite.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from run import VARIANTS  # noqa: E402  (the variants' order and descriptions)


def _law(suite_seeds: int, level: int) -> dict[str, list[float]]:
    from agents.sweep import law_levels
    from blf_gym.results.io import atomic_write_json

    path = HERE / "law.json"
    if path.is_file():
        kept = json.loads(path.read_text())
        if kept["suite_seeds"] == suite_seeds and kept["level"] == level:
            return kept["rmse_deg"]
    law = law_levels(suite_seeds, None, "proposed", level)
    atomic_write_json(path, {"controller": "proposed", "suite_seeds": suite_seeds, "level": level, "rmse_deg": law})
    return law


def _in_bounds(point: dict, groups, duration: float) -> float:
    """The curve point's time before the first violation, s, averaged over its groups (the training
    suite's group counts its earliest episode; an episode without one counts its whole duration)."""
    return float(np.mean([duration if point[g].get("first_violation_s") is None else point[g]["first_violation_s"]
                          for g in groups]))


def summarize_runs() -> dict:
    from blf_gym.envs.protocol import CURVE_GROUPS
    from agents.sweep import score_point

    out = {"variants": []}
    law = None
    for name, (what, overrides) in VARIANTS.items():
        d = HERE / "runs" / name
        if not (d / "eval" / "curve.json").is_file():
            continue
        meta = json.loads((d / "metadata.json").read_text())
        curve = json.loads((d / "eval" / "curve.json").read_text())
        seeds = int(curve["suite_seeds"])
        level = int(curve["env_kwargs"].get("level", 3))
        law = law or _law(seeds, level)
        rows = [score_point(p, law, seeds) for p in curve["points"]]
        for r, p in zip(rows, curve["points"]):
            r["time_in_bounds_s"] = _in_bounds(p, CURVE_GROUPS, curve["env_kwargs"].get("duration") or 30.0)
            r["violating_share"] = float(np.mean([np.mean(p[g]["violation_fraction"]) for g in CURVE_GROUPS]))
        last, pts = rows[-1], curve["points"][-1]
        firsts = [pts[g]["first_violation_s"] for g in CURVE_GROUPS if pts[g].get("first_violation_s") is not None]
        out["variants"].append({
            "name": name, "what": what, "overrides": overrides, "seed": meta["seed"],
            "timesteps": meta["timesteps"], "wall_s": meta["wall_s"], "completed": meta["completed"],
            "git_commit": meta.get("git_commit"), "level": level,
            "final": {"score_vs_law": last["score_vs_law"], "failed_episodes": last["failed_episodes"],
                      "time_in_bounds_s": last["time_in_bounds_s"], "violating_share": last["violating_share"],
                      "episodes": last["episodes"], "earliest_violation_s": min(firsts) if firsts else None,
                      "rmse_deg": {g: last[g]["rmse_deg"] for g in CURVE_GROUPS}},
            "curve": [{"timesteps": r["timesteps"], "score_vs_law": r["score_vs_law"],
                       "failed_episodes": r["failed_episodes"], "time_in_bounds_s": r["time_in_bounds_s"],
                       "violating_share": r["violating_share"]}
                      for r in rows],
        })
    out["law_rmse_deg"] = law
    return out


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, c, b) = plt.subplots(1, 3, figsize=(17, 4.8))
    cmap = plt.get_cmap("tab20")
    for k, v in enumerate(summary["variants"]):
        t = np.array([p["timesteps"] for p in v["curve"]]) / 1e6
        # the candidate and the last, combined variant solid; the one-factor variants dashed
        last = k == len(summary["variants"]) - 1
        kw = {"ls": "-" if v["name"] == "base" or last else "--", "lw": 2.5 if v["name"] == "base" or last else 1.2,
              "color": cmap(k % 20), "label": v["name"]}
        a.plot(t, [p["score_vs_law"] for p in v["curve"]], **kw)
        b.plot(t, [p["violating_share"] for p in v["curve"]], **kw)
        c.plot(t, [p["time_in_bounds_s"] for p in v["curve"]], **kw)
    a.set_yscale("log")
    a.axhline(1.0, color="k", lw=0.8)
    a.set_xlabel("agent steps (millions)")
    a.set_ylabel("score_vs_law (1 = the law's tracking)")
    a.set_title("tracking against the law (presets + 4 training-suite episodes)")
    c.set_xlabel("agent steps (millions)")
    c.set_ylabel("time before the first violation (s), mean over groups")
    c.set_title("how far into the episode the policy keeps its bounds")
    b.set_xlabel("agent steps (millions)")
    b.set_ylabel("share of 1 ms samples outside the bounds")
    b.set_title("share of samples outside the bounds")
    b.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    from blf_gym.results.io import atomic_write_json

    summary = summarize_runs()
    if not summary["variants"]:
        print("no kept runs in docs/plain_audit/runs; run docs/plain_audit/run.py first")
        return 1
    atomic_write_json(HERE / "summary.json", summary)
    plot(summary, HERE / "curves.png")
    print(f"wrote {HERE / 'summary.json'} and {HERE / 'curves.png'} ({len(summary['variants'])} variants)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
