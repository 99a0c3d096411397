"""Bad input to the environments: every constructor argument, variation, reset option, seed and
action that is not accepted raises ValueError naming the field and what it accepts.

Booleans are booleans and numbers are numbers: a bool where a number is expected, a string where a
bool or a number is expected, a complex number, a container, NaN and infinities are refused;
numpy integer and float scalars are numbers (and ``numpy.bool_`` a bool) and are accepted.

(a) The examples of issue 10 ("Parameters"), one by one. (b) Hypothesis property tests: for every
env keyword argument and every reset option / variation knob, bad values of every kind are refused
with the field's name in the message, and good values from the documented ranges are accepted and
reach the env. Construction does not run the simulation, so these are fast.
"""

from __future__ import annotations

import dataclasses
import math
import re
import warnings

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import blf_gym  # noqa: F401  (registers the ids)
from blf_gym.plugins.registry import available_controllers
from blf_gym.envs.envcore import RewardWeights
from blf_gym.envs.env import PlanarBLFEnv
from blf_gym.model.params import DT_MIN, SimParams, usable_cores
from blf_gym.envs.scenarios import SAFE_RANGES, VARIATIONS
from blf_gym.kernel.simulate import CHANNELS
from blf_gym.envs.vector import PlanarBLFVectorEnv

FAST = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ZERO = np.zeros(3, dtype=np.float32)
SCENARIOS = ("paper-0.1hz", "paper-0.5hz", "randomized")
CONTROLLERS = tuple(available_controllers())


def assert_refused(call, field: str):
    """``call()`` raises ValueError whose message names ``field`` and says what is accepted."""
    with pytest.raises(ValueError) as exc:
        call()
    msg = str(exc.value)
    assert field in msg, (field, msg)
    assert re.search(r"\bmust\b|accepted", msg), msg
    return msg


# ---------------------------------------------------------------------------------------------
# (a) the examples of the issue


@pytest.mark.parametrize("env_id, kwargs, field", [
    ("PlanarBLF-v0", {"terminate_on_violation": "False"}, "terminate_on_violation"),
    ("PlanarBLF-v0", {"terminate_on_violation": 0}, "terminate_on_violation"),
    ("PlanarBLFResidual-v0", {"residual_scale": True}, "residual_scale"),
    ("PlanarBLF-v0", {"max_torque": True}, "max_torque"),
    ("PlanarBLF-v0", {"duration": True}, "duration"),
    ("PlanarBLF-v0", {"variations": 0}, "variations"),
    ("PlanarBLF-v0", {"variations": "payload"}, "variations"),
    # strings for numbers
    ("PlanarBLFResidual-v0", {"residual_scale": "2.0"}, "residual_scale"),
    ("PlanarBLF-v0", {"control_period": "0.01"}, "control_period"),
    ("PlanarBLF-v0", {"duration": "1"}, "duration"),
    ("PlanarBLF-v0", {"max_torque": "150"}, "max_torque"),
    ("PlanarBLF-v0", {"dt": "1e-4"}, "dt"),
    ("PlanarBLF-v0", {"angle_noise_std": "0"}, "angle_noise_std"),
    ("PlanarBLF-v0", {"variations": {"frequency": "0.2"}}, "frequency"),
    ("PlanarBLF-v0", {"reward_weights": {"tracking": "1"}}, "tracking"),
    ("PlanarBLF-v0", {"variations": {"initial_error": [0.01, 0.02]}}, "initial_error"),
    ("PlanarBLF-v0", {"reward_weights": {"bogus": 1.0}}, "reward_weights"),
    ("PlanarBLF-v0", {"scenario": ["paper-0.1hz"]}, "scenario"),
    ("PlanarBLF-v0", {"controller": ["proposed"]}, "controller"),
])
def test_issue_examples_at_construction(env_id, kwargs, field):
    assert_refused(lambda: gym.make(env_id, **kwargs), field)
    assert_refused(lambda: gym.make_vec(env_id, num_envs=2, **kwargs), field)


def test_a_too_small_dt_is_blamed_on_dt():
    for make in (lambda: gym.make("PlanarBLF-v0", dt=1e-300), lambda: PlanarBLFEnv(dt=1e-9)):
        msg = assert_refused(make, "dt")
        assert msg.startswith("PlanarBLFEnv: dt must be") and f"{DT_MIN:g}" in msg, msg
        assert "control_period" not in msg, msg
    msg = assert_refused(lambda: SimParams(dt=1e-300), "SimParams.dt")
    assert f"{DT_MIN:g}" in msg
    assert SimParams(dt=1e-6).steps_per_sample == 1000  # small but above the floor is fine


@pytest.mark.parametrize("options, field", [
    ({"frequency": "0.2"}, "frequency"),
    ({"initial_error": [0.01, 0.02]}, "initial_error"),
    ({"payload": True}, "payload"),
    ({"force": 1j}, "force"),
])
def test_issue_examples_at_reset(options, field):
    env = gym.make("PlanarBLF-v0")
    assert_refused(lambda: env.reset(options=options), field)
    venv = gym.make_vec("PlanarBLF-v0", num_envs=2)
    assert_refused(lambda: venv.reset(options=options), field)
    for bad in (0, "payload", [("payload", 0.1)]):  # options must be a mapping
        assert_refused(lambda: env.reset(options=bad), "options")
        assert_refused(lambda: venv.reset(options=bad), "options")


def test_vector_env_reset_accepts_numpy_integer_seeds():
    venv = PlanarBLFVectorEnv(num_envs=2, scenario="randomized")
    scenarios = []
    for seed in (3, np.int64(3), np.uint16(3), [3, 4], [np.int32(3), np.int64(4)], (3, 4), np.array([3, 4])):
        venv.reset(seed=seed)
        scenarios.append(list(venv.core.scenarios))
    assert all(s == scenarios[0] for s in scenarios)
    venv.reset(seed=[None, 7])
    env = PlanarBLFEnv(scenario="randomized")
    env.reset(seed=np.int64(4))
    assert env.scenario == scenarios[0][1]  # arm 1 of seed 3 is the single env of seed 4


def test_single_env_reset_accepts_numpy_integer_seeds_through_gym_make():
    env = gym.make("PlanarBLF-v0", scenario="randomized")
    _, info = env.reset(seed=np.int64(3))
    _, info_int = env.reset(seed=3)
    assert info["scenario"] == info_int["scenario"]
    _, info_other = env.reset(seed=np.uint8(4))
    assert info_other["scenario"] != info["scenario"]


@pytest.mark.parametrize("seed, field", [
    (True, "seed"), (np.True_, "seed"), (-1, "seed"), (1.0, "seed"), ("3", "seed"), (1 + 0j, "seed"),
    ([1], "seed"), ([1, 2, 3], "seed"), ([1, True], "seed[1]"), ([1, -2], "seed[1]"),
    ([1, 2.0], "seed[1]"), (["1", 2], "seed[0]"), ({"a": 1}, "seed"),
])
def test_vector_env_reset_refuses_bad_seeds(seed, field):
    venv = PlanarBLFVectorEnv(num_envs=2)
    msg = assert_refused(lambda: venv.reset(seed=seed), field)
    assert msg.startswith("PlanarBLFVectorEnv.reset:")


@pytest.mark.parametrize("seed", [True, False, np.True_, -1, np.int64(-5), 1.0, np.float64(2.0), "3",
                                  [1], 1j])
def test_single_env_reset_refuses_bad_seeds(seed):
    env = gym.make("PlanarBLF-v0")
    msg = assert_refused(lambda: env.reset(seed=seed), "seed")
    assert msg.startswith("PlanarBLFEnv.reset: seed must be")


@pytest.mark.parametrize("action, what", [
    (np.array([0.1 + 0.5j, 0.0, 0.0]), "complex"),
    (np.array([0.1 + 0.0j, 0.0, 0.0]), "complex"),  # even with a zero imaginary part
    ([0.1j, 0.0, 0.0], "complex"),
    (np.array([True, False, True]), "bool"),
    (["0.1", "0", "0"], "<U"),
    ([0.1, None, 0.0], "object"),
    ([[0.1, 0.2], 0.0, 0.0], "real numbers"),  # ragged
    ([np.nan, 0.0, 0.0], "finite"),
    ([0.0, 0.0], "shape"),
])
def test_bad_actions_raise_and_do_not_advance_the_arm(action, what):
    env = PlanarBLFEnv()
    env.reset(seed=0)
    X = env.core.loop.X.copy()
    with pytest.raises(ValueError, match="action") as exc:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no ComplexWarning: refused, not truncated
            env.step(action)
    assert what in str(exc.value)
    np.testing.assert_array_equal(env.core.loop.X, X)
    venv = PlanarBLFVectorEnv(num_envs=2)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="action") as exc:
        venv.step([action, action])
    assert what in str(exc.value)


@pytest.mark.parametrize("action", [ZERO, np.zeros(3), np.zeros(3, dtype=np.int64), [0, 0, 1],
                                    (0.5, -0.5, 0.0), np.zeros(3, dtype=np.float16)])
def test_real_actions_of_any_real_dtype_are_accepted(action):
    env = PlanarBLFEnv(terminate_on_violation=False)
    env.reset(seed=0)
    env.step(action)
    assert env.core.loop.time[0] == pytest.approx(0.01)


# ---------------------------------------------------------------------------------------------
# (b) property tests: strategies of bad values

BOOLS = st.sampled_from([True, False, np.True_, np.False_])
NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf, np.float64("nan"), np.float32("-inf")])
STRINGS = st.text(max_size=6) | st.sampled_from(["1", "0.01", "1e-4", "True", "False", "nan", "None"])
COMPLEX = (st.complex_numbers(max_magnitude=10.0, allow_nan=False, allow_infinity=False)
           | st.sampled_from([1 + 0j, np.complex128(0.01), np.complex64(2.0)]))
CONTAINERS = (st.lists(st.floats(0.001, 1.0), max_size=4) | st.tuples(st.floats(0.001, 1.0))
              | st.dictionaries(st.text(max_size=3), st.integers(), max_size=2)
              | st.builds(lambda x: np.array([x]), st.floats(0.001, 1.0)) | st.just(object()))
NOT_A_NUMBER = BOOLS | STRINGS | COMPLEX | CONTAINERS


def bad_real(lo: float, lo_open: bool, hi: float | None = None, none_ok: bool = True, extra=None):
    """Values refused where a finite real number >= lo (> lo if lo_open), <= hi is expected."""
    below = st.floats(max_value=lo, exclude_max=not lo_open, allow_nan=False)
    s = NOT_A_NUMBER | NON_FINITE | below | below.map(np.float64)
    if hi is not None:
        s = s | st.floats(min_value=hi, exclude_min=True, allow_nan=False)
    if not none_ok:
        s = s | st.none()
    if extra is not None:
        s = s | extra
    return s


NOT_A_BOOL = (st.integers(-2, 2) | st.floats(allow_nan=False) | STRINGS | st.none() | COMPLEX | CONTAINERS
              | st.sampled_from([np.int64(1), np.float64(0.0)]))


def bad_int(lo: int, none_ok: bool):
    s = (BOOLS | st.floats(allow_nan=True) | st.sampled_from([2.0, np.float64(1.0)]) | STRINGS | COMPLEX
         | CONTAINERS | st.integers(max_value=lo - 1) | st.integers(-(2**63), lo - 1).map(np.int64))
    return s if none_ok else s | st.none()


def bad_knob(name: str):
    """Values refused for a variation / reset option ``name`` (outside its safe range included)."""
    lo, hi = SAFE_RANGES[name]
    s = (NOT_A_NUMBER | NON_FINITE | st.none()
         | st.floats(max_value=lo, exclude_max=True, allow_nan=False)
         | st.floats(min_value=hi, exclude_min=True, allow_nan=False))
    if name == "initial_error":
        s = (s.filter(lambda v: not (isinstance(v, (list, tuple, np.ndarray)) and len(v) == 3))
             | st.lists(st.floats(-0.05, 0.05), min_size=0, max_size=6).filter(lambda v: len(v) != 3)
             | st.tuples(st.floats(-0.05, 0.05), st.sampled_from([True, "0.0", None, math.nan, 0.5, 1j]),
                         st.floats(-0.05, 0.05)))
    return s


def _bad_mapping(field: str, names, bad_value):
    """(value, field named in the message) for a mapping-valued argument."""
    return (
        st.tuples(st.integers() | STRINGS | BOOLS | st.lists(st.integers(), max_size=2) | COMPLEX,
                  st.just(field))
        | st.sampled_from(list(names)).flatmap(lambda k: bad_value(k).map(lambda v: ({k: v}, k)))
    )


def _unknown_key(field_for):
    return st.text(max_size=5).filter(lambda k: k not in VARIATIONS and k not in RW_FIELDS).map(
        lambda k: ({k: 1.0}, field_for(k)))


# every field of RewardWeights, read from the dataclass (a hand-written list missed ``score``, and
# Hypothesis then drew "score" as an unknown key that the env rightly accepts)
RW_FIELDS = tuple(f.name for f in dataclasses.fields(RewardWeights))


def bad_reward_field(name: str):
    if name in ("relative", "law_baseline"):
        return NOT_A_BOOL
    if name == "relative_cap":
        return bad_real(0.0, True, none_ok=False)
    return bad_real(0.0, False, none_ok=name == "alive")


BAD_KWARGS = {
    # kwarg: strategy of (value, field named in the message)
    "scenario": st.tuples(
        STRINGS.filter(lambda s: s not in SCENARIOS) | st.integers() | st.floats() | st.none() | BOOLS
        | CONTAINERS, st.just("scenario")),
    "controller": st.tuples(
        STRINGS.filter(lambda s: s not in CONTROLLERS) | st.integers() | st.floats() | BOOLS
        | CONTAINERS, st.just("controller")),
    "observer": st.tuples(
        STRINGS.filter(lambda s: s != "leso") | st.integers() | st.floats() | st.none() | BOOLS
        | CONTAINERS, st.just("observer")),
    "residual_scale": st.tuples(bad_real(0.0, True, none_ok=False), st.just("residual_scale")),
    "control_period": st.tuples(
        bad_real(0.0, True, hi=30.0, none_ok=False,
                 extra=st.sampled_from([0.0015, 0.00015, 0.0123, 2.5e-5, 1e-9])),
        st.just("control_period")),
    "privileged": st.tuples(NOT_A_BOOL, st.just("privileged")),
    "terminate_on_violation": st.tuples(NOT_A_BOOL, st.just("terminate_on_violation")),
    "record": st.tuples(NOT_A_BOOL, st.just("record")),
    "record_channels": st.tuples(
        STRINGS.filter(lambda s: s not in CHANNELS) | st.integers() | st.floats() | BOOLS
        | st.lists(STRINGS.filter(lambda s: s not in CHANNELS), min_size=1, max_size=2)
        | st.just(["e1", "e1"]) | st.lists(st.integers(), min_size=1, max_size=2)
        # a set or a dict has no order for the channels; a channel's own name is one name, not a list
        | st.sampled_from([{"u"}, {"u": 1}, "u", b"u", frozenset({"t"})]),
        st.just("record_channels")),
    "angle_noise_std": st.tuples(
        bad_real(0.0, False, extra=st.floats(min_value=2e-4, exclude_min=True, allow_nan=False)),
        st.just("angle_noise_std")),
    "duration": st.tuples(bad_real(0.0, True, extra=st.sampled_from([0.0015, 1e-4, 0.015, 29.9995])),
                          st.just("duration")),
    "max_torque": st.tuples(bad_real(0.0, True), st.just("max_torque")),
    "bound_scale": st.tuples(bad_real(1.0, False, hi=15.0, none_ok=False), st.just("bound_scale")),
    "level": st.tuples(bad_int(0, False) | st.integers(min_value=4), st.just("level")),
    # (a sequence of three numbers in (0, 150] is a valid per-joint scale, so the containers that
    # happen to be one are left out)
    "action_scale": st.tuples((bad_real(0.0, True, hi=150.0) | st.just([25.0, 25.0])).filter(
        lambda v: v != "law" and not (isinstance(v, (list, tuple)) and len(v) == 3 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and 0 < x <= 150 for x in v))),
        st.just("action_scale")),
    # with the env's default (score) reward every start time is refused, naming start_time; a
    # valid (low, high) pair would be refused for the same reason, so only values bad in themselves
    "start_time": st.tuples((bad_real(0.0, False, hi=29.99) | st.just([10.0, 5.0]) | st.just([1.0])).filter(
        lambda v: not (isinstance(v, (list, tuple)) and len(v) == 2 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and 0 <= x <= 29.99 for x in v)
            and v[0] <= v[1])),
        st.just("start_time")),
    "dt": st.tuples(bad_real(DT_MIN, False, extra=st.sampled_from([3e-4, 7e-5, 1.5e-3, 2e-3, 0.5])),
                    st.just("dt")),
    "variations": _bad_mapping("variations", VARIATIONS, bad_knob) | _unknown_key(repr),
    "reward_weights": (_bad_mapping("reward_weights", RW_FIELDS, bad_reward_field)
                       | _unknown_key(lambda k: "reward_weights")),
    "observation_extras": st.tuples(
        STRINGS | st.integers() | st.floats() | st.none() | BOOLS
        | st.lists(STRINGS.filter(lambda s: s not in ("u_law", "z2_hat")), min_size=1, max_size=2)
        | st.just(["u_law", "u_law"]) | st.lists(st.integers(), min_size=1, max_size=2),
        st.just("observation_extras")),
    "residual_filter": st.tuples(
        STRINGS.filter(lambda s: s != "barrier") | st.integers() | st.floats() | BOOLS | CONTAINERS,
        st.just("residual_filter")),
    # above the cores this process may use is refused too: extra threads only wait
    "threads": st.tuples(bad_int(1, none_ok=True) | st.integers(usable_cores() + 1, 10**6), st.just("threads")),
    "n_links": st.tuples(bad_int(2, none_ok=True) | st.integers(8, 10**6), st.just("n_links")),
    "render_mode": st.tuples(STRINGS.filter(lambda s: s not in ("rgb_array", "human")) | st.integers()
                             | BOOLS, st.just("render_mode")),
}


def test_every_constructor_argument_has_a_bad_value_strategy():
    import inspect

    from blf_gym.envs.envcore import EnvCore

    kwargs = {p for p in inspect.signature(EnvCore.__init__).parameters if p not in ("self", "single")}
    assert kwargs - {"num_envs"} | {"render_mode"} == set(BAD_KWARGS)


@pytest.mark.parametrize("kwarg", sorted(BAD_KWARGS))
@FAST
@given(data=st.data())
def test_property_bad_constructor_argument_is_a_value_error_naming_it(kwarg, data):
    value, field = data.draw(BAD_KWARGS[kwarg], label=kwarg)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complex number must not be truncated with a warning
        assert_refused(lambda: PlanarBLFEnv(**{kwarg: value}), field)
        if kwarg != "render_mode":
            assert_refused(lambda: PlanarBLFVectorEnv(num_envs=2, **{kwarg: value}), field)


@FAST
@given(value=bad_int(1, none_ok=False))
def test_property_bad_num_envs_is_a_value_error_naming_it(value):
    assert_refused(lambda: PlanarBLFVectorEnv(num_envs=value), "num_envs")


_ENV: dict[str, PlanarBLFEnv] = {}


def _shared_env() -> PlanarBLFEnv:
    if "env" not in _ENV:
        _ENV["env"] = PlanarBLFEnv()
    return _ENV["env"]


@pytest.mark.parametrize("knob", VARIATIONS)
@FAST
@given(data=st.data())
def test_property_bad_reset_option_is_a_value_error_naming_it(knob, data):
    env = _shared_env()
    value = data.draw(bad_knob(knob), label=knob)
    env.reset(seed=0)
    before = env.scenario
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert_refused(lambda: env.reset(options={knob: value}), knob)
    assert env.scenario is before  # a refused reset changes nothing


# ---------------------------------------------------------------------------------------------
# (b) property tests: good values are accepted and reach the env


def _as(draw, value: float, kinds=(float, np.float64)):
    return draw(st.sampled_from(kinds))(value)


def _good_knob(draw, name: str):
    lo, hi = SAFE_RANGES[name]
    if name == "initial_error" and draw(st.booleans()):
        e = [_as(draw, draw(st.floats(lo, hi))) for _ in range(3)]
        return draw(st.sampled_from([list, tuple, np.array]))(e)
    return _as(draw, draw(st.floats(lo, hi)))


@st.composite
def good_options(draw):
    names = draw(st.lists(st.sampled_from(VARIATIONS), unique=True, max_size=len(VARIATIONS)))
    return {k: _good_knob(draw, k) for k in names}


@st.composite
def good_kwargs(draw):
    kw: dict = {}
    maybe = lambda: draw(st.booleans())  # noqa: E731
    if maybe():
        kw["scenario"] = draw(st.sampled_from(SCENARIOS))
    if maybe():
        kw["controller"] = draw(st.sampled_from([None, "none", "proposed", "lesobc", "bc"]))
    if maybe():
        kw["residual_scale"] = _as(draw, draw(st.floats(1e-3, 1e3)), (float, np.float64, np.float32))
    if maybe():
        kw["residual_scale"] = draw(st.sampled_from([int, np.int64]))(draw(st.integers(1, 400)))
    cp = draw(st.sampled_from([0.001, 0.002, 0.005, 0.01, 0.02]))
    if maybe():
        kw["control_period"] = _as(draw, cp)
    for name in ("privileged", "terminate_on_violation", "record"):
        if maybe():
            kw[name] = draw(BOOLS)
    if maybe():
        kw["angle_noise_std"] = _as(draw, draw(st.floats(*SAFE_RANGES["angle_noise_std"])))
    if maybe():
        kw["duration"] = _as(draw, 0.02 * draw(st.integers(1, 1500)))
    if maybe():
        kw["max_torque"] = _as(draw, draw(st.floats(1.0, 1e3)), (float, np.float64, np.float32, int))
    if maybe():
        kw["dt"] = _as(draw, draw(st.sampled_from([1e-3, 5e-4, 2.5e-4, 2e-4, 1e-4, 5e-5])))
    if maybe():
        kw["variations"] = draw(good_options())
    if maybe():
        rw = {"tracking": _as(draw, draw(st.floats(0.0, 10.0))),
              "torque": _as(draw, draw(st.floats(0.0, 1.0))),
              "violation": _as(draw, draw(st.floats(0.0, 1e3))),
              "relative": draw(BOOLS), "relative_cap": _as(draw, draw(st.floats(0.1, 1e3)))}
        kw["reward_weights"] = RewardWeights(**rw) if maybe() else rw
    if maybe():
        kw["threads"] = draw(st.sampled_from([None, 1, np.int64(1), np.int32(2)]))
    if maybe():
        kw["render_mode"] = draw(st.sampled_from([None, "rgb_array"]))
    return kw


def _given(v):
    """The number a real argument stands for: a float32 (or float16) is the decimal it prints as
    (blf_gym.model.params.check_real), so np.float32(0.01) is 0.01; anything else its float."""
    if isinstance(v, np.floating) and v.dtype.itemsize < 8:
        return float(str(v))
    return float(v)


@FAST
@given(kw=good_kwargs())
def test_property_good_constructor_arguments_are_accepted_and_reach_the_env(kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = PlanarBLFEnv(**kw)
    core = env.core
    sim = core.sim
    if "residual_scale" in kw:
        assert core.residual_scale == _given(kw["residual_scale"])
    if "control_period" in kw:
        assert core.control_period == _given(kw["control_period"])
    for name in ("privileged", "terminate_on_violation", "record"):
        if name in kw:
            assert getattr(core, name) is bool(kw[name])
    for name in ("duration", "max_torque", "dt"):
        if name in kw:
            assert getattr(sim, name) == _given(kw[name])
    if "angle_noise_std" in kw:
        assert core.base.angle_noise_std == _given(kw["angle_noise_std"])
    if "variations" in kw and "frequency" in kw["variations"]:
        assert core.base.reference.frequency == _given(kw["variations"]["frequency"])
    if "reward_weights" in kw:
        rw = kw["reward_weights"]
        tracking = rw.tracking if isinstance(rw, RewardWeights) else rw["tracking"]
        assert core.weights.tracking == _given(tracking)


@FAST
@given(n=st.integers(1, 3), kind=st.sampled_from([int, np.int64, np.int32, np.uint8]))
def test_property_numpy_integer_num_envs_are_accepted(n, kind):
    assert PlanarBLFVectorEnv(num_envs=kind(n), threads=1).num_envs == n


@FAST
@given(options=good_options(), seed=st.integers(0, 2**32))
def test_property_good_reset_options_are_accepted_and_reach_the_scenario(options, seed):
    env = _shared_env()
    env.reset(seed=seed, options=options)
    sc = env.scenario
    base = env.core.base
    expect = {
        "frequency": sc.reference.frequency, "force": sc.force.wrench[0], "force_onset": sc.force.onset,
        "friction_scale": sc.friction.viscous / base.friction.viscous,
        "dead_zone_scale": sc.dead_zone.break_right / base.dead_zone.break_right,
        "payload": sc.arm.masses[2], "angle_noise_std": sc.angle_noise_std,
    }
    for k, v in options.items():
        if k == "initial_error":
            want = np.broadcast_to(np.asarray(v, dtype=float), (3,))
            np.testing.assert_array_equal(sc.initial_error, want)
        else:
            assert expect[k] == pytest.approx(float(v), rel=1e-12, abs=1e-15), k


@FAST
@given(seed=st.integers(0, 2**63 - 1), kind=st.sampled_from([int, np.int64, np.uint64]))
def test_property_integer_seeds_of_any_integer_type_are_accepted(seed, kind):
    env = _ENV.setdefault("randomized", PlanarBLFEnv(scenario="randomized"))
    env.reset(seed=kind(seed))
    a = env.scenario
    env.reset(seed=seed)
    assert env.scenario == a
