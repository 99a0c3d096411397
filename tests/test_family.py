"""The task family of 2 to 7 links (blf_gym.model.family, docs/family.md): the arms' resampling
against hand-worked values and the paper's arm, the table's torques and inertias against the
package's own dynamics (checked against Pinocchio in tests/test_dynamics.py), the presets and
references, and the refusals naming n_links."""

from __future__ import annotations

import math

from pathlib import Path

import numpy as np
import pytest

from blf_gym.model.dynamics import gravity, mass_matrix, pose_jacobian
from blf_gym.model.family import (FAMILY_AMPLITUDE, FAMILY_LINKS, MODULE_LENGTH, MODULE_MASS, family_arm, family_base, family_preset,
                                  family_presets, family_table, preset_links)
from blf_gym.model.params import PRESETS, ArmParams, preset
from blf_gym.model.reference import joint_reference
from baselines.params import velocity_gain


def test_the_three_link_member_is_the_paper_s_arm_and_presets():
    assert family_arm(3) == ArmParams()
    assert family_presets(3) == tuple(PRESETS)
    assert family_preset("paper-0.5hz") == preset("paper-0.5hz")
    assert family_base(3) == preset("paper-0.1hz")


@pytest.mark.parametrize("n", [m for m in FAMILY_LINKS if m != 3])
def test_the_other_members_are_chains_of_the_paper_s_average_link(n):
    arm = family_arm(n)
    assert arm.n_links == n and arm.gravity == ArmParams().gravity
    # a third of the paper's reach (0.80 m) and mass (0.53 kg) per module, to 0.1 mm and 0.1 g
    assert arm.lengths == (MODULE_LENGTH,) * n and abs(MODULE_LENGTH - 0.8 / 3) < 5e-5
    assert arm.masses == (MODULE_MASS,) * n and abs(MODULE_MASS - 0.53 / 3) < 5e-5


def _lightest_mode(arm, draws=400):
    """The smallest eigenvalue of M(q) over random joint angles (and q = 0), kg m^2."""
    qs = np.random.default_rng(0).uniform(-np.pi, np.pi, (draws, arm.n_links))
    return min(np.linalg.eigvalsh(mass_matrix(q, arm)).min() for q in [np.zeros(arm.n_links), *qs])


def test_every_member_s_lightest_mode_stays_near_the_paper_s():
    # the reason for modules (blf_gym.model.family): the lightest mode within a factor of 2.5 of the
    # paper's at every n, where cutting the paper's arm into 7 equal pieces makes it 10 times lighter
    paper = _lightest_mode(ArmParams())
    for n in FAMILY_LINKS:
        assert 0.9 < _lightest_mode(family_arm(n)) / paper < 2.5, n
    pieces = ArmParams(lengths=(0.8 / 7,) * 7, masses=(0.53 / 7,) * 7)
    assert _lightest_mode(pieces) / paper < 0.1


@pytest.mark.parametrize("row", family_table(), ids=lambda r: f"n{r['n']}")
def test_the_table_s_torques_and_inertias_are_the_dynamics(row):
    arm = family_arm(row["n"])
    n = arm.n_links
    zero = np.zeros(n)
    assert row["gravity_torque"] == pytest.approx(abs(gravity(zero, arm)[0]), rel=1e-12)
    np.testing.assert_allclose(row["inertia_q0"], np.diag(mass_matrix(zero, arm)), rtol=1e-12)
    up = np.zeros(n)
    up[0] = math.pi / 2  # the arm vertical: the 40 N force along x acts with the whole reach
    tau = pose_jacobian(up, arm).T @ np.array([40.0, 0.0, 0.0])
    assert row["force_torque"] == pytest.approx(abs(tau[0]), rel=1e-12)
    # every torque the gravity and the force ask inside the paper's 150 N m actuator limit
    assert row["gravity_torque"] + row["force_torque"] < preset("paper-0.1hz").sim.max_torque


@pytest.mark.parametrize("n", [m for m in FAMILY_LINKS if m != 3])
def test_the_other_members_presets_follow_their_joint_sinusoids(n):
    names = family_presets(n)
    assert names == (f"n{n}-0.1hz", f"n{n}-0.5hz")
    for name, f in zip(names, (0.1, 0.5)):
        sc = family_preset(name, duration=2.0)
        assert sc.name == name and sc.arm == family_arm(n) and sc.sim.duration == 2.0 and preset_links(name) == n
        t = np.linspace(0.0, 2.0, 9)
        q, _, _ = joint_reference(t, sc)
        phases = math.pi * np.arange(n) / n
        np.testing.assert_allclose(q, FAMILY_AMPLITUDE * np.sin(2 * math.pi * f * t[:, None] + phases), atol=1e-13)
        # the paper's plant around the arm: friction, dead zone, force and bounds
        paper = preset("paper-0.1hz")
        assert (sc.friction, sc.dead_zone, sc.force, sc.bounds, sc.sim.dt) == (
            paper.friction, paper.dead_zone, paper.force, paper.bounds, paper.sim.dt)


@pytest.mark.parametrize("bad", [1, 8, 0, -3, 3.0, True, "4", None])
def test_a_number_of_links_outside_the_family_is_refused_by_name(bad):
    with pytest.raises(ValueError, match=r"n_links must be an integer in \[2, 7\]"):
        family_arm(bad)


def test_an_unknown_preset_lists_the_family_s():
    with pytest.raises(ValueError, match=r"unknown preset 'n8-0.1hz'.*'n7-0.5hz'"):
        family_preset("n8-0.1hz")
    assert preset_links("n3-0.1hz") is None  # n = 3 is the paper's presets, not a joint-space copy


def _fastest_pole(gains, arm, poses):
    """The velocity loop's fastest pole over ``poses``: the largest generalized eigenvalue of
    (diag(gains), M(q)), by scipy's symmetric solver (not the code's own eigvals of M^-1 K)."""
    from scipy.linalg import eigh

    return max(eigh(np.diag(gains), mass_matrix(q, arm), eigvals_only=True).max() for q in poses)


@pytest.mark.parametrize("n", [2, 5, 7])
def test_the_paper_s_gains_carried_to_n_links(n):
    # docs/family.md, "Gains": K1 read at the joints' positions along the chain (at n = 5, joints 0,
    # 2 and 4 sit where the paper's three do, and 1 and 3 halfway); K2 of the same shape, scaled so
    # that the velocity loop's fastest pole over the poses is the paper's on its arm
    from blf_gym.plugins.registry import make_controller

    arm = family_arm(n)
    p = make_controller("proposed", nominal=arm).params
    paper = make_controller("proposed").params
    positions = np.linspace(0.0, 1.0, n)
    np.testing.assert_allclose(p.K1, np.interp(positions, [0.0, 0.5, 1.0], paper.K1), rtol=1e-15)
    shape = np.interp(positions, [0.0, 0.5, 1.0], paper.K2)
    ratio = np.asarray(p.K2) / shape
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)
    rng = np.random.default_rng(0)
    poses = rng.uniform(-np.pi, np.pi, (512, n))
    poses[0] = 0.0
    paper_poses = np.random.default_rng(0).uniform(-np.pi, np.pi, (512, 3))
    paper_poses[0] = 0.0
    assert _fastest_pole(p.K2, arm, poses) == pytest.approx(_fastest_pole(paper.K2, ArmParams(), paper_poses),
                                                            rel=1e-9)
    if n == 5:
        assert p.K1[1] == (paper.K1[0] + paper.K1[1]) / 2 and p.K1[3] == (paper.K1[1] + paper.K1[2]) / 2
    # given gains are taken as they are; the paper's own arm keeps the paper's, bit for bit
    assert make_controller("proposed", nominal=arm, K2=7.0).params.K2 == (7.0,) * n
    assert make_controller("proposed", nominal=ArmParams()).params == paper


# ---- the env on a member (kernels: the law with the LESO at 2 links and the plain env's at 2,
# which tests/test_n_links.py compiles too) -------------------------------------------------------

def test_the_env_on_two_links_takes_the_member_s_preset_arm_and_carried_law():
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env

    import blf_gym  # noqa: F401 (registers the env ids)

    env = gym.make("PlanarBLFResidual-v0", n_links=2, duration=1.0)
    core = env.unwrapped.core
    assert core.base.name == "n2-0.1hz" and core.base.arm == family_arm(2) and core.n == 2
    assert core.controller.nominal == family_arm(2) == core.observer.nominal
    assert core.controller.params.K2 == velocity_gain((45.0, 45.0, 15.0), family_arm(2))
    o, _ = env.reset(seed=0)
    assert env.action_space.shape == (2,) and o.shape == env.observation_space.shape
    for _ in range(100):  # the law alone on the member's preset: the whole second inside the bounds
        o, r, term, trunc, info = env.step(np.zeros(2, dtype=np.float32))
        assert not term
    assert trunc and info["episode_metrics"]["violating_samples"] == 0
    check_env(env.unwrapped, skip_render_check=True)
    fast = gym.make("PlanarBLFResidual-v0", n_links=2, scenario="paper-0.5hz").unwrapped.core.base
    assert fast.name == "n2-0.5hz" and fast.reference.frequency == 0.5
    # the plain env's suites are drawn around the member's preset
    plain = gym.make("PlanarBLF-v0", n_links=2, scenario="randomized", duration=0.1, reward_weights={})
    plain.reset(seed=3)
    drawn = plain.unwrapped.core.scenarios[0]
    assert drawn.name == "randomized" and drawn.arm.lengths == family_arm(2).lengths
    assert drawn.reference.kind == "joint" and plain.action_space.shape == (2,)


def test_three_links_is_the_paper_s_env_bit_for_bit():
    import gymnasium as gym

    import blf_gym  # noqa: F401 (registers the env ids)

    a = gym.make("PlanarBLFResidual-v0", duration=0.3)
    b = gym.make("PlanarBLFResidual-v0", duration=0.3, n_links=3)
    oa, _ = a.reset(seed=5)
    ob, _ = b.reset(seed=5)
    assert oa.tobytes() == ob.tobytes()
    act = np.random.default_rng(0).uniform(-1, 1, (30, 3)).astype(np.float32)
    for x in act:
        ra, rb = a.step(x), b.step(x)
        assert ra[0].tobytes() == rb[0].tobytes() and ra[1] == rb[1]


@pytest.mark.parametrize("kwargs, match", [
    ({"n_links": 8}, r"n_links must be an integer in \[2, 7\]"),
    ({"n_links": 2, "scenario": "n5-0.1hz"}, r"the preset 'n5-0.1hz' is the 5-link arm's, not n_links=2's"),
    ({"n_links": 2, "scenario": preset("paper-0.1hz")}, r"n_links=2 but the Scenario's arm has 3 links"),
    ({"n_links": 4, "controller": "pd_gravity"}, r"controller 'pd_gravity' does not serve an arm of 4 links \(n_links\)"),
    ({"scenario": "n9-0.1hz"}, r"scenario must be one of .*task-family preset"),
])
def test_a_member_the_env_cannot_make_is_one_error_naming_the_field(kwargs, match):
    import gymnasium as gym

    import blf_gym  # noqa: F401 (registers the env ids)

    with pytest.raises(ValueError, match=match):
        gym.make("PlanarBLFResidual-v0", **kwargs)


# ---- blf-eval on members (kernel: the law's batch build at 2 links) ----------------------------

def test_the_groups_of_a_member_are_its_presets_and_suites_drawn_by_the_same_seeds():
    from agents.episodes import build_scenarios

    paper = build_scenarios(["paper-0.1hz", "paper-0.5hz"], [2, 1], {}, None, ["randomized", "stress"])
    assert build_scenarios(["paper-0.1hz", "paper-0.5hz"], [2, 1], {}, None, ["randomized", "stress"], n_links=3) == paper
    five = build_scenarios(["paper-0.1hz", "paper-0.5hz"], [2, 1], {}, None, ["randomized", "stress"], n_links=5)
    assert [g for g, _ in five] == ["n5-0.1hz", "n5-0.5hz", "n5-randomized", "n5-stress"]
    assert all(sc.arm == family_arm(5) or sc.arm.lengths == family_arm(5).lengths for _, scs in five for sc in scs)
    short = build_scenarios(["paper-0.1hz"], [1], {}, 2.0, ["randomized"], n_links=5)
    assert all(sc.sim.duration == 2.0 and sc.arm.n_links == 5 for _, scs in short for sc in scs)
    # the same seeds draw the same knobs: the paper's training draw k and the member's share them
    (_, a), (_, b) = paper[2], five[2]
    assert [sc.reference.frequency for sc in a] == [sc.reference.frequency for sc in b]
    assert [sc.force.onset for sc in a] == [sc.force.onset for sc in b]
    with pytest.raises(ValueError, match=r"--n-links.*n_links must be an integer in \[2, 7\]"):
        build_scenarios(["paper-0.1hz"], 0, {}, None, n_links=9)


@pytest.mark.slow
def test_blf_eval_scores_the_law_on_a_member_and_refuses_an_agent_of_another_arm(tmp_path, capsys):
    import json

    from agents.evaluate import main

    out = tmp_path / "eval"
    rc = main(["--n-links", "2", "--controllers", "proposed", "--reference", "none", "--scenarios", "paper-0.5hz",
               "--suite", "randomized", "--suite-seeds", "2", "--duration", "0.5", "--out", str(out), "--no-plots",
               "--no-progress", "--jobs", "1"])
    assert rc == 0, capsys.readouterr().err
    recs = json.loads((out / "results.json").read_text())["records"]
    assert [r["scenario"] for r in recs] == ["n2-0.5hz", "n2-randomized"]
    assert all(len(r["rmse_deg"]) == 2 and r["violations"] == [0, 0] for r in recs)
    capsys.readouterr()
    assert main(["--n-links", "2", "--agents", "agents/pretrained/ppo_residual", "--no-progress", "--jobs", "1"]) == 2
    err = capsys.readouterr().err
    # said before the agent is loaded (and its kernels compiled): one line
    assert "ppo_residual acts on an arm of 3 links, and the groups are of [2]" in err and err.count("\n") == 1


@pytest.mark.slow
def test_the_gain_search_runs_on_a_member_and_scores_the_carried_law_as_the_law(tmp_path):
    # the same kernel as blf-eval's test above (the proposed law's batch build at 2 links)
    import json

    from baselines.gains import main
    from blf_gym.plugins.registry import make_controller

    carried = make_controller("proposed", nominal=family_arm(2)).params.K2[0]
    assert main(["proposed", "--n-links", "2", "--grid", f"K2={carried!r},{carried / 2!r}", "--episodes", "1",
                 "--no-progress", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "gains.json").read_text())
    assert res["n_links"] == 2 and res["episodes"] == ["n2-0.1hz", "n2-0.5hz", "randomized/0"]
    same = next(r for r in res["rows"] if r["point"]["K2"] == carried)
    assert same["score_geomean"] == 1.0 and same["effort_ratio"] == 1.0 and same["admissible"]
    assert "on the task family's 2-link arm" in (tmp_path / "gains.md").read_text()


def test_a_member_s_learning_curve_reads_its_own_groups_under_the_roles_names():
    from agents.episodes import curve_scenarios
    from blf_gym.envs.protocol import CURVE_GROUPS

    paper = curve_scenarios(2, 1.0)
    seven = curve_scenarios(2, 1.0, n_links=7)
    assert [g for g, _ in seven] == [g for g, _ in paper] == list(CURVE_GROUPS)
    assert [sc.name for _, scs in seven for sc in scs][:2] == ["n7-0.1hz", "n7-0.5hz"]
    assert all(sc.arm.n_links == 7 for _, scs in seven for sc in scs)
    assert curve_scenarios(2, 1.0, n_links=3) == paper


_SEARCHED = Path(__file__).resolve().parents[1] / "docs" / "gains" / "family"


@pytest.mark.parametrize("law,n", [(law, m) for law in ("ppc", "proposed_tuned") for m in FAMILY_LINKS if m != 3
                                   and (_SEARCHED / f"{law.split('_')[0]}_n{m}" / "gains.json").is_file()])
def test_a_law_s_member_gains_are_the_search_s_choice_on_that_member(law, n):
    # baselines.ppc.PPC_MEMBER_GAINS (and baselines.controllers.PROPOSED_TUNED_MEMBER_GAINS) hold what
    # python -m baselines.gains ppc (proposed) --n-links N chose (docs/gains/family/<law>_n<N>/gains.json),
    # in the carried vectors' shape; another arm of n links keeps the rule's carried gains
    import json

    from baselines.controllers import PROPOSED_TUNED_MEMBER_GAINS
    from baselines.ppc import PPC_MEMBER_GAINS
    from blf_gym.plugins.registry import make_controller

    chosen = json.loads((_SEARCHED / f"{law.split('_')[0]}_n{n}" / "gains.json").read_text())["chosen"]
    assert {"ppc": PPC_MEMBER_GAINS, "proposed_tuned": PROPOSED_TUNED_MEMBER_GAINS}[law][n] == chosen
    p = make_controller(law, nominal=family_arm(n)).params
    other = ArmParams(lengths=(0.8 / n,) * n, masses=(0.53 / n,) * n)
    carried = make_controller("proposed", nominal=family_arm(n)).params  # the same shapes as PPC's carried
    for k in ("K1", "K2"):
        assert getattr(p, k)[0] == pytest.approx(chosen[k], rel=1e-12)
        np.testing.assert_allclose(np.asarray(getattr(p, k)) / getattr(p, k)[0],
                                   np.asarray(getattr(carried, k)) / getattr(carried, k)[0], rtol=1e-12)
    assert make_controller(law, nominal=other).params.K1[0] == 1280.0  # the rule's, not the member's


def test_a_member_s_draws_are_known_as_the_member_and_level_0_puts_back_its_masses():
    from blf_gym.envs.levels import apply_level
    from blf_gym.envs.scenarios import sample_suite
    from blf_gym.model.family import member_arm
    from blf_gym.model.params import joint_scenario

    drawn = [sample_suite(np.random.default_rng(k), family_base(4), "randomized") for k in range(5)]
    assert any(sc.arm.masses != family_arm(4).masses for sc in drawn)  # the payload knob moved the last mass
    assert all(member_arm(sc.arm) == family_arm(4) for sc in drawn)
    assert all(apply_level(sc, 0).arm.masses == family_arm(4).masses for sc in drawn)
    assert member_arm(joint_scenario(4).arm) is None  # another arm of 4 links is no member
    assert apply_level(joint_scenario(4), 0).arm == joint_scenario(4).arm
