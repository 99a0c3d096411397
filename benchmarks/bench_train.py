"""Where a training run's time goes: env, policy inference, update, learning-curve evaluation, the rest.

Trains with ``agents.train.train`` (the same code as ``blf-train``) and times, by wrapping them in
this process only:

* ``env``: the SB3 adapter's ``step_wait`` and ``reset`` (the native vector env, all arms);
* ``normalize``: VecNormalize around it (its ``step_wait`` less the calls inside it);
* ``inference``: the policy's forward pass while collecting rollouts (``ActorCriticPolicy.forward``;
  off-policy algorithms' ``predict``);
* ``update``: the algorithm's ``train()`` (the gradient steps);
* ``curves``: the learning-curve evaluations (``blf_gym.results.metrics.summarize`` of their episodes);
* ``bookkeeping``: on-policy rollouts (``collect_rollouts``) less the env, normalization and
  inference: the rollout buffer, tensor conversions, callbacks (checkpoints) and GAE;
* ``rest``: the wall time less all of the above (logging, set-up, saving).

Each figure is exclusive: a timed call's time less that of the timed calls inside it. Prints
seconds, shares and end-to-end agent steps/s. Measure alone: two runs at once share the
two cores.

Run:  python benchmarks/bench_train.py [--algo ppo] [--mode residual] [--timesteps 65536]
                                       [--config FILE] [--set KEY=VALUE ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path

TIMES: dict[str, float] = defaultdict(float)
"""Exclusive wall time per key: a timed call's time less that of the timed calls inside it."""
_STACK: list[list[float]] = []  # per open timed call: [time spent in timed calls inside it]


def _timed(owner, name: str, key: str) -> None:
    """Wrap ``owner.name`` so that its exclusive wall time adds to TIMES[key]."""
    inner = getattr(owner, name)

    def wrapper(*args, **kwargs):
        _STACK.append([0.0])
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            dt = time.perf_counter() - t0
            nested = _STACK.pop()[0]
            TIMES[key] += dt - nested
            if _STACK:
                _STACK[-1][0] += dt

    setattr(owner, name, wrapper)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--algo", default="ppo", help="a registered algorithm (default ppo)")
    p.add_argument("--mode", default="residual", help="plain or residual (default residual)")
    p.add_argument("--timesteps", type=int, default=65_536, help="agent steps (default 65536)")
    p.add_argument("--config", type=Path, default=None,
                   help="a config YAML, as blf-train's --config (default: the algorithm's shipped config)")
    p.add_argument("--set", action="append", default=[], dest="overrides", metavar="KEY=VALUE",
                   help="config overrides, as blf-train's --set (default: the shipped config as it is)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here (default: print only)")
    args = p.parse_args()

    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
    from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy
    from stable_baselines3.common.vec_env import VecNormalize

    import torch

    import blf_gym.results.metrics
    from agents.loading import algorithm_class
    from agents.train import train
    from agents.vec_env import BLFVecEnv

    _timed(BLFVecEnv, "step_wait", "env")
    _timed(BLFVecEnv, "reset", "env")
    _timed(VecNormalize, "step_wait", "normalize")
    _timed(ActorCriticPolicy, "forward", "inference")
    cls = algorithm_class(args.algo)
    _timed(cls, "train", "update")
    if issubclass(cls, OffPolicyAlgorithm):
        _timed(BasePolicy, "predict", "inference")
    assert issubclass(cls, (OnPolicyAlgorithm, OffPolicyAlgorithm))
    _timed(blf_gym.results.metrics, "summarize", "curves")  # it consumes agent_episodes' generator
    if issubclass(cls, OnPolicyAlgorithm):
        _timed(OnPolicyAlgorithm, "collect_rollouts", "rollouts")

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        out = train(algo=args.algo, mode=args.mode, timesteps=args.timesteps, out=Path(tmp) / "run", progress=False,
                    config=args.config, overrides=args.overrides, scenario="randomized")
        wall = time.perf_counter() - t0
        meta = json.loads((out / "metadata.json").read_text())
    steps = int(meta["timesteps"])
    rows = {k: TIMES[k] for k in ("env", "normalize", "inference", "update", "curves")}
    rows["bookkeeping"] = TIMES["rollouts"]
    rows["rest"] = wall - sum(rows.values())
    print(f"{args.algo} {args.mode}, {steps} agent steps in {wall:.1f} s: {steps / wall:,.0f} agent steps/s end to end"
          f" ({steps / (wall - rows['curves']):,.0f} /s without the learning-curve evaluations)")
    for k, v in rows.items():
        print(f"  {k:10s} {v:8.1f} s  {100 * v / wall:5.1f} %")
    if args.json:
        args.json.write_text(json.dumps({"algo": args.algo, "mode": args.mode, "steps": steps, "wall_s": wall,
                                         "overrides": args.overrides, "seconds": rows,
                                         "threads": {"torch": torch.get_num_threads(),
                                                     "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")},
                                         "config": meta.get("config")}, indent=1))


if __name__ == "__main__":
    main()
