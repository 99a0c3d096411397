"""examples/cleanrl_ppo.py, the CleanRL-style single-file PPO on Gymnasium 1.x: it runs, reads each
finished episode from final_info as a dict of arrays, and the same seed gives the same run."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("cleanrl_ppo", ROOT / "examples" / "cleanrl_ppo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ARGS = ["--num-envs", "2", "--num-steps", "50", "--total-timesteps", "200", "--duration", "0.2",
        "--update-epochs", "2", "--num-minibatches", "2"]


def test_it_trains_and_records_every_finished_episode_with_the_envs_metrics(tmp_path):
    mod = _script()
    out = mod.train(mod.parse_args([*ARGS, "--out", str(tmp_path)]))
    assert out["steps"] == 200 and len(out["losses"]) == 2 and all(math.isfinite(x) for x in out["losses"])
    # 20-step episodes (0.2 s of 10 ms steps), 100 steps per env: 5 episodes per env, all truncated
    eps = out["episodes"]
    assert len(eps) == 10
    assert all(e["length"] == 20 and e["ended"] == "time_limit" and len(e["rmse_deg"]) == 3 for e in eps)
    assert all(math.isfinite(e["return"]) for e in eps)
    assert (tmp_path / "model.pt").is_file() and (tmp_path / "summary.json").is_file()


def test_the_same_seed_gives_the_same_run():
    mod = _script()
    a = mod.train(mod.parse_args(ARGS))
    b = mod.train(mod.parse_args(ARGS))
    assert a["losses"] == b["losses"] and [e["return"] for e in a["episodes"]] == [e["return"] for e in b["episodes"]]
    c = mod.train(mod.parse_args([*ARGS, "--seed", "1"]))
    assert c["losses"] != a["losses"]
