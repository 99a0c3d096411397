"""What a newcomer trips on, and the faults that lose work (the first hour and the bad day).

Resume and checkpoints under kills, the compile notice, help texts, readable plots and frames,
one message for a diverged reproduction, and disk errors reported as one line with exit 2.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from agents.train import main as train_main  # noqa: E402

TINY = """
n_envs: 2
normalize: true
env:
  control_period: 0.01
  residual_scale: 2.0
  duration: 0.2
hyperparams: {n_steps: 50, batch_size: 50, n_epochs: 1}
policy_kwargs:
  net_arch: [16, 16]
eval_freq: 100
checkpoint_freq: 100
curve_suite_seeds: 1
"""


def _cfg(tmp_path: Path, checkpoint_freq: int = 100) -> str:
    p = tmp_path / "tiny.yaml"
    p.write_text(TINY.replace("checkpoint_freq: 100", f"checkpoint_freq: {checkpoint_freq}"))
    return str(p)


def _meta(run: Path) -> dict:
    return json.loads((run / "metadata.json").read_text())


def _train(*args: str) -> int:
    return train_main([*args, "--no-progress"])


# ---- 1. no dead end after a short run ---------------------------------------------------------

def test_a_short_run_leaves_a_checkpoint_and_can_be_extended(tmp_path, capsys):
    run = tmp_path / "small"
    # checkpoint_freq far beyond the budget: before, such a run had no checkpoint to resume from
    assert _train("--timesteps", "100", "--config", _cfg(tmp_path, 100_000), "--out", str(run)) == 0
    assert (run / "checkpoints" / "step_100" / "model.zip").is_file()
    first = _meta(run)
    assert first["completed"] and not first["resumed"] and first["timesteps"] == 100
    # resuming a finished run without a larger budget does nothing and rewrites nothing
    capsys.readouterr()
    assert _train("--resume", "--out", str(run)) == 0
    assert "nothing to do" in capsys.readouterr().err
    assert _meta(run) == first
    # a larger --timesteps extends it, with the run's own settings and a second segment
    assert _train("--resume", "--timesteps", "200", "--out", str(run)) == 0
    meta = _meta(run)
    assert meta["timesteps"] == 200 and meta["completed"] and meta["resumed"]
    assert [s["start_timesteps"] for s in meta["segments"]] == [0, 100]
    assert meta["wall_s"] == pytest.approx(sum(s["wall_s"] for s in meta["segments"]), abs=1e-2)
    assert meta["wall_s"] > first["wall_s"]
    # an option that contradicts the run's own settings is refused by name
    assert _train("--resume", "--timesteps", "300", "--algo", "sac", "--out", str(run)) == 2
    assert "--algo sac differs" in capsys.readouterr().err


# ---- 8. checkpoints are complete sets ---------------------------------------------------------

def test_resume_skips_incomplete_checkpoints_and_says_so(tmp_path, capsys):
    run = tmp_path / "run"
    cfg = _cfg(tmp_path)
    assert _train("--timesteps", "200", "--config", cfg, "--out", str(run)) == 0
    ck = run / "checkpoints"
    assert sorted(p.name for p in ck.iterdir()) == ["step_100", "step_200"]
    # a kill between SB3's two checkpoint files: a newer loose model zip without its normalization
    shutil.copy(ck / "step_200" / "model.zip", ck / "model_300_steps.zip")
    # a kill while a set was being written, and a set that lost a file
    shutil.copytree(ck / "step_200", ck / ".partial_400_999")
    shutil.copytree(ck / "step_200", ck / "step_500")
    (ck / "step_500" / "vecnormalize.pkl").unlink()
    capsys.readouterr()
    assert _train("--resume", "--timesteps", "300", "--out", str(run)) == 0
    err = capsys.readouterr().err
    assert "model_300_steps.zip (its normalization file model_vecnormalize_300_steps.pkl is missing)" in err
    assert ".partial_400_999" in err and "step_500 (vecnormalize.pkl is missing or empty)" in err
    assert "from its checkpoint at 200 steps" in err
    assert _meta(run)["timesteps"] == 300 and _meta(run)["segments"][-1]["start_timesteps"] == 200
    assert not list(ck.glob(".partial_*"))  # the debris of the interrupted write is cleared


def test_a_checkpoint_set_appears_whole_or_not_at_all(tmp_path):
    from stable_baselines3 import PPO

    from agents.checkpoints import find_checkpoints, save_checkpoint
    from agents.vec_env import BLFVecEnv
    from stable_baselines3.common.vec_env import VecNormalize

    env = VecNormalize(BLFVecEnv(1, seed=0, threads=1, controller=None, duration=0.05))
    model = PPO("MlpPolicy", env, n_steps=16, batch_size=16, device="cpu", seed=0)

    class Boom(RuntimeError):
        pass

    def failing_save(path):  # the process "dies" after the model, before the statistics
        raise Boom

    env.save = failing_save
    with pytest.raises(Boom):
        save_checkpoint(model, tmp_path, {"wall_s_to_model": 1.0})
    assert find_checkpoints(tmp_path, normalize=True) == ([], [])  # nothing half-written is left
    del env.save
    folder = save_checkpoint(model, tmp_path, {"wall_s_to_model": 1.0})
    found, skipped = find_checkpoints(tmp_path, normalize=True)
    assert [c.model for c in found] == [folder / "model.zip"] and not skipped
    assert found[0].stats == folder / "vecnormalize.pkl" and found[0].state["wall_s_to_model"] == 1.0


# ---- 9. nothing lost across kills -------------------------------------------------------------

def test_a_point_interrupted_by_a_kill_is_evaluated_on_resume_and_wall_times_keep_rising(tmp_path):
    run = tmp_path / "run"
    assert _train("--timesteps", "200", "--config", _cfg(tmp_path), "--out", str(run)) == 0
    # as if killed while evaluating the point at 200: the checkpoint exists, the point does not,
    # and the metadata still says running
    curve = run / "eval" / "curve.json"
    c = json.loads(curve.read_text())
    c["points"] = [p for p in c["points"] if p["timesteps"] < 200]
    curve.write_text(json.dumps(c))
    meta = _meta(run)
    meta["status"], meta["completed"] = "running", False
    meta["segments"][-1]["status"] = "running"
    (run / "metadata.json").write_text(json.dumps(meta))
    assert _train("--resume", "--timesteps", "300", "--out", str(run)) == 0
    points = json.loads(curve.read_text())["points"]
    assert [p["timesteps"] for p in points] == [0, 100, 200, 300]
    walls = [p["wall_s"] for p in points]
    assert walls == sorted(walls)
    meta = _meta(run)
    assert [s["status"] for s in meta["segments"]] == ["killed", "completed"] and meta["resumed"]


def test_metadata_is_written_while_training_not_only_at_the_end(tmp_path):
    import signal
    import time

    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "agents.train", "--timesteps", "1000000", "--config",
                             _cfg(tmp_path), "--out", str(run), "--no-progress"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300  # an upper bound on the wait, generous for a loaded machine, not a timing
    while time.time() < deadline and not list((run / "checkpoints").glob("step_*")):
        time.sleep(0.3)
    assert list((run / "checkpoints").glob("step_*")), "no checkpoint within 300 s"
    time.sleep(0.5)
    proc.send_signal(signal.SIGKILL)  # no handler runs: what is on disk is all there is
    proc.wait(timeout=30)
    meta = _meta(run)
    assert meta["status"] == "running" and meta["segments"][0]["wall_s"] > 0 and meta["timesteps"] >= 100
    assert _train("--resume", "--timesteps", str(meta["timesteps"] + 100), "--out", str(run)) == 0
    after = _meta(run)
    assert after["segments"][0]["status"] == "killed" and after["wall_s"] > meta["wall_s"]


# ---- 2. the compile notice, wherever numba caches ---------------------------------------------

@pytest.mark.slow
def test_the_compile_notice_names_numba_s_real_cache_and_is_printed_once(tmp_path):
    # NUMBA_CACHE_DIR stands in for a read-only install, where numba falls back to another folder.
    # Two processes start together on an empty cache, as pytest workers, sweep trials or subprocess
    # vector envs do: each kernel is compiled and saved once (numba's cache log says which process
    # saved it); without the lock in ClosedLoop both compile it and both save it. blf-reproduce
    # builds two kernels, the bc law's and the proposed law's (its comparison row), so each process
    # may compile one while it waits for the other: the waits are counted per kernel.
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), NUMBA_DEBUG_CACHE="1")
    cmd = [sys.executable, "-m", "baselines.reproduce", "--controller", "bc", "--preset", "paper-0.1hz",
           "--duration", "0.01", "--no-progress"]
    procs = [subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=900) for p in procs]
    assert all(p.returncode == 0 for p in procs), [e[-2000:] for _, e in outs]
    notice = "compiling the closed loop for the bc law, with the leso observer, stepping one arm (first run only"
    assert any(notice in err and str(tmp_path / "cache") in err for _, err in outs)
    for law in ("bc", "proposed"):
        name = f"advance1__n3__{law}__"
        # the processes that saved the build's functions (the loop and the parts it calls): exactly one
        saved = [i for i, (out, _) in enumerate(outs)
                 if any("data saved to" in ln and name in ln for ln in out.splitlines())]
        assert len(saved) == 1, [ln for out, _ in outs for ln in out.splitlines() if "data saved to" in ln]
        wait = f"another process is compiling the closed loop for the {law} law, with the leso observer"
        waited = [i for i, (_, err) in enumerate(outs) if wait in err]
        loaded = [i for i, (out, _) in enumerate(outs)
                  if any("data loaded from" in ln and name in ln for ln in out.splitlines())]
        assert len(waited) <= 1 and set(waited) <= set(loaded)  # the one that waited loaded the other's build
    second = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0 and "compiling" not in second.stderr


# ---- 3. help texts ----------------------------------------------------------------------------

def _parsers() -> dict[str, argparse.ArgumentParser]:
    from agents import curves, evaluate, sweep, train, tune
    from baselines import reproduce

    return {"blf-train": train._parser(), "blf-eval": evaluate._parser(), "blf-tune": tune._parser(),
            "blf-reproduce": reproduce._parser(), "blf-curves": curves._parser(),
            "blf-sweep": sweep._parser()}


@pytest.mark.parametrize("name", ["blf-train", "blf-eval", "blf-tune", "blf-reproduce", "blf-curves", "blf-sweep"])
def test_every_option_has_help_and_its_default_once(name):
    parser = _parsers()[name]
    text = parser.format_help()
    assert "(default: None)" not in text
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help, f"{name} {action.option_strings or action.dest} has no help"
        if action.option_strings:
            assert action.help.count("default") == 1, f"{name} {action.option_strings}: {action.help!r}"


@pytest.mark.parametrize("name", ["blf-train", "blf-eval", "blf-tune", "blf-reproduce", "blf-curves", "blf-sweep"])
def test_help_is_plain_text_not_restructuredtext(name):
    text = _parsers()[name].format_help()
    assert "``" not in text and ":func:`" not in text and ":data:`" not in text, name


def test_blf_curves_writes_into_the_run_folder_by_default(tmp_path, capsys):
    from agents.curves import main as curves_main

    run = tmp_path / "run"
    assert _train("--timesteps", "100", "--config", _cfg(tmp_path, 100_000), "--out", str(run)) == 0
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert curves_main([str(run)]) == 0
    finally:
        os.chdir(cwd)
    assert (run / "learning_curves.png").is_file() and not (tmp_path / "learning_curves.png").exists()
    assert str(run / "learning_curves.png") in capsys.readouterr().out


def test_blf_eval_takes_a_run_folder(tmp_path, capsys):
    from agents.evaluate import load_agent, main as eval_main

    run = tmp_path / "run"
    assert _train("--timesteps", "100", "--config", _cfg(tmp_path, 100_000), "--out", str(run)) == 0
    _, meta, norm = load_agent(run)
    assert meta["name"] == "run" and norm is not None
    assert eval_main(["--controllers", "--agents", str(run), "--duration", "0.2", "--suite-seeds", "0",
                      "--no-progress"]) == 0
    assert "run " in capsys.readouterr().out
    with pytest.raises(ValueError, match="no model.zip"):
        load_agent(tmp_path)


# ---- 4. plots and frames people can read ------------------------------------------------------

def test_plain_agents_get_their_own_panel(tmp_path):
    from PIL import Image

    from agents.eval_tables import plots as _plots
    from blf_gym.results.metrics import summarize
    from blf_gym.model.params import preset
    from blf_gym.kernel.simulate import simulate

    tr = simulate(preset("paper-0.1hz", duration=0.05), "proposed")
    law = summarize([tr], "proposed", "baseline", "paper-0.1hz", 1e-4)
    plain = dict(law, policy="spinner", kind="plain")
    _plots([(law, [tr])], tmp_path / "one")
    _plots([(law, [tr]), (plain, [tr])], tmp_path / "two")
    w1 = Image.open(tmp_path / "one" / "error_paper-0.1hz.png").size[0]
    w2 = Image.open(tmp_path / "two" / "error_paper-0.1hz.png").size[0]
    assert w2 > 1.4 * w1  # a second column of panels


def test_rendered_frames_carry_units_names_and_a_scale_for_small_errors():
    import gymnasium as gym

    import blf_gym  # noqa: F401

    env = gym.make("PlanarBLFResidual-v0", render_mode="rgb_array", scenario="paper-0.5hz", duration=0.1)
    env.reset(seed=0)
    env.step(np.zeros(3, dtype=np.float32))
    frame = env.render()
    assert frame.shape == (320, 640, 3)
    r = env.unwrapped._renderer
    assert r.ax_arm.get_xlabel() == "x (m)" and r.ax_arm.get_ylabel() == "y (m)"
    title = r.ax_arm.get_title()
    assert "paper-0.5hz" in title and "proposed" in title
    assert r.ax_err.get_yscale() == "symlog"
    # on a symlog axis linear within 0.01 deg, a 0.01 deg bar spans a visible part of the axis
    lo, hi = r.ax_err.get_ylim()
    tf = r.ax_err.transScale.transform
    share = (tf((0, 0.01))[1] - tf((0, 0.0))[1]) / (tf((0, hi))[1] - tf((0, lo))[1])
    assert share > 0.03, share
    env.close()


# ---- 7. one message when the reproduction diverges --------------------------------------------

def test_the_paper_step_gives_one_message_and_a_failing_exit(capsys):
    from baselines.reproduce import main as reproduce_main

    assert reproduce_main(["--dt", "1e-3", "--duration", "0.2", "--no-progress"]) == 1
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and warnings[0].startswith("warning: all 6 cases diverged")
    assert "plain" not in warnings[0] and "dt = 0.001 s is too large" in warnings[0]
    assert "every case diverged" in err


def test_plain_mode_divergence_blames_the_actions_not_the_step():
    from blf_gym.kernel.simulate import divergence_message

    assert "actions" in divergence_message(2, 1.0, 1e-4, 100, "none")
    assert "too large" in divergence_message(2, 1.0, 1e-3, 100, "proposed")
    assert "actions" not in divergence_message(2, 1.0, 1e-3, 100, "proposed")


# ---- 11. disk and permissions -----------------------------------------------------------------

@pytest.mark.parametrize("command", ["blf-eval", "blf-reproduce"])
def test_an_out_that_is_a_file_is_one_line_and_exit_2(tmp_path, capsys, command):
    from agents.evaluate import main as eval_main
    from baselines.reproduce import main as reproduce_main

    target = tmp_path / "afile"
    target.write_text("x")
    main = eval_main if command == "blf-eval" else reproduce_main
    args = (["--controllers", "proposed", "--agents", "--suite-seeds", "0"] if command == "blf-eval"
            else ["--controller", "proposed"])
    assert main([*args, "--duration", "0.01", "--out", str(target), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(target) in err and "Traceback" not in err


@pytest.mark.parametrize("code, hint", [(errno.ENOSPC, "free some space"), (errno.EACCES, "can write to"),
                                        (errno.EROFS, "read-only")])
@pytest.mark.parametrize("command", ["blf-eval", "blf-reproduce"])
def test_a_full_disk_or_a_read_only_folder_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch,
                                                                   command, code, hint):
    # root ignores permission bits, so the failing write is injected where results are written
    import agents.eval_runner as runner  # where blf-eval's run writes its records
    import agents.evaluate as ev
    import baselines.reproduce as rp

    def fail(records, out, *meta):
        raise OSError(code, os.strerror(code), str(Path(out) / "results.json"))

    monkeypatch.setattr(runner if command == "blf-eval" else rp, "write_results", fail)
    main = ev.main if command == "blf-eval" else rp.main
    args = (["--controllers", "proposed", "--agents", "--suite-seeds", "0"] if command == "blf-eval"
            else ["--controller", "proposed"])
    assert main([*args, "--duration", "0.01", "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "o" / "results.json") in err[0] and hint in err[0]
