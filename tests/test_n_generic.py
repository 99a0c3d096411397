"""n as a parameter in the Python layer (issue 62, item 4): nothing in blf_gym's envs and results,
baselines or agents assumes 3 joints but the paper's own data, which says so. The baselines'
registered laws and policies at n = 2 and 4 (built, refused by name where their defaults are the
paper's 3-link gains, and a few run for a short episode), the shapes of observations, actions and
metrics at n, the n = 3 defaults unchanged, and a grep that fails if a bare 3-joint default comes
back.

Kernels compiled here (about 30-60 s each, the first time): (ppc, leso, 2), (computed_torque_leso,
leso, 4), and the plain env's zero-torque controller with the LESO at 2 and 4 (which
tests/test_n_links.py compiles too)."""

from __future__ import annotations

import re
from dataclasses import fields
from importlib.metadata import entry_points
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import blf_gym  # noqa: F401 (registers the env ids)
from blf_gym.envs.observation import observation_index, observation_layout
from blf_gym.model.params import joint_scenario
from blf_gym.plugins.registry import make_controller, make_observer, make_policy
from blf_gym.results.metrics import episode_stats, summarize

ROOT = Path(__file__).resolve().parents[1]

# the registered plug-ins of this repository (an installed example's are not ours to check)
OURS = sorted(e.name for e in entry_points(group="blf_gym.controllers") if e.value.startswith("baselines."))
CARRIED = {"bc", "lesobc", "proposed", "proposed_tuned", "ppc"}
"""The laws whose default gains are vectors for the paper's 3-link arm, carried to an arm of n links
by docs/family.md's rule (tests/test_family.py checks the rule's numbers)."""
PAPER_GAINED = {"pd_gravity", "pd_gravity_leso"}
"""The laws whose default gains are vectors for the paper's 3-link arm and are not carried: refused
at other n, by name."""
ANY_N = {"funnel", "computed_torque", "computed_torque_leso"}
"""The laws whose defaults are one number for every joint (or scalars): they build at any n."""


def _per_joint(params):
    """The names of a gain dataclass's per-joint (tuple) fields."""
    return [f.name for f in fields(params) if isinstance(getattr(params, f.name), tuple)]


def test_the_registered_laws_are_the_ones_this_file_sorts():
    assert set(OURS) == CARRIED | PAPER_GAINED | ANY_N, set(OURS) ^ (CARRIED | PAPER_GAINED | ANY_N)


@pytest.mark.parametrize("n", [2, 4])
def test_every_registered_law_builds_at_n_or_names_the_paper_gain_it_needs(n):
    arm = joint_scenario(n).arm
    for name in OURS:
        if name in ANY_N | CARRIED:
            c = make_controller(name, nominal=arm)
            # a gain vector for the paper's 3 joints, given on this arm, is still refused by name
            paper = make_controller(name).params
            for k in _per_joint(paper):
                with pytest.raises(ValueError, match=rf"\.{k} must have one number or {n} entries"):
                    make_controller(name, nominal=arm, **{k: getattr(paper, k) + (1.0,) * (3 - len(getattr(paper, k)))})
        else:
            with pytest.raises(ValueError, match=rf"\.(K1|Kp) must have one number or {n} entries.*paper's 3-link arm"):
                make_controller(name, nominal=arm)
            # one number per gain stands for every joint
            paper = make_controller(name).params
            c = make_controller(name, nominal=arm, **{k: getattr(paper, k)[0] for k in _per_joint(paper)})
        assert c.nominal.n_links == n
        for k in _per_joint(c.params):  # a tuple of n, packed as n entries of the gains the kernel reads
            assert len(getattr(c.params, k)) == n and c.param_layout[k][1] == n, (name, k)


def test_the_paper_defaults_are_unchanged_at_3():
    from baselines.classical import CTCGains, PDGains
    from baselines.controllers import ControllerGains
    from baselines.floor import FloorParams
    from baselines.leso import LESO

    g = ControllerGains()
    assert g.K1 == (20.0, 20.0, 15.0) and g.K2 == (45.0, 45.0, 15.0)
    assert make_controller("ppc").params.K1 == (1280.0, 1280.0, 960.0)
    assert make_controller("proposed_tuned").params.K2 == (11.25, 11.25, 3.75)
    assert make_controller("pd_gravity").params.Kp == (12800.0, 12800.0, 3200.0)
    assert PDGains().Kp == (6400.0, 6400.0, 1600.0) and PDGains().Kd == (10.0, 10.0, 2.5)
    assert CTCGains().Kp == (102400.0,) * 3 and CTCGains().Kd == (80.0,) * 3
    assert FloorParams().Kp == (19600.0,) * 3 and FloorParams().Kd == (112.0,) * 3
    for name in OURS:  # every gain a float, as before
        assert all(type(x) is float for k in _per_joint(make_controller(name).params)
                   for x in getattr(make_controller(name).params, k))
    assert LESO().n == 3 and LESO().xhat.shape == (9,)


def test_the_sampled_leso_reads_n_from_its_arm():
    from baselines.leso import LESO

    arm = joint_scenario(4).arm
    obs = LESO(nominal=arm.pack())
    assert obs.n == 4 and obs.reset(np.full(4, 0.1)).shape == (12,)
    x = obs.step(np.full(4, 0.1), np.zeros(4), 1e-4)
    assert x.shape == (12,) and np.all(np.isfinite(x))
    with pytest.raises(ValueError, match="LESO.n = 3 but the nominal arm has 4 links"):
        LESO(nominal=arm.pack(), n=3)


def _closed_loop_record(sc, controller):
    from blf_gym.kernel.simulate import simulate_batch

    (tr,) = simulate_batch([sc], controller, make_observer("leso", nominal=sc.arm), threads=1)
    return tr


@pytest.mark.parametrize("n,name,gains", [
    (2, "ppc", {"K1": 1280.0, "K2": 11.25}),  # PPC's tuned numbers per joint, stated
    (4, "computed_torque_leso", {}),  # its defaults: the same number on every joint
])
def test_a_registered_law_runs_an_episode_at_n_and_its_record_has_n_joints(n, name, gains):
    sc = joint_scenario(n, duration=1.0)
    tr = _closed_loop_record(sc, make_controller(name, nominal=sc.arm, **gains))
    assert not tr.diverged, tr.message
    for ch in ("e1", "u", "q", "q_ref", "x3_hat"):
        assert tr.signals[ch].shape == (sc.sim.n_samples, n), ch
    st = episode_stats(tr)
    assert st.n_joints == n and len(st.rmse_deg) == n and np.all(np.isfinite(st.rmse_deg))
    rec = summarize([tr, st], name, "baseline", sc.name, sc.sim.dt)
    from blf_gym.results.metrics import PER_JOINT

    for f in PER_JOINT:
        assert len(rec[f]) == n, f
    assert np.degrees(np.abs(tr.e1[sc.sim.n_samples // 2:]).max()) < 2.0  # it tracks


def test_episode_stats_reads_n_from_the_signals_and_refuses_none():
    t = np.zeros(0)
    none = np.zeros((0, 4))
    empty = {"t": t, "e1": none, "k_a": none, "k_b": none, "u": none, "saturated": none}
    st = episode_stats(empty)
    assert st.n_joints == 4 and st.samples == 0
    assert summarize([st], "x", "baseline", "s", 1e-4)["rmse_deg"] == [None] * 4
    flat = {"t": t, "e1": t, "k_a": t, "k_b": t, "u": t, "saturated": t}
    with pytest.raises(ValueError, match=r"must be \(samples, n joints\)"):
        episode_stats(flat)  # it used to be taken for 3 joints


def _plain_env(sc, **kw):
    return gym.make("PlanarBLF-v0", scenario=sc, observer=make_observer("leso", nominal=sc.arm), reward_weights={},
                    **kw)


def test_the_baseline_policy_drives_an_arm_of_2_links():
    from baselines.controllers import ControllerGains
    from baselines.policies import BaselinePolicy

    sc = joint_scenario(2, duration=0.05)
    env = _plain_env(sc, control_period=1e-4)
    pol = BaselinePolicy("proposed", gains=ControllerGains(K1=20.0, K2=45.0, nominal=sc.arm), env=env)
    assert pol.n == 2
    o, _ = env.reset(seed=0)
    assert o.shape == (len(observation_layout(2)),) and env.action_space.shape == (2,)
    for _ in range(500):
        a, _ = pol.predict(o)
        assert a.shape == (2,) and a.dtype == np.float32
        o, _, term, trunc, info = env.step(a)
        assert not term
        assert info["e1"].shape == (2,)
    assert trunc
    m = info["episode_metrics"]
    assert len(m["rmse_deg"]) == 2 and m["violating_samples"] == 0 and not m["diverged"]
    # a batch of observations gives a batch of actions
    assert pol.predict(np.stack([o, o]))[0].shape == (2, 2)
    # the paper's law (3 links) refuses this env by name, and the 2-link law refuses a 3-link observation
    with pytest.raises(ValueError, match="models an arm of 3 links, the env's has 2"):
        BaselinePolicy("proposed", env=env)
    with pytest.raises(ValueError, match="an arm of 2 links"):
        pol.predict(np.zeros(len(observation_layout(2)) - 1, dtype=np.float32))


def test_the_floor_policy_acts_at_4_links():
    sc = joint_scenario(4, duration=0.5)
    pol = make_policy("floor", nominal=sc.arm)
    assert pol.n == 4 and pol.params.Kp == (19600.0,) * 4  # its gain, the same on every joint
    env = _plain_env(sc, terminate_on_violation=False, **pol.env_kwargs)
    o, _ = env.reset(seed=0)
    ix = observation_index(4, False, ())
    assert o.shape == (max(s.stop for s in ix.values()),) == env.observation_space.shape
    assert env.action_space.shape == (4,)
    while True:
        a, _ = pol.predict(o)
        assert a.shape == (4,)
        o, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    m = info["episode_metrics"]
    assert trunc and not m["diverged"] and len(m["rmse_deg"]) == 4 and m["samples"] == sc.sim.n_samples


def test_the_agents_helpers_follow_n():
    from agents.adversarial import sequences
    from agents.episodes import _ZeroResidual
    from agents.eval_tables import table
    from agents.falsify import space
    from blf_gym.envs.scenarios import check_variations

    for n in (2, 4):
        seqs = sequences(5, n)
        assert len(seqs) == 2 ** n + 23 and all(a.shape == (5, n) for a in seqs.values())
        assert len({tuple(seqs[k][0]) for k in seqs if k.startswith("sat")}) == 2 ** n  # every sign pattern
        assert [k for k in space(n=n) if k.startswith("initial_error")] == [f"initial_error_{j}" for j in range(n)]
        assert check_variations({"initial_error": 0.01}, n)["initial_error"] == (0.01,) * n
        assert _ZeroResidual(n).predict(np.zeros((3, 7)))[0].shape == (3, n)
    assert len(sequences(5)) == 31 and len(space()) == len(space(n=3))  # the paper's arm by default
    assert _ZeroResidual().n == 3
    with pytest.raises(ValueError, match="per-joint variation 'initial_error' needs n_links"):
        check_variations({"initial_error": 0.01})
    # blf-eval's console table: a column per joint of the records
    one = np.ones((3, 4))
    rec = summarize([episode_stats({"t": np.arange(3.0), "e1": 0.01 * one, "k_a": one, "k_b": one, "u": one,
                                    "saturated": 0 * one})],
                    "x", "baseline", "s", 1e-4)
    head = table([rec]).splitlines()[0]
    assert "RMSE j1 j2 j3 j4" in " ".join(head.split()) and "0.5730" in table([rec])


# a bare 3-joint default: `_N = 3`, `... else 3`, `n: int = 3`, `n_links: int = 3` (the paper's data
# is marked on its line with "# paper:")
_BARE_THREE = re.compile(r"\b_N\s*=\s*3\b|\belse\s+3\b|\b(?:n|n_links|n_joints)\s*:\s*int\s*=\s*3\b")


def test_the_grep_catches_what_it_is_for():
    assert _BARE_THREE.search("_N = 3") and _BARE_THREE.search("n = x.shape[1] if x.ndim == 2 else 3")
    assert _BARE_THREE.search("def f(n: int = 3) -> None:") and _BARE_THREE.search("    n_links: int = 3,")
    assert not _BARE_THREE.search("_N = 30") and not _BARE_THREE.search("level: int = 3")


def test_no_bare_three_joint_default_in_the_python_layer():
    found = []
    for top in ("baselines", "agents", "blf_gym/envs", "blf_gym/results"):
        for path in sorted((ROOT / top).rglob("*.py")):
            for i, line in enumerate(path.read_text().splitlines(), 1):
                if _BARE_THREE.search(line) and "# paper:" not in line:
                    found.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not found, "3 joints assumed (take n from the scenario, or mark the paper's data '# paper:'):\n" + \
        "\n".join(found)
