"""A PPO-Lagrangian run's training log as a figure: episode cost against its limit and the episode
length, the multiplier, the episode return and the funnel curriculum over training, beside the
learning curve scored at the benchmark's own bounds.

    python docs/budget/training_log.py export RUN [--out FILE]   # RUN/tb/**/events* -> RUN/training_log.json
    python docs/budget/training_log.py plot LOG CURVE --out PNG

``export`` reads the run's TensorBoard events (SB3's logger, ``lagrangian/*``, ``rollout/*`` and
``curriculum/bound_scale``) and keeps those scalars as JSON, small enough for ``docs/``; ``plot``
draws from that file and the run's ``curve.json``. Each shipped figure,
``docs/budget/<run>_training.png``, was drawn from
``docs/budget/runs/<run>/{training_log.json,curve.json}``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from blf_gym.results.io import atomic_path, atomic_write_text

TAGS = ("lagrangian/mean_episode_cost", "lagrangian/cost_limit", "lagrangian/multiplier", "rollout/ep_rew_mean",
        "rollout/ep_len_mean", "curriculum/bound_scale")
"""The scalars kept: the cost the multiplier reads, its limit, the multiplier, the return, the
episode length and the curriculum's width factor."""


def export(run: Path, out: Path) -> None:
    """Keep :data:`TAGS` of ``run``'s newest TensorBoard events file as ``{tag: [[step, value], ...]}``."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted(run.glob("tb/**/events.out.tfevents.*"), key=lambda p: p.stat().st_mtime)
    if not files:
        raise SystemExit(f"training_log.py: no TensorBoard events under {run}/tb")
    acc = EventAccumulator(str(files[-1]), size_guidance={"scalars": 0})
    acc.Reload()
    have = set(acc.Tags()["scalars"])
    log = {t: [[e.step, e.value] for e in acc.Scalars(t)] for t in TAGS if t in have}
    atomic_write_text(out, json.dumps({"run": run.name, "scalars": log}, indent=1) + "\n")
    print(f"wrote {out} ({', '.join(f'{t}: {len(v)}' for t, v in log.items())})")


def plot(log_path: Path, curve_path: Path, out: Path) -> None:
    """The 2 x 2 figure of the module docstring."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = json.loads(log_path.read_text())
    s = {t: list(zip(*v)) for t, v in log["scalars"].items()}
    curve = json.loads(curve_path.read_text())["points"]
    fig, ax = plt.subplots(2, 2, figsize=(9.0, 6.4), sharex=True)
    a = ax[0][0]
    a.plot(*s["lagrangian/mean_episode_cost"], label="mean episode cost")
    a.plot(*s["lagrangian/cost_limit"], "--", color="0.4", label="cost limit")
    a.set_ylabel("violating 10 ms steps per episode")
    if "rollout/ep_len_mean" in s:
        a.plot(*s["rollout/ep_len_mean"], ":", color="tab:purple", label="mean episode length (steps)")
    a.legend(fontsize=8)
    a = ax[0][1]
    a.plot(*s["lagrangian/multiplier"], color="tab:red")
    a.set_ylabel("multiplier lambda")
    a = ax[1][0]
    a.plot(*s["rollout/ep_rew_mean"], color="tab:green", label="episode return")
    a.set_ylabel("episode return (env reward)")
    if "curriculum/bound_scale" in s:
        b = a.twinx()
        b.plot(*s["curriculum/bound_scale"], ":", color="0.3", label="bound scale")
        b.set_ylabel("curriculum: bounds' width factor")
    a = ax[1][1]
    steps = [p["timesteps"] for p in curve]
    for group, style in (("paper-0.1hz", "-"), ("paper-0.5hz", "--"), ("randomized", ":")):
        worst = [max(p[group]["rmse_deg"]) for p in curve]
        a.plot(steps, worst, style, label=group)
        div = [(x, y) for x, y, p in zip(steps, worst, curve) if p[group]["diverged"]]
        if div:
            a.plot(*zip(*div), "x", color="k", ms=4)
    a.axhline(180.0, color="0.5", lw=0.8)
    a.set_yscale("log")
    a.set_ylabel("worst-joint RMSE, benchmark bounds (deg)")
    a.legend(fontsize=8, title="x: diverged; line: 180 deg", title_fontsize=8)
    for a in ax[1]:
        a.set_xlabel("agent steps")
    fig.suptitle(f"{log['run']}: training log and learning curve", fontsize=11)
    fig.tight_layout()
    with atomic_path(out, ".png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    print(f"wrote {out}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="keep a run's training scalars as JSON")
    e.add_argument("run", type=Path, help="the run folder blf-train wrote (with tb/)")
    e.add_argument("--out", type=Path, default=None, help="the JSON to write (default RUN/training_log.json)")
    q = sub.add_parser("plot", help="draw the figure")
    q.add_argument("log", type=Path, help="a JSON that export wrote")
    q.add_argument("curve", type=Path, help="the run's curve.json (eval/curve.json in a run folder)")
    q.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = p.parse_args()
    if args.cmd == "export":
        export(args.run, args.out or args.run / "training_log.json")
    else:
        plot(args.log, args.curve, args.out)


if __name__ == "__main__":
    main()
