"""An rl-zoo3 run as a blf-eval agent, so that it is scored by ``score_vs_law`` on the protocol
instead of by rl-zoo3's own evaluation reward (``enjoy`` prints the episode reward of whatever
reward the env was made with, which is no benchmark figure):

    python -m rl_zoo3.train --algo ppo --env PlanarBLFResidual-v0 --gym-packages blf_gym \\
        --conf-file agents/configs/zoo/ppo.yml -f logs ...
    python -m agents.zoo logs/ppo/PlanarBLFResidual-v0_1 --out runs/zoo_ppo
    blf-eval --agents runs/zoo_ppo

The command reads the run's model (``<env id>.zip``, or ``best_model.zip`` with ``--best``), its
``<env id>/config.yml`` (the training env kwargs and whether observations were normalized),
``<env id>/args.yml`` (algorithm, env id, seed and any ``--env-kwargs`` given on the command line,
which replace the file's) and ``<env id>/vecnormalize.pkl``, and writes a folder that
:func:`agents.loading.load_agent` checks like any ``blf-train`` run: ``metadata.json`` (with
``source: rl-zoo3`` and the run's path), ``model.zip`` and, when the run normalized observations,
``vecnormalize.pkl``. The folder is checked before the command reports success.
"""

from __future__ import annotations

import argparse
import ast
import json
import shutil
import sys
from pathlib import Path
from typing import Any

from blf_gym import ENV_IDS
from blf_gym.results.io import atomic_write_text, os_error_message

__all__ = ["convert"]


def _yaml(path: Path) -> dict[str, Any]:
    """rl-zoo3's yaml files: a mapping, or a list of [key, value] pairs (config.yml)."""
    import yaml

    if not path.is_file():
        raise ValueError(f"{path}: not found; give the folder of one rl-zoo3 run (e.g. logs/ppo/<env id>_1)")
    data = yaml.unsafe_load(path.read_text())  # rl-zoo3 writes python objects (OrderedDict) with tags
    return dict(data) if data is not None else {}


def _normalizes_observations(value: Any) -> bool:
    """rl-zoo3's ``normalize`` hyperparameter: a bool, or a dict (or its string) of VecNormalize's
    keyword arguments."""
    if isinstance(value, str):
        value = ast.literal_eval(value) if value.strip().startswith("{") else value.strip().lower() == "true"
    if isinstance(value, dict):
        return bool(value.get("norm_obs", True))
    return bool(value)


def convert(run: str | Path, out: str | Path, best: bool = False, name: str | None = None) -> Path:
    """Write the blf-eval agent folder ``out`` for the rl-zoo3 run folder ``run`` (module docstring)
    and check it with :func:`agents.loading.check_agent_folder`; returns ``out``."""
    run, out = Path(run), Path(out)
    args = _yaml(next(iter(sorted(run.glob("*/args.yml"))), run / "args.yml"))
    env_id = args.get("env")
    if env_id not in ENV_IDS.values():
        raise ValueError(f"{run}: args.yml: env {env_id!r} is not a PlanarBLF id ({sorted(ENV_IDS.values())})")
    sub = run / env_id
    config = _yaml(sub / "config.yml")
    env_kwargs = dict(args.get("env_kwargs") or config.get("env_kwargs") or {})
    mode = "residual" if env_id == ENV_IDS["residual"] or env_kwargs.get("controller") not in (None, "none") \
        else "plain"
    if mode == "residual":
        env_kwargs.setdefault("controller", "proposed")  # what the residual id builds
    model = run / ("best_model.zip" if best else f"{env_id}.zip")
    if not model.is_file():
        raise ValueError(f"{model}: not found" + ("" if best else " (give --best for best_model.zip)"))
    normalize = _normalizes_observations(config.get("normalize", False))
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(model, out / "model.zip")
    if normalize:
        stats = sub / "vecnormalize.pkl"
        if not stats.is_file():
            raise ValueError(f"{stats}: not found, but config.yml says the run normalized observations")
        shutil.copyfile(stats, out / "vecnormalize.pkl")
    elif (out / "vecnormalize.pkl").exists():
        (out / "vecnormalize.pkl").unlink()
    meta = {"name": name or f"zoo_{args.get('algo', 'agent')}_{env_id}_s{args.get('seed', 0)}",
            "algo": args.get("algo"), "mode": mode, "env_id": ENV_IDS[mode], "env_kwargs": env_kwargs,
            "seed": args.get("seed"), "config": {"normalize": normalize}, "source": "rl-zoo3",
            "zoo_run": str(run.resolve()), "zoo_model": model.name}
    from .loading import file_hashes

    meta["files"] = file_hashes(out)
    atomic_write_text(out / "metadata.json", json.dumps(meta, indent=1, default=str))
    from .loading import check_agent_folder

    check_agent_folder(out)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m agents.zoo",
                                 description="Turn an rl-zoo3 run into a folder that blf-eval --agents scores.")
    ap.add_argument("run", help="the rl-zoo3 run folder, e.g. logs/ppo/PlanarBLFResidual-v0_1")
    ap.add_argument("--out", required=True, help="the agent folder to write")
    ap.add_argument("--best", action="store_true", help="take best_model.zip instead of the final model")
    ap.add_argument("--name", default=None, help="the agent's name in blf-eval's tables")
    a = ap.parse_args(argv)
    try:
        out = convert(a.run, a.out, a.best, a.name)
    except ValueError as e:
        print(f"python -m agents.zoo: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # an --out that is a file, a full disk, a read-only folder
        print(f"python -m agents.zoo: error: {os_error_message(e, a.out)}", file=sys.stderr)
        return 2
    print(f"wrote {out}; score it with: blf-eval --agents {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
