"""``blf-curves`` (also ``python -m agents.curves``): plot learning curves of ``blf-train`` runs.

Reads each run's ``eval/curve.json`` (RMSE and violations of the deterministic policy, every
``eval_freq`` steps, on both paper presets and held-out randomized-suite episodes) and draws one
panel per scenario group and joint: RMSE against training steps, one line per run (seed), with the
proposed law's level on the same scenarios as a dashed line. A last row counts violating samples.

Example::

    blf-curves runs/final/sac_s0 runs/final/sac_s1 runs/final/sac_s2 --out docs/learning_curves.png

Without ``--out`` the figure goes to ``learning_curves.png`` in the first run's folder. For runs of
millions of steps, ``--log-steps`` puts the steps on a logarithmic axis (the point at step 0, the
untrained policy, is then drawn at half the first evaluated step and marked so), which shows whether
a learner still improves at the end; ``--log-rmse`` does the same for the RMSE, for learners whose
error is orders of magnitude above the law's.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

from blf_gym.results.io import help_text

from blf_gym.envs.protocol import CURVE_GROUPS

__all__ = ["main", "plot_curves"]


def plot_curves(runs: Sequence[Path], out: Path, law: dict[str, list[float]] | None = None,
                title: str | None = None, log_steps: bool = False, log_rmse: bool = False) -> Path:
    """Draw the curves of ``runs`` into the PNG ``out`` (written atomically) and return its path;
    ``log_steps`` and ``log_rmse`` put the steps and the RMSE on logarithmic axes (module
    docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from blf_gym.results.io import atomic_path

    curves = _read_curves(runs)
    if law is None:
        from .sweep import law_levels

        first = curves[0][1]
        law = law_levels(int(first.get("suite_seeds", 4)), first.get("env_kwargs", {}).get("duration"))
    n = len(law[CURVE_GROUPS[0]])  # joints
    cols = max(n, 2)  # a column per joint, at least two: the bottom row's legend sits in the second
    fig, axes = plt.subplots(len(CURVE_GROUPS) + 1, cols, figsize=(13 * cols / 3, 11), sharex=True)
    scale = 1.0 if log_steps else 1e3
    for name, c in curves:
        pts = c["points"]
        steps = np.array([p["timesteps"] for p in pts], dtype=float) / scale
        if log_steps and len(steps) > 1 and steps[0] == 0.0:
            steps[0] = 0.5 * steps[1]  # the untrained policy, drawn at half the first evaluated step
        for gi, g in enumerate(CURVE_GROUPS):
            rmse = np.array([p[g]["rmse_deg"] for p in pts])
            for j in range(n):
                axes[gi, j].plot(steps, rmse[:, j], marker=".", label=name)
        viol = np.array([sum(sum(p[g]["violations"]) for g in CURVE_GROUPS) for p in pts])
        axes[-1, 0].plot(steps, viol, marker=".", label=name)
    for gi, g in enumerate(CURVE_GROUPS):
        for j in range(n):
            ax = axes[gi, j]
            ax.axhline(law[g][j], color="k", ls="--", lw=1.2, label="proposed law")
            ax.set_title(f"{g}, joint {j + 1}", fontsize=9)
            ax.set_ylabel("RMSE (deg)")
            if log_rmse:
                ax.set_yscale("log")
            else:
                ax.ticklabel_format(axis="y", style="plain", useOffset=False)
            if log_steps:
                ax.set_xscale("log")
            ax.grid(alpha=0.3)
    for gi in range(len(CURVE_GROUPS)):
        for j in range(n, cols):  # a single joint leaves the second column of the curves' rows empty
            axes[gi, j].axis("off")
    axes[-1, 0].axhline(0, color="k", ls="--", lw=1.2, label="proposed law")
    axes[-1, 0].set_ylabel("violating samples\n(all scenarios)")
    axes[-1, 0].grid(alpha=0.3)
    for j in range(1, axes.shape[1]):
        axes[-1, j].axis("off")
    if log_steps:
        from matplotlib.ticker import NullFormatter

        axes[-1, 0].set_xscale("log")
        axes[-1, 0].set_yscale("symlog", linthresh=1.0)
        axes[-1, 0].set_ylim(bottom=0.0)
        for ax in axes.flat:  # label the decades only: matplotlib's minor labels overlap on a short span
            ax.xaxis.set_minor_formatter(NullFormatter())
    for j in range(axes.shape[1]):
        axes[-1, j].set_xlabel("training steps (log; step 0 drawn at half the first evaluation)" if log_steps
                               else "training steps (thousands)")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    axes[-1, 1].legend(handles, labels, loc="center", fontsize=9)
    fig.suptitle(title or "Learning curves: deterministic policy, blf-eval metrics", fontsize=11)
    fig.tight_layout()
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
    return out


def _read_curves(runs: Sequence[Path]) -> list[tuple[str, dict]]:
    """(run name, its curve.json) of each run; ValueError if one has none or they were scored on
    different scenarios."""
    curves = []
    for run in runs:
        path = Path(run) / "eval" / "curve.json"
        if not path.is_file() and (Path(run) / "curve.json").is_file():
            path = Path(run) / "curve.json"  # a run's record as kept in docs/ (docs/budget/runs/NAME)
        if not path.is_file():
            raise ValueError(f"{run}: no eval/curve.json (was it trained by blf-train?)")
        curves.append((Path(run).name, json.loads(path.read_text())))
    scoring = {(c.get("suite_seeds", 4), c.get("env_kwargs", {}).get("duration")) for _, c in curves}
    if len(scoring) > 1:
        raise ValueError("the runs' curves were scored on different scenarios (curve_suite_seeds or "
                         f"duration differ: {sorted(scoring, key=str)}); plot them separately")
    return curves


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-curves", description=help_text(__doc__),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path, help="run folders written by blf-train")
    p.add_argument("--out", type=Path, default=None, metavar="PNG",
                   help="PNG to write (default: learning_curves.png in the first run's folder)")
    p.add_argument("--title", default=None,
                   help="figure title (default: 'Learning curves: deterministic policy, blf-eval metrics')")
    p.add_argument("--log-steps", action="store_true",
                   help="training steps on a logarithmic axis (for long runs; off by default)")
    p.add_argument("--log-rmse", action="store_true", help="RMSE on a logarithmic axis (off by default)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    out = args.out if args.out is not None else args.runs[0] / "learning_curves.png"
    try:
        path = plot_curves(args.runs, out, title=args.title, log_steps=args.log_steps, log_rmse=args.log_rmse)
    except ValueError as exc:
        print(f"blf-curves: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        from blf_gym.results.io import os_error_message

        print(f"blf-curves: error: {os_error_message(exc, out)}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
