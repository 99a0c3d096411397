"""blf-eval in worker processes (``--jobs``): the same records, to the bit, as in one process; a
Ctrl-C ends the workers at once and keeps what finished; and the env records only the signals
the metrics read when asked (``record_channels``), with the same numbers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agents.evaluate import main as eval_main
from agents.loading import PRETRAINED
from blf_gym.envs.envcore import EnvCore
from blf_gym.results.metrics import METRIC_CHANNELS
from blf_gym.kernel.simulate import CHANNELS

ROOT = Path(__file__).resolve().parent.parent


def _records(out: Path) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "wall_s"}
            for r in json.loads((out / "results.json").read_text())["records"]]


@pytest.mark.slow
def test_workers_score_what_one_process_scores(tmp_path, capsys):
    # two agents with different control periods (two law references), two baselines, every kind of
    # piece; trajectories saved by the workers too
    common = ["--controllers", "proposed", "bc", "--agents", str(PRETRAINED / "ppo_residual"),
              str(PRETRAINED / "ppo_plain_searched"), "--suite-seeds", "3", "--duration", "0.5",
              "--no-progress", "--no-plots", "--save-traj"]
    assert eval_main([*common, "--jobs", "1", "--out", str(tmp_path / "one")]) == 0
    assert eval_main([*common, "--jobs", "2", "--out", str(tmp_path / "two"), "--fresh-law"]) == 0
    one, two = _records(tmp_path / "one"), _records(tmp_path / "two")
    # 4 policies x 4 groups, in the same order, every field but the wall time the same
    assert len(one) == 16 and one == two
    files = sorted(p.name for p in (tmp_path / "one" / "traj").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "two" / "traj").iterdir()) and len(files) == 4 * 8
    for name in files:
        a, b = np.load(tmp_path / "one" / "traj" / name), np.load(tmp_path / "two" / "traj" / name)
        assert sorted(a.files) == sorted(b.files) and {c for c in CHANNELS} <= set(a.files)
        for k in a.files:
            assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), (name, k)


def test_jobs_must_be_a_positive_count(capsys, monkeypatch):
    assert eval_main(["--jobs", "0", "--agents", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["blf-eval: error: --jobs must be an integer >= 1, got 0"]
    monkeypatch.setenv("BLF_GYM_JOBS", "two")
    assert eval_main(["--agents", "--no-progress"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "blf-eval: error: BLF_GYM_JOBS must be an integer >= 1 (blf-eval's default --jobs), got 'two'"]


def test_the_default_workers_are_the_cpus_at_most_four_unless_told(monkeypatch):
    from agents.evaluate import MAX_DEFAULT_JOBS, default_jobs

    monkeypatch.setenv("BLF_GYM_JOBS", "3")
    assert default_jobs() == 3
    monkeypatch.delenv("BLF_GYM_JOBS")
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert default_jobs() == max(1, min(cpus, MAX_DEFAULT_JOBS)) and MAX_DEFAULT_JOBS == 4


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_ctrl_c_ends_the_workers_and_keeps_the_finished_records(tmp_path):
    from blf_gym.kernel.simulate import ClosedLoop
    from blf_gym.model.params import preset

    # The builds both workers load, compiled here first (into the run's cache folder, which the
    # command inherits): the law's worker steps blocks of four arms, the agent's env one arm. Left
    # cold, the law's worker compiles for tens of seconds under load, long enough for the agent's
    # whole piece to finish first, and the run then ended before the signal could interrupt it.
    for lanes in (1, 4):
        ClosedLoop([preset("paper-0.1hz")], "proposed", threads=1, lanes=lanes).advance(10)
    out = tmp_path / "out"
    # the presets' baseline rows finish in a second or two; the stress agents take far longer. No
    # second reference: every record waits for the reference's episodes, and the reference's build
    # (PPC, stepping four arms) compiling cold under load held all six back until the agent's had
    # finished too (CI, stop 70), so the signal came after the run had nothing left to interrupt
    cmd = [sys.executable, "-m", "agents.evaluate", "--controllers", "proposed", "--agents",
           str(PRETRAINED / "ppo_residual"), "--suite", "stress", "--suite-seeds", "100", "--jobs", "2",
           "--reference", "none", "--no-progress", "--no-plots", "--out", str(out)]
    with open(tmp_path / "stderr", "w") as err:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline and proc.poll() is None:
                if (out / "results.json").exists() and len(_children(proc.pid)) >= 2:
                    break
                time.sleep(0.2)
            workers = _children(proc.pid)
            assert proc.poll() is None and len(workers) >= 2, (tmp_path / "stderr").read_text()
            proc.send_signal(signal.SIGINT)  # to the main process alone: it must end its workers
            rc = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert rc == 130, (tmp_path / "stderr").read_text()

    def alive(w: int) -> bool:
        try:
            return "zombie" not in Path(f"/proc/{w}/status").read_text()
        except OSError:  # gone
            return False

    # ended, not left running their pieces: waited for as an event (a loaded machine takes a while
    # to reap them), never by a fixed sleep
    until = time.monotonic() + 60
    while time.monotonic() < until and any(alive(w) for w in workers):
        time.sleep(0.2)
    assert not any(alive(w) for w in workers), workers
    recs = json.loads((out / "results.json").read_text())["records"]
    assert recs and len(recs) < 6  # kept what finished, and it had not finished
    assert json.loads((out / "manifest.json").read_text())["complete"] is False
    assert "interrupted" in (tmp_path / "stderr").read_text()


def test_an_env_that_records_the_metrics_channels_keeps_the_same_numbers():
    from agents.evaluate import build_scenarios

    scs = build_scenarios([], 3, {}, 0.3, "randomized")[0][1]
    assert all(sc.angle_noise_std > 0 for sc in scs)  # noisy arms: each draws its own stream
    cores = [EnvCore(3, controller="proposed", record=True, threads=1, record_channels=ch, duration=0.3,
                     terminate_on_violation=False)
             for ch in (None, METRIC_CHANNELS, ("u",))]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(30, 3, 3))
    for core in cores:
        for i in range(3):
            core.rngs[i] = np.random.default_rng(100 + i)
        core.reset_envs(range(3), scenarios=scs)
        for a in actions:
            core.step(a)
    for i in range(3):
        full, some, one = (c.trajectory(i) for c in cores)
        assert set(full.signals) == set(CHANNELS)
        assert tuple(some.signals) == METRIC_CHANNELS and tuple(one.signals) == ("t", "u")
        assert full.n_samples == some.n_samples == one.n_samples == 300
        for k in METRIC_CHANNELS:
            assert np.array_equal(full.signals[k], some.signals[k]), k
        assert np.array_equal(full.signals["u"], one.signals["u"])
        assert some.step_violations == full.step_violations and some.diverged == full.diverged


@pytest.mark.parametrize("bad", [("e1", "e1"), ("e9",), (3,), "u", {"u"}, {"u": 1}, 3])
def test_record_channels_refuses_unknown_or_repeated_names_and_non_sequences(bad):
    with pytest.raises(ValueError, match="record_channels must be a list or tuple of distinct names among"):
        EnvCore(1, record=True, record_channels=bad)


def _stepped_and_held(controller: str | None, action: float, period: float) -> tuple[list, list, list, list]:
    from agents.evaluate import build_scenarios

    scs = [sc for _, g in build_scenarios(["paper-0.5hz"], 3, {}, 1.0, "stress") for sc in g]
    out = []
    for held in (False, True):
        core = EnvCore(len(scs), controller=controller, record=True, threads=1, duration=1.0, control_period=period,
                       terminate_on_violation=False, reward_weights={})
        for i in range(len(scs)):
            core.rngs[i] = np.random.default_rng(50 + i)
        core.reset_envs(range(len(scs)), scenarios=scs)
        core.observe()
        a = np.full((len(scs), 3), action)
        if held:
            for periods in (1, 6, 13, core.max_episode_steps - 20):  # uneven cuts of the episode
                core.hold(a, periods)
        else:
            for _ in range(core.max_episode_steps):
                core.step(a)
        out.append(([core.trajectory(i) for i in range(len(scs))], [r.bit_generator.state for r in core.rngs]))
    return out[0][0], out[1][0], out[0][1], out[1][1]


@pytest.mark.parametrize("controller, action, period", [("proposed", 0.0, 0.01), ("proposed", 0.7, 0.002),
                                                        (None, 1.0, 0.005)])
def test_holding_an_action_gives_the_trajectories_of_stepping_it(controller, action, period):
    # the law alone (blf-eval's reference), a residual, and a plain full torque that diverges
    stepped, held, rng_stepped, rng_held = _stepped_and_held(controller, action, period)
    assert rng_stepped == rng_held  # every arm drew the same numbers
    if controller is None:
        assert all(t.diverged for t in stepped)  # 150 N m on every joint: the arm is lost
    for a, b in zip(stepped, held):
        assert set(a.signals) == set(b.signals) == set(CHANNELS) and a.n_samples == b.n_samples > 0
        for k in CHANNELS:
            assert np.array_equal(a.signals[k], b.signals[k]), k
        for f in ("diverged", "diverged_at", "step_violations", "first_violation_step_time", "saturated_steps",
                  "divergence_code"):
            assert getattr(a, f) == getattr(b, f), f


def test_hold_refuses_what_it_cannot_hold():
    core = EnvCore(2, controller="proposed", duration=0.1, terminate_on_violation=False, reward_weights={})
    core.reset_envs(range(2))
    with pytest.raises(ValueError, match="past the episode's end"):
        core.hold(np.zeros((2, 3)), 11)
    with pytest.raises(ValueError, match="periods must be"):
        core.hold(np.zeros((2, 3)), 0)
    with pytest.raises(ValueError, match="no score term"):
        EnvCore(2, controller="proposed", duration=0.1, terminate_on_violation=False).hold(np.zeros((2, 3)), 1)
    with pytest.raises(ValueError, match="terminate_on_violation=False"):
        EnvCore(2, controller="proposed", duration=0.1, reward_weights={}).hold(np.zeros((2, 3)), 1)
    fine = EnvCore(1, controller="proposed", duration=0.1, control_period=5e-4, terminate_on_violation=False,
                   reward_weights={})
    with pytest.raises(ValueError, match="whole 1 ms samples"):
        fine.hold(np.zeros((1, 3)), 1)
    with pytest.raises(ValueError, match="action must be finite"):
        core.hold(np.full((2, 3), np.nan), 1)
