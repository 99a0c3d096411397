"""blf-falsify (issue 52, item 1): its robustness is STL's (checked against rtamt), the law alone has
no counterexample by definition, a policy built to fail is caught within a stated budget, and a
counterexample replays to the bit."""

from __future__ import annotations

import json

import numpy as np
import pytest

import blf_gym  # noqa: F401
from agents.falsify import Target, case_scenario, falsify, first_cases, replay, rho, robustness, space
from blf_gym.results.metrics import episode_stats
from blf_gym.envs.observation import observation_index
from blf_gym.model.params import preset
from blf_gym.model.reference import joint_reference
from blf_gym.envs.scenarios import apply_variations

DURATION = 5.0  # s: the planted push happens within the first period of a 0.5 Hz reference


def test_rho_is_stl_robustness_of_the_bounds_by_rtamt():
    """rho of an episode that leaves its bounds equals rtamt's robustness of
    always((k_a - e1 >= 0) and (e1 + k_b >= 0)), joint by joint, at the first sample."""
    rtamt = pytest.importorskip("rtamt")
    import gymnasium as gym

    # a constant torque in plain mode, termination off: the arm leaves its bounds and comes back
    # through them, so the episode has margins of both signs
    env = gym.make("PlanarBLF-v0", scenario="paper-0.1hz", terminate_on_violation=False, duration=1.0, record=True,
                   reward_weights={})
    env.reset(seed=0)
    for k in range(100):
        env.step(np.array([0.05, -0.05, 0.02] if k < 30 else [0.0, 0.0, 0.0], np.float32))
    tr = env.unwrapped.trajectory()
    env.close()
    st = episode_stats(tr)
    per_joint = []
    for j in range(3):
        spec = rtamt.StlDiscreteTimeSpecification()
        for v in ("e", "ka", "kb"):
            spec.declare_var(v, "float")
        spec.spec = "always((ka - e >= 0) and (e + kb >= 0))"
        spec.parse()
        t = list(range(len(tr.t)))
        out = spec.evaluate({"time": t, "e": tr.e1[:, j].tolist(), "ka": tr.k_a[:, j].tolist(),
                             "kb": tr.k_b[:, j].tolist()})
        per_joint.append(out[0][1])
    assert min(per_joint) < 0  # the case leaves a bound, so the sign is exercised
    assert rho(st) == pytest.approx(np.degrees(min(per_joint)), rel=1e-12, abs=1e-12)


def test_robustness_of_the_implication():
    assert robustness(-0.5, 0.2) == -0.2  # the law keeps, the policy leaves: a counterexample
    assert robustness(-0.5, -0.1) == 0.1  # the law itself leaves: not one
    assert robustness(0.3, 0.2) == 0.3


def test_the_first_cases_are_the_box_centre_edges_and_corners():
    box = space()
    assert set(box) >= {"frequency", "initial_error_0", "initial_error_2", "angle_noise_std"}
    cases = first_cases(box, seed=0)
    names = list(box)
    assert cases[0] == {**{k: (lo + hi) / 2 for k, (lo, hi) in box.items()}, "noise_seed": 0}
    for i, k in enumerate(names):  # each knob at either end, the others centred
        assert cases[1 + 2 * i][k] == box[k][0] and cases[2 + 2 * i][k] == box[k][1]
    corners = cases[1 + 2 * len(names):]
    assert len(corners) == 2 + 16
    assert all(c[k] in box[k] for c in corners for k in names)
    assert len({tuple(c[k] for k in names) for c in corners}) == len(corners)
    # a case is the 0.1 Hz preset with those knobs
    sc, seed = case_scenario({**cases[2], "noise_seed": 7}, box)
    assert sc.reference.frequency == box["frequency"][1] and seed == 7


def test_bad_ranges_are_refused_by_name():
    with pytest.raises(ValueError, match="payload"):
        space({"payload": (0.3, 0.1)})
    with pytest.raises(ValueError, match="payload"):
        space({"payload": (-1.0, 0.1)})


def test_the_law_alone_has_no_counterexample():
    report = falsify(Target.from_args(controller="proposed"), budget=24, duration=DURATION, batch=12)
    assert report["counterexamples"] == 0 and report["falsification_rate"] == 0.0
    assert report["runs"][0]["lowest_robustness_deg"] >= 0.0


class _Planted:
    """A residual that pushes joint 3 outward at full scale whenever joint 1's reference speed
    exceeds what a 0.2 Hz reference ever reaches: it can fail only in the faster part of the frequency
    range, which the falsifier must find (at 0.5 Hz, the top of the range, the law itself fails with
    some knobs, so those cases are not counterexamples)."""

    def __init__(self, threshold: float) -> None:
        idx = observation_index(3, privileged=False)
        self.qd = idx["qd_d"]
        self.threshold = 100.0 * np.tanh(threshold / 100.0)  # the observation squashes qd_d by 100

    def predict(self, obs, deterministic=True):
        fast = np.abs(obs[:, self.qd][:, 0]) > self.threshold
        a = np.zeros((obs.shape[0], 3), dtype=np.float32)
        a[fast, 2] = 1.0
        return a, None


def _planted_target() -> Target:
    slow = apply_variations(preset("paper-0.1hz"), {"frequency": 0.2}, strict=False)
    t = np.linspace(0.0, 5.0, 5001)  # one whole period at 0.2 Hz
    threshold = float(np.abs(joint_reference(t, slow)[1][:, 0]).max()) * 1.02
    meta = {"name": "planted", "mode": "residual", "algo": "planted",
            "env_kwargs": {"controller": "proposed", "residual_scale": 150.0, "control_period": 0.01}}
    return Target("planted", "agent", {"agent": None, "policy": None, "controller": None, "residual_filter": None},
                  _Planted(threshold), meta, None)


def test_a_policy_built_to_fail_is_caught_and_its_counterexample_replays_to_the_bit(tmp_path, monkeypatch):
    target = _planted_target()
    report = falsify(target, budget=16, duration=DURATION, batch=16)  # the stated budget: 16 episodes
    assert report["falsification_rate"] == 1.0 and report["simulations_to_first"][0] <= 16
    ces = report["runs"][0]["counterexamples"]
    # only fast references fail, and only where the law keeps its bounds
    assert all(c["params"]["frequency"] > 0.2 and c["law_margin_deg"] > 0 > c["policy_margin_deg"] for c in ces)
    # the replay re-simulates the case from its knobs alone
    import agents.falsify as fz

    monkeypatch.setattr(fz.Target, "from_args", classmethod(lambda cls, *a, **k: target))
    out = replay(json.loads(json.dumps(report)), 0, 0)
    assert out["identical"], out


class _Batched(_Planted):
    """The planted policy with a batched network's trait: its action moves in a low digit with the
    number of rows it is given (as a matrix product's blocking follows the batch's shape)."""

    def predict(self, obs, deterministic=True):
        a, _ = super().predict(obs, deterministic)
        return a + np.float32(1e-6) * np.float32(obs.shape[0] % 7), None


def test_a_counterexample_found_in_a_batch_replays_to_the_bit_in_a_batch_of_its_size(monkeypatch):
    # the search steps 6 cases at a time, the last batch of a 16-case budget holds 4: each
    # counterexample replays in a batch of the size it was found in (a lone replay would not match)
    import agents.falsify as fz

    from dataclasses import replace as swap

    target = _planted_target()
    batched = _Batched.__new__(_Batched)
    batched.__dict__.update(vars(target.model))
    target = swap(target, model=batched)
    report = falsify(target, budget=16, duration=DURATION, batch=6)
    ces = report["runs"][0]["counterexamples"]
    assert ces
    monkeypatch.setattr(fz.Target, "from_args", classmethod(lambda cls, *a, **k: target))
    for k in range(len(ces)):
        out = replay(json.loads(json.dumps(report)), 0, k)
        assert out["identical"], (k, out)
    lone = dict(json.loads(json.dumps(report)), batch=1)
    assert not all(replay(lone, 0, k)["identical"] for k in range(len(ces)))  # the batch's size matters


def test_the_command_writes_its_report(tmp_path):
    from agents.falsify import main

    assert main(["--controller", "proposed", "--budget", "4", "--batch", "4", "--duration", "1",
                 "--out", str(tmp_path), "--no-progress"]) == 0
    rep = json.loads((tmp_path / "falsify.json").read_text())
    assert rep["simulations"] == 4 and rep["counterexamples"] == 0 and "git_commit" in rep["provenance"]
    assert main(["--controller", "nope", "--budget", "4"]) == 2


def test_a_network_target_runs_torch_on_one_thread():
    # as blf-eval: a batch of 16 rows gains nothing from more threads, and idle ones beside another
    # job made each network call about 15 times slower (agents/falsify.py, Target.from_args)
    import torch

    torch.set_num_threads(2)
    Target.from_args(policy="floor")
    assert torch.get_num_threads() == 1
