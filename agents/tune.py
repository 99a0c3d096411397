"""``blf-tune`` (also ``python -m agents.tune``): several fixed configs x seeds, as a grid sweep.

A thin alias of ``blf-sweep`` (docs/sweeps.md): the candidate ``blf-train`` config files become
``space: {config: {grid: [...]}}`` of a grid sweep with the given seeds and budget, run on Ray
Tune (local by default). Runs are named ``<config stem>_s<seed>``, scored and ranked by the sweep's
objective (``score_vs_law`` on the learning curve's last point; a failed episode loses), and the
table is ``OUT/sweep.md`` / ``OUT/sweep.json``. Needs the sweep extra (``pip install
"blf-gym[sweep]"``). Re-running the same command resumes.

Examples::

    blf-tune docs/tuning/configs/*.yaml --algo ppo --timesteps 300000 --out runs/tune --jobs 2
    blf-tune runs/ppo_residual.yaml --timesteps 1000000 --seeds 0 1 2 3 4 --out runs/final5
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from blf_gym.results.io import atomic_write_text, help_text

from .config import add_config_options, parse_overrides
from .sweep import law_levels, main as sweep_main  # noqa: F401 - law_levels is re-exported

__all__ = ["main", "sweep_file"]


def sweep_file(configs: Sequence[Path], algo: str, mode: str, timesteps: int, seeds: Sequence[int],
               scenario: str, jobs: int | None, overrides: Sequence[str] = ()) -> dict:
    """The grid sweep that blf-tune runs; ``overrides`` (``--set KEY=VALUE``) change every candidate."""
    files = [str(Path(c).resolve()) for c in configs]
    spec = {"name": "tune", "base": files[0], "algo": algo, "mode": mode, "scenario": scenario,
            "timesteps": timesteps, "seeds": list(seeds), "search": "grid"}
    if len(files) > 1:
        spec["space"] = {"config": {"grid": files}}
    else:
        spec["name"] = Path(files[0]).stem
    if jobs:
        spec["concurrency"] = jobs
    if overrides:
        spec["overrides"] = parse_overrides(overrides)
    return spec


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="blf-tune", description=help_text(__doc__),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("configs", nargs="+", type=Path, help="candidate blf-train config files (YAML)")
    p.add_argument("--algo", default="ppo", help="SB3 algorithm for every candidate (default ppo)")
    p.add_argument("--mode", default="residual", choices=("plain", "residual"),
                   help="plain: the action is the torque; residual: added to the proposed law (default residual)")
    p.add_argument("--timesteps", type=int, default=300_000, metavar="N",
                   help="budget per run, in agent steps (default 300000)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], metavar="S",
                   help="training seeds per candidate (default 0)")
    p.add_argument("--scenario", default="randomized", metavar="NAME",
                   help="training scenario (default randomized, the randomized suite)")
    p.add_argument("--out", type=Path, default=Path("runs/tune"), metavar="DIR",
                   help="folder for the runs, sweep.json and sweep.md (default runs/tune)")
    p.add_argument("--jobs", type=int, default=None, metavar="J",
                   help="runs trained at the same time (default one per core)")
    p.add_argument("--address", default=None, metavar="ADDRESS",
                   help="an existing Ray cluster (default: a local Ray instance)")
    add_config_options(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    import yaml

    args = _parser().parse_args(argv)
    if args.jobs is not None and args.jobs < 1:
        print("blf-tune: error: --jobs must be >= 1", file=sys.stderr)
        return 2
    missing = [str(c) for c in args.configs if not c.is_file()]
    if missing:
        print(f"blf-tune: error: config not found: {', '.join(missing)}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "tune_sweep.yaml"
    try:
        spec = sweep_file(args.configs, args.algo, args.mode, args.timesteps, args.seeds, args.scenario, args.jobs,
                          args.overrides)
    except ValueError as exc:
        print(f"blf-tune: error: {exc}", file=sys.stderr)
        return 2
    atomic_write_text(path, yaml.safe_dump(spec, sort_keys=False))
    rest = ["--out", str(args.out)] + (["--address", args.address] if args.address else [])
    return sweep_main([str(path), *rest])


if __name__ == "__main__":
    raise SystemExit(main())
