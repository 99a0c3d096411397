"""The block protocol of blf_gym.plugins.blocks, as a user would use it, and the refusal of bad plug-ins.

A user's own law is written below as a plain Python function over named signals (its parameter
names), declared as a ``Controller`` with a frozen, unit-carrying parameter dataclass, and run in
the compiled closed loop. Every bad plug-in of the protocol's list is refused with a ValueError
that names it and the problem, before numba sees it.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, field

import numpy as np
import pytest

from blf_gym.plugins.blocks import Controller, Observer, connect, gravity
from blf_gym.plugins.registry import available_controllers, make_controller, make_observer
from blf_gym.model.params import ArmParams, preset
from blf_gym.kernel.simulate import ClosedLoop, simulate

KP, KD = 50.0, 1.0  # N m/rad, N m s/rad


@dataclass(frozen=True)
class PDGains:
    Kp: float = field(default=KP, metadata={"unit": "N m/rad"})
    Kd: float = field(default=KD, metadata={"unit": "N m s/rad"})


def pd_gravity(y, x2_hat, q_d, qd_d, Kp, Kd, nominal, work, u_law):
    """u = -Kp (y - q_d) - Kd (x2_hat - qd_d) + G(y): output feedback only, never qd_true."""
    n = y.shape[0]
    g = work[:n]
    gravity(nominal, g)
    for i in range(n):
        u_law[i] = -Kp * (y[i] - q_d[i]) - Kd * (x2_hat[i] - qd_d[i]) + g[i]


def _mypd() -> Controller:
    return Controller("mypd", pd_gravity, PDGains())


def _gravity_by_hand(q: np.ndarray, arm: ArmParams = ArmParams()) -> np.ndarray:
    """G(q) = dV/dq for point masses at the distal link ends (docs/model.md section 1), one config per row.

    V = g sum_i m_i y_i with y_i = sum_{j<=i} l_j sin(theta_j), theta_j = q_1 + ... + q_j, so
    dV/dq_k = g sum_{j>=k} l_j cos(theta_j) sum_{i>=j} m_i.
    """
    l, m, g = np.array(arm.lengths), np.array(arm.masses), arm.gravity
    theta = np.cumsum(q, axis=-1)
    mass_beyond = np.cumsum(m[::-1])[::-1]
    terms = g * l * mass_beyond * np.cos(theta)
    return np.cumsum(terms[..., ::-1], axis=-1)[..., ::-1]


@pytest.fixture(scope="module")
def runs():
    sc = preset("paper-0.1hz", duration=2.0)
    return simulate(sc, controller=_mypd()), simulate(sc, controller="proposed")


def test_gravity_by_hand_matches_a_two_link_textbook_formula():
    # n = 2: G1 = (m1 + m2) g l1 c1 + m2 g l2 c12, G2 = m2 g l2 c12
    arm = ArmParams(lengths=(0.7, 0.4), masses=(1.5, 0.8), gravity=9.81)
    q = np.array([0.3, -1.1])
    c1, c12 = np.cos(0.3), np.cos(0.3 - 1.1)
    want = [(1.5 + 0.8) * 9.81 * 0.7 * c1 + 0.8 * 9.81 * 0.4 * c12, 0.8 * 9.81 * 0.4 * c12]
    np.testing.assert_allclose(_gravity_by_hand(q, arm), want, rtol=1e-14)


@pytest.mark.slow
def test_user_law_runs_in_the_closed_loop(runs):
    mine, _ = runs
    assert not mine.diverged, mine.message
    assert mine.controller == "mypd"
    assert mine.t.shape == (2000,)
    assert np.all(np.isfinite(mine.u))
    assert not np.any(mine.saturated)


def test_recorded_torque_is_the_users_formula(runs):
    mine, _ = runs
    k = np.array([0, 1, 7, 250, 999, 1500, 1999])
    y, q_ref, qd_ref, x2_hat = mine.y[k], mine.q_ref[k], mine.qd_ref[k], mine.x2_hat[k]
    want = -KP * (y - q_ref) - KD * (x2_hat - qd_ref) + _gravity_by_hand(y)
    np.testing.assert_allclose(mine.u_law[k], want, rtol=0, atol=1e-9)
    # no residual and no clipping: the commanded torque is the law's
    np.testing.assert_array_equal(mine.u[k], mine.u_law[k])
    # at t = 0 the arm starts on the reference at rest and the observer at [q(0), 0, 0], so the
    # law's output is -Kd * (0 - qd_d(0)) + G(q(0))
    assert mine.t[0] == 0.0
    np.testing.assert_allclose(mine.x2_hat[0], 0.0, atol=0)
    np.testing.assert_allclose(mine.u_law[0], KD * mine.qd_ref[0] + _gravity_by_hand(mine.q[0]), atol=1e-9)


def test_user_pd_tracks_worse_than_the_proposed_law(runs):
    mine, proposed = runs
    rmse_mine = np.sqrt(np.mean(mine.e1 ** 2, axis=0))
    rmse_prop = np.sqrt(np.mean(proposed.e1 ** 2, axis=0))
    assert np.all(rmse_mine > rmse_prop), (np.degrees(rmse_mine), np.degrees(rmse_prop))
    assert rmse_mine.mean() > 2.0 * rmse_prop.mean()


def test_make_controller_passes_an_object_through_and_rejects_unknown_names():
    mine = _mypd()
    assert make_controller(mine) is mine
    assert mine.gains.dtype == np.float64 and mine.gains.tolist() == [KP, KD]
    assert mine.param_layout == {"Kp": (0, None), "Kd": (1, None)}
    with pytest.raises(ValueError) as exc:
        make_controller("nonexistent")
    msg = str(exc.value)
    assert "nonexistent" in msg
    for name in ("bc", "lesobc", "proposed", "none"):
        assert repr(name) in msg, name


def test_registered_controllers_are_available():
    names = available_controllers()
    for name in ("bc", "lesobc", "proposed", "none"):
        assert name in names
        assert isinstance(make_controller(name), Controller)
    assert make_controller("bc").full_state is True
    assert make_controller("proposed").full_state is False
    assert list(make_controller("proposed").outputs) == ["u_law", "z1", "z2_hat", "barrier"]


# ---------------------------------------------------------------------------------------------
# bad plug-ins: refused with a ValueError naming the plug-in and the problem


def _refused(match, build):
    with pytest.raises(ValueError, match=match) as exc:
        build()
    # one message about the plug-in, not a traceback out of the generated glue or numba's typing
    assert "glue" not in str(exc.value) and "Traceback" not in str(exc.value) and "\n" not in str(exc.value)
    return str(exc.value)


def test_a_wrong_signature_is_refused():
    def star(*signals):
        pass

    def default(y, u_law=None):
        pass

    msg = _refused("plain positional", lambda: Controller("star", star))
    assert "'star'" in msg
    _refused("has a default", lambda: Controller("dflt", default))
    _refused("Python function", lambda: Controller("notfn", 3.0))


def test_a_signal_no_block_provides_is_refused_at_connection():
    # a law that reads x3_hat, paired with an observer that has only x1_hat and x2_hat
    def reads_x3(y, x3_hat, u_law):
        for i in range(y.shape[0]):
            u_law[i] = -x3_hat[i]

    def two_state(y, x1_hat, x2_hat, d_x1_hat, d_x2_hat):
        for i in range(y.shape[0]):
            d_x1_hat[i] = x2_hat[i] + 100.0 * (y[i] - x1_hat[i])
            d_x2_hat[i] = 2500.0 * (y[i] - x1_hat[i])

    law = Controller("needs_x3", reads_x3)
    hgo = Observer("hgo2", two_state, {"x1_hat": "n", "x2_hat": "n"})
    msg = _refused("no block provides", lambda: connect(law, hgo, 3))
    assert "'needs_x3'" in msg and "'x3_hat'" in msg and "'hgo2'" in msg
    _refused("no block provides", lambda: ClosedLoop([preset("paper-0.1hz")], law, hgo))
    # with the LESO, which has x3_hat, the same law connects
    connect(law, make_observer("leso"), 3)


def test_a_wrong_state_size_is_refused():
    def upd(y, d_s):
        pass

    def out(y, u_law):
        for i in range(y.shape[0]):
            u_law[i] = 0.0

    _refused("size", lambda: Controller("neg", out, states={"s": -1}, update=upd))
    _refused("size", lambda: Controller("weird", out, states={"s": "n^2"}, update=upd))
    _refused("no update", lambda: Controller("noupd", out, states={"s": "n"}))
    _refused("declares no states", lambda: Controller("noupd", out, update=upd))
    bad_init = Controller("badinit", out, states={"s": "n"}, update=upd, initial_state=lambda y0, n: np.zeros(2))
    _refused("initial_state must return 3", lambda: ClosedLoop([preset("paper-0.1hz")], bad_init))
    _refused("declares no states", lambda: Observer("empty", upd, {}))


def test_a_wrong_output_shape_or_an_unwritten_output_is_refused():
    def short(y, u_law):
        u_law[:] = np.zeros(2)  # two entries for three joints

    def partial(y, u_law):
        u_law[0] = 1.0  # the other joints never written

    def returns(y, u_law):
        for i in range(y.shape[0]):
            u_law[i] = 0.0
        return u_law

    msg = _refused("failed on a trial call", lambda: connect(Controller("short", short), make_observer("leso"), 3))
    assert "'short'" in msg
    msg = _refused("unwritten", lambda: connect(Controller("partial", partial), make_observer("leso"), 3))
    assert "[1, 2]" in msg
    _refused("returns nothing", lambda: connect(Controller("returns", returns), make_observer("leso"), 3))
    _refused("u_law", lambda: Controller("no_torque", short, outputs={"z": "n"}))


def test_parameters_must_be_a_frozen_dataclass_with_units():
    def out(y, Kp, u_law):
        for i in range(y.shape[0]):
            u_law[i] = Kp

    @dataclass
    class Loose:
        Kp: float = field(default=1.0, metadata={"unit": "N m/rad"})

    @dataclass(frozen=True)
    class NoUnit:
        Kp: float = 1.0

    @dataclass(frozen=True)
    class Text:
        Kp: str = field(default="high", metadata={"unit": "-"})

    _refused("frozen", lambda: Controller("loose", out, Loose()))
    _refused("carries no unit", lambda: Controller("nounit", out, NoUnit()))
    _refused("number", lambda: Controller("text", out, Text()))
    _refused("frozen dataclass", lambda: Controller("dict", out, {"Kp": 1.0}))


def test_reading_the_commanded_torque_in_the_output_is_refused():
    def out(y, u, u_law):
        for i in range(y.shape[0]):
            u_law[i] = u[i]

    _refused("'u'", lambda: connect(Controller("loop", out), make_observer("leso"), 3))


@pytest.mark.slow
def test_code_numba_cannot_compile_is_reported_against_the_plug_in():
    def out(y, u_law):
        names = {"a": 1.0}  # a dict of Python objects: fine in Python, not in the kernel
        for i in range(y.shape[0]):
            u_law[i] = names["a"] * 0.0 + str(i).__len__() * 0.0

    msg = _refused("could not be compiled by numba", lambda: ClosedLoop([preset("paper-0.1hz", duration=0.01)],
                                                                        Controller("pyobj", out)))
    assert "'pyobj'" in msg


def _imports_none_of(setup: str, roots: tuple[str, ...]) -> None:
    """Run ``setup`` in a fresh interpreter; fail if any module under ``roots`` got imported."""
    code = (f"import sys; {setup}; bad = sorted(m for m in sys.modules if m.split('.')[0] in {roots!r}); "
            "assert not bad, bad")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr


def test_blf_gym_does_not_import_controllers_or_learning_libraries():
    _imports_none_of("import blf_gym, blf_gym.kernel.simulate, blf_gym.results.metrics, blf_gym.plugins.registry",
                     ("baselines", "agents", "torch", "stable_baselines3", "ray", "jax", "sbx"))


def test_the_training_and_evaluation_commands_do_not_import_ray_or_jax():
    # the sweep and jax extras are optional: blf-train and blf-eval import them only for an
    # algorithm that needs them (listing the registered algorithms loads none)
    _imports_none_of("import agents.train, agents.evaluate, agents.loading; agents.loading.available_algorithms(); "
                     "agents.train._parser()", ("ray", "jax", "sbx"))


def test_blf_reproduce_module_does_not_import_torch():
    # baselines.reproduce's docstring: torch and stable-baselines3 are never imported on this path
    _imports_none_of("import baselines.reproduce", ("agents", "torch", "stable_baselines3"))


def test_an_observer_serves_any_controller_whose_signals_it_provides():
    # no pairing list: the signals decide, so an observer built from the LESO's parts serves a
    # controller of its own author's, and a list of names is no longer accepted
    leso = make_observer("leso")
    mine = Observer("mine", leso.rhs, leso.states, leso.params)
    assert connect(_mypd(), mine, 3).observer is mine
    with pytest.raises(TypeError, match="pairs_with"):
        Observer("mine", leso.rhs, leso.states, leso.params, pairs_with=("bc",))


OLD_PATHS = ("params", "dynamics", "simulate", "blocks", "registry", "envcore", "env", "metrics", "vmath",
             "core", "controller")
"""Flat modules of blf_gym 0.1 before the sub-packages (CHANGELOG.md maps each to its new path)."""


@pytest.mark.parametrize("name", OLD_PATHS)
def test_the_old_flat_module_paths_are_gone(name):
    # no shims: an old path fails at import, so nothing keeps working by accident on a stale name
    code = f"import blf_gym.{name}"
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode != 0 and "ModuleNotFoundError" in p.stderr, p.stderr
