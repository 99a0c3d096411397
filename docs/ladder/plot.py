"""The ladder's figure (docs/levels.md, "The ladder"): each policy's IQM ``score_vs_law`` with its 95 %
interval by difficulty level, on the training suite's and the stress suite's held-out episodes,
from docs/ladder/L<level>/report.json (docs/ladder/eval.sh).

    python docs/ladder/plot.py      # writes docs/ladder/ladder.png
"""

from __future__ import annotations

import json
from pathlib import Path


HERE = Path(__file__).resolve().parent
ROWS = (("law, paper gains", "proposed"), ("law, tuned", "proposed_tuned"), ("PPC", "ppc"), ("floor", "floor"),
        ("residual over tuned law", "ppo_residual_tuned"), ("plain PPO 2M", "ppo_L{level}"),
        ("plain SAC 2M", "sac_L{level}"), ("plain PPO 20M", "ppo_long_L{level}"),
        ("plain PPO 2M, benchmark reward", "ppo_bench_L{level}"))


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), sharey=True)
    for ax, group, title in zip(axes, ("randomized", "stress"), ("training suite (20 held-out)", "stress (50)")):
        for k, (label, policy) in enumerate(ROWS):
            xs, ys, lo, hi = [], [], [], []
            for level in range(4):
                path = HERE / f"L{level}" / "report.json"
                if not path.is_file():
                    continue
                tag = "" if level == 3 else f"@L{level}"
                st = next((x for x in json.loads(path.read_text())["statistics"]
                           if x["policy"] == policy.format(level=level) and x["scenario"] == group + tag), None)
                if st is None:
                    continue
                # a log axis: values below 1e-6 are drawn at 1e-6
                y, a, b = (max(v, 1e-6) for v in (st["iqm"], *st["ci95"]))
                xs.append(level + 0.06 * (k - len(ROWS) / 2))
                ys.append(y)
                lo.append(max(y - a, 0.0))
                hi.append(max(b - y, 0.0))
            if xs:
                ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", ms=4, capsize=2, label=label, lw=1.0)
        ax.set_yscale("log")
        ax.axhline(1.0, color="k", lw=0.6)
        ax.axhline(0.5, color="k", lw=0.6, ls=":")
        ax.set_xticks(range(4), ["L0 nominal", "L1 uncertain-wide", "L2 no force", "L3 full"])
        ax.set_title(title)
    axes[0].set_ylabel("IQM score_vs_law (law with paper gains = 1; dotted: 1/2)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(HERE / "ladder.png", dpi=110)
    print(f"wrote {HERE / 'ladder.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
