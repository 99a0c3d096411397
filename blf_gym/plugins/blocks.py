"""The closed loop as declared blocks connected by named signals (docs/extending.md).

Three kinds of block make the loop: the plant (:data:`PLANT`, built in), an :class:`Observer` and
a :class:`Controller` (which may ship :class:`ResidualFilter` blocks for a learned residual). Each
is declared with

* its own state size, as named parts (``states={"x1_hat": "n", "x2_hat": "n"}``; a size is an
  ``int`` or ``"n"``, ``"2n"``, ... for a multiple of the number of joints);
* a frozen parameter dataclass whose numeric fields carry their unit in the field's metadata
  (``field(default=..., metadata={"unit": "1/s"})``), packed for the kernel in field order;
* named input and output signals: a plug-in function's *parameter names* are the signals it reads
  and the outputs it writes.

A plug-in is plain Python: functions over numpy arrays, which the package compiles with numba into
the closed-loop kernel (specialised per controller, observer and number of joints, cached on disk).
They write their results into the output arrays they are handed and return nothing. Write them as
loops over joints and use the operators below for the nominal model; they must not allocate
(``work`` is scratch).

Signals a function may read (n joints; "scalar" means a float)::

    t                         scalar   time, s
    y                         (n,)     measured joint angles, rad (true angles + noise)
    qd_true, q_true           (n,)     true joint velocities, rad/s, and angles, rad (a full-state law;
                                       results say so; filters' monitors read them)
    u_max                     scalar   the actuator's torque limit, N m
    q_d, qd_d, qdd_d          (n,)     joint reference and its derivatives, rad, rad/s, rad/s^2
    k_a, k_a_dot, k_a_ddot    scalar   upper error bound and its rates, rad, rad/s, rad/s^2
    k_b, k_b_dot, k_b_ddot    scalar   lower error bound (the error stays above -k_b) and rates
    nominal                   array    the nominal model at y: pass it to the operators below
    work                      (W,)     scratch, W = 2 n^2 + 12 n entries, undefined on entry
    <observer state names>    (size,)  the observer's states (LESO: x1_hat, x2_hat, x3_hat)
    <controller outputs>      (size,)  after Controller.output: u_law and the law's extra outputs
    u                         (n,)     torque commanded to the actuators (law + residual, after the
                                       limit, before the dead-zone); after Controller.output
    residual                  (n,)     the raw residual, N m: ResidualFilter.apply only
    <filter outputs>          (size,)  after ResidualFilter.apply: r_f and its other outputs
    <own parameter fields>    (len,) or scalar, from the block's parameter dataclass
    <own state names>, state  the block's own state (its parts, or all of it)

and write::

    Controller.output: its declared outputs (u_law, N m, always, plus any extras)
    Observer.rhs, Controller.update: dstate (all) or d_<state name> (a part), the time derivative

Nominal-model operators at the measured angles (compiled; call them from a plug-in)::

    mass_times(nominal, w, out)      out = M(y) w
    mass_solve(nominal, b, out)      out = M(y)^-1 b
    coriolis_times(nominal, v, w, out)  out = C(y, v) w   (C(y, x2_hat) alpha1 with v = x2_hat)
    gravity(nominal, out)            out = G(y)

Order inside one stage evaluation (every ODE3 stage): plant measurement y, reference and bounds,
the nominal model at y, ``Controller.output``, the residual filter if any, the actuator
(``u = sat(u_law + r_f)``, r_f the residual or its filtered form), the
plant's acceleration, ``Observer.rhs``, ``Controller.update``. A bad plug-in is refused with a
``ValueError`` naming it and the problem when it is built or first connected (:func:`connect`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import inspect
import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.model.dynamics import (abs_trig_into, coriolis_times_into, gravity_into, ldl_factor_into, ldl_solve_factored,
                       mass_matrix_into)
from blf_gym.results.io import cache_dir
from blf_gym.model.params import ArmParams
from blf_gym.jit.codegen import load_module
from blf_gym.jit.layout import BOUND, NOMINAL, PLUGIN_WORK, REF, at, links_of, part
from blf_gym.model.reference import REFERENCE_SIGNALS

__all__ = [
    "BASE_SIGNALS", "Block", "PLANT", "Controller", "Observer", "ResidualFilter", "Connection", "connect", "mass_times",
    "mass_solve", "coriolis_times", "gravity", "nominal_acceleration", "nominal_length", "work_length", "units",
    "parse_filter_spec",
]

# ---------------------------------------------------------------------------------------------
# the nominal model signal and its operators


_NOM_M, _NOM_G, _NOM_TRIG, _NOM_L, _NOM_ARM, _NOM_SCRATCH = (NOMINAL.start(p) for p in NOMINAL)
_SIZE_M, _SIZE_G, _SIZE_TRIG, _SIZE_L, _SIZE_ARM, _SIZE_SCRATCH = (NOMINAL.size(p) for p in NOMINAL)
_NOM_TOTAL, _WORK_TOTAL = NOMINAL.total, PLUGIN_WORK.total


@njit(cache=True, error_model="numpy", inline="always")
def work_length(n):
    """Length of the ``work`` scratch signal for n joints (:data:`blf_gym.jit.layout.PLUGIN_WORK`)."""
    return at(_WORK_TOTAL, n)


@njit(cache=True, error_model="numpy", inline="always")
def model_length(n):
    """Length of the model part of the ``nominal`` signal (:data:`blf_gym.jit.layout.NOMINAL` up to
    the arm): [M(y) row-major (n^2), G(y) (n), cos and sin of the absolute link angles (2n), the
    LDL^T factor of M(y) (n^2)]."""
    return at(_NOM_ARM, n)


@njit(cache=True, error_model="numpy", inline="always")
def nominal_length(n):
    """Length of the ``nominal`` signal: the model part, the nominal arm (2n + 1, ArmParams.pack())
    and 4n entries of scratch for the operators."""
    return at(_NOM_TOTAL, n)


@njit(cache=True, error_model="numpy", inline="always")
def nominal_model_into(y, arm, model, work):
    """Fill the model part of a ``nominal`` signal, [M(y), G(y), cos theta, sin theta, LDL^T factor of
    M(y)], for the arm ``arm`` (ArmParams.pack()). ``work`` needs ``n`` entries."""
    n = y.shape[0]
    abs_trig_into(y, part(model, _NOM_TRIG, _SIZE_TRIG, n))
    nominal_terms_into(arm, model, work)


@njit(cache=True, error_model="numpy", inline="always")
def nominal_terms_into(arm, model, work):
    """The rest of :func:`nominal_model_into` once the model's cos and sin entries are in place:
    M, G and the LDL^T factor (the closed loop computes the trigonometry apart, see
    :mod:`blf_gym.kernel.simulate`)."""
    n = links_of(arm.shape[0], _SIZE_ARM)
    trig = part(model, _NOM_TRIG, _SIZE_TRIG, n)
    mass_matrix_into(trig, arm, part(model, _NOM_M, _SIZE_M, n), work)
    gravity_into(trig, arm, part(model, _NOM_G, _SIZE_G, n), work)
    ldl_factor_into(part(model, _NOM_M, _SIZE_M, n), part(model, _NOM_L, _SIZE_L, n))


@njit(cache=True, error_model="numpy", inline="always")
def mass_times(nominal, w, out):
    """out = M(y) w, the nominal inertia at the measured angles."""
    n = w.shape[0]
    m0 = at(_NOM_M, n)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += nominal[m0 + i * n + j] * w[j]
        out[i] = acc


@njit(cache=True, error_model="numpy", inline="always")
def mass_solve(nominal, b, out):
    """out = M(y)^-1 b (from the LDL^T factor, no division)."""
    n = b.shape[0]
    ldl_solve_factored(part(nominal, _NOM_L, _SIZE_L, n), b, out)


@njit(cache=True, error_model="numpy", inline="always")
def coriolis_times(nominal, v, w, out):
    """out = C(y, v) w with C the Christoffel-symbol Coriolis matrix of the nominal arm."""
    n = v.shape[0]
    coriolis_times_into(part(nominal, _NOM_TRIG, _SIZE_TRIG, n), v, w, part(nominal, _NOM_ARM, _SIZE_ARM, n), out,
                        part(nominal, _NOM_SCRATCH, _SIZE_SCRATCH, n))


@njit(cache=True, error_model="numpy", inline="always")
def gravity(nominal, out):
    """out = G(y), the nominal gravity torque at the measured angles."""
    n = out.shape[0]
    g0 = at(_NOM_G, n)
    for i in range(n):
        out[i] = nominal[g0 + i]


@njit(cache=True, error_model="numpy", inline="always")
def nominal_acceleration(nominal, v, u, c, g, out):
    """out = M(y)^-1 (u - C(y, v) v - G(y)): the nominal arm's acceleration at the measured angles,
    velocity ``v`` and torque ``u`` (the LESO's model and the CBF filter's law acceleration); ``c``
    and ``g`` are scratch of n entries (they end holding u - C v - G and G)."""
    n = out.shape[0]
    coriolis_times(nominal, v, v, c)
    gravity(nominal, g)
    for i in range(n):
        c[i] = u[i] - c[i] - g[i]
    mass_solve(nominal, c, out)


# ---------------------------------------------------------------------------------------------
# declarations

BASE_SIGNALS: dict[str, tuple[str, str, str]] = {
    # name: (size, unit, meaning)
    "t": ("scalar", "s", "time"),
    "y": ("n", "rad", "measured joint angles"),
    "qd_true": ("n", "rad/s", "true joint velocities (full state)"),
    "q_d": ("n", "rad", "joint reference"),
    "qd_d": ("n", "rad/s", "its first derivative"),
    "qdd_d": ("n", "rad/s^2", "its second derivative"),
    "k_a": ("scalar", "rad", "upper error bound"),
    "k_a_dot": ("scalar", "rad/s", "its rate"),
    "k_a_ddot": ("scalar", "rad/s^2", "its second derivative"),
    "k_b": ("scalar", "rad", "lower error bound (e1 > -k_b)"),
    "k_b_dot": ("scalar", "rad/s", "its rate"),
    "k_b_ddot": ("scalar", "rad/s^2", "its second derivative"),
    "q_true": ("n", "rad", "true joint angles (for monitors; a law reading it is full-state)"),
    "u_max": ("scalar", "N m", "the actuator's torque limit"),
    "nominal": ("model", "-", "nominal model at y, for the operators"),
    "work": ("work", "-", "scratch"),
}
"""Signals every plug-in function may read, whatever the other blocks are."""
_RESERVED = {*BASE_SIGNALS, "u", "state", "dstate", "residual"}
_SIZE = re.compile(r"^\s*(\d*)\s*\*?\s*n\s*$")


@functools.lru_cache(maxsize=256)
def _offsets(owner: str, parts: tuple[tuple[str, Any], ...], n: int) -> tuple[tuple[str, tuple[int, int]], ...]:
    """(name, (offset, size)) of each declared part, in order, for n joints."""
    out, o = [], 0
    for k, s in parts:
        m = size_of(s, n, owner)
        out.append((k, (o, m)))
        o += m
    return tuple(out)


def size_of(spec: Any, n: int, what: str) -> int:
    """An entry count from its declaration: an int >= 0, or ``"n"``, ``"2n"``, ``"2*n"``."""
    if isinstance(spec, bool) or not isinstance(spec, (int, np.integer, str)):
        raise ValueError(f"{what}: a size must be an int or a multiple of n such as 'n' or '2n', got {spec!r}")
    if isinstance(spec, str):
        m = _SIZE.match(spec)
        if not m:
            raise ValueError(f"{what}: a size must be an int or a multiple of n such as 'n' or '2n', got {spec!r}")
        return int(m.group(1) or 1) * n
    if spec < 0:
        raise ValueError(f"{what}: a size must be >= 0, got {spec}")
    return int(spec)


def units(params: Any) -> dict[str, str]:
    """Each packed field of a parameter dataclass (class or instance) and its unit."""
    return {f.name: f.metadata.get("unit", "") for f in dataclasses.fields(params) if f.name != "nominal"}


def _pack_params(owner: str, params: Any) -> tuple[np.ndarray, dict[str, tuple[int, int | None]]]:
    """Packed float64 gains and, per field, (offset, length or None for a scalar)."""
    if params is None:
        return np.zeros(0), {}
    if not (dataclasses.is_dataclass(params) and not isinstance(params, type)):
        raise ValueError(f"{owner}: params must be an instance of a frozen dataclass, got {params!r}")
    if not params.__dataclass_params__.frozen:
        raise ValueError(f"{owner}: params must be a frozen dataclass (@dataclass(frozen=True)), "
                         f"{type(params).__name__} is not")
    values: list[float] = []
    layout: dict[str, tuple[int, int | None]] = {}
    for f in dataclasses.fields(params):
        v = getattr(params, f.name)
        if f.name == "nominal":
            if not isinstance(v, ArmParams):
                raise ValueError(f"{owner}: params.nominal must be a blf_gym.model.params.ArmParams, got {v!r}")
            continue
        if "unit" not in f.metadata:
            raise ValueError(f"{owner}: parameter field {f.name!r} of {type(params).__name__} carries no unit; "
                             f"declare it with field(default=..., metadata={{'unit': '...'}}) ('-' if none)")
        if f.name in _RESERVED:
            raise ValueError(f"{owner}: parameter field {f.name!r} shadows a signal of that name; rename it")
        arr = np.asarray(v, dtype=object)
        flat = arr.ravel().tolist() if arr.ndim else [v]
        if any(isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)) for x in flat):
            raise ValueError(f"{owner}: parameter field {f.name!r} must be a number or a tuple of numbers, got {v!r}")
        if not all(math.isfinite(float(x)) for x in flat):
            raise ValueError(f"{owner}: parameter field {f.name!r} must be finite, got {v!r}")
        layout[f.name] = (len(values), None if arr.ndim == 0 else len(flat))
        values += [float(x) for x in flat]
    return np.array(values, dtype=np.float64), layout


def _fn_params(owner: str, fn: Any) -> list[str]:
    """The parameter names of a plug-in function (a plain function or a numba dispatcher)."""
    py = getattr(fn, "py_func", fn)
    if not inspect.isfunction(py):
        raise ValueError(f"{owner} must be a Python function (or a numba @njit function), got {fn!r}")
    sig = inspect.signature(py)
    names = []
    for p in sig.parameters.values():
        if p.kind not in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            raise ValueError(f"{owner}: parameter {p.name!r} must be a plain positional parameter (no *args, "
                             "**kwargs or keyword-only parameters); its name is the signal it reads or writes")
        if p.default is not p.empty:
            raise ValueError(f"{owner}: parameter {p.name!r} has a default; every parameter is a signal")
        names.append(p.name)
    return names


def _parts(owner: str, what: str, parts: Mapping[str, Any] | None) -> dict[str, Any]:
    parts = dict(parts or {})
    for name, spec in parts.items():
        if not (isinstance(name, str) and name.isidentifier()):
            raise ValueError(f"{owner}: {what} names must be identifiers, got {name!r}")
        if name in _RESERVED:
            raise ValueError(f"{owner}: {what} {name!r} shadows a signal of that name; rename it")
        size_of(spec, 3, f"{owner}: {what} {name!r}")
    return parts


@dataclass(frozen=True, eq=False)
class Block:
    """A declaration: a block's states, parameter dataclasses, inputs and outputs (documentation and
    checks; the plant's arithmetic is built into the kernel)."""

    name: str
    states: Mapping[str, Any]
    params: tuple[type, ...]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    doc: str = ""


def _plant_block() -> Block:
    from blf_gym.model.params import ArmParams, DeadZoneParams, ForceParams, FrictionParams

    return Block("planar_arm", {"q": "n", "qd": "n"}, (ArmParams, FrictionParams, DeadZoneParams, ForceParams),
                 inputs=("u",), outputs=("y", "qd_true"),
                 doc="M(q) qdd = H(u) - C(q, qd) qd - G(q) - J(q)^T f_ext - tau_fric(qd)  (docs/model.md section 1)")


PLANT = _plant_block()
"""The plant: joint angles and velocities; torque in, measured angles (and, for full-state laws, the
true velocities) out."""


class _PluginBase:
    kind = "block"

    def _init_common(self, name: Any, params: Any, nominal: Any) -> None:
        if not (isinstance(name, str) and name.isidentifier()):
            raise ValueError(f"{self.kind} name must be an identifier string, got {name!r}")
        owner = f"{self.kind} {name!r}"
        gains, layout = _pack_params(owner, params)
        if nominal is None:
            nominal = getattr(params, "nominal", None) if params is not None else None
            nominal = nominal if nominal is not None else ArmParams()
        if not isinstance(nominal, ArmParams):
            raise ValueError(f"{owner}: nominal must be a blf_gym.model.params.ArmParams, got {nominal!r}")
        object.__setattr__(self, "gains", gains)
        object.__setattr__(self, "param_layout", layout)
        object.__setattr__(self, "nominal", nominal)

    @property
    def owner(self) -> str:
        return f"{self.kind} {self.name!r}"

    def _layout(self, parts: Mapping[str, Any], n: int) -> dict[str, tuple[int, int]]:
        """(offset, size) of each declared part, in order, for n joints (a new dict; the offsets
        are worked out once per declaration and n, since every reset asks for them)."""
        items = tuple(parts.items())
        try:
            return dict(_offsets(self.owner, items, n))
        except TypeError:  # an unhashable size: size_of refuses it by name
            return dict(_offsets.__wrapped__(self.owner, items, n))

    def state_size(self, n: int) -> int:
        return sum(m for _, m in self._layout(self.states, n).values())

    def state_offsets(self, n: int) -> dict[str, tuple[int, int]]:
        return self._layout(self.states, n)

    def output_size(self, n: int) -> int:
        return sum(m for _, m in self._layout(getattr(self, "outputs", {}), n).values())

    def output_offsets(self, n: int) -> dict[str, tuple[int, int]]:
        return self._layout(getattr(self, "outputs", {}), n)


@dataclass(frozen=True, eq=False)
class Controller(_PluginBase):
    """An inner control law: ``output`` writes ``u_law`` (and any extra outputs) from signals;
    with states, ``update`` writes their derivative, integrated by the same ODE3 stages as the
    plant and the observer."""

    name: str
    output: Callable
    params: Any = None
    outputs: Mapping[str, Any] = field(default_factory=lambda: {"u_law": "n"})
    states: Mapping[str, Any] = field(default_factory=dict)
    update: Callable | None = None
    initial_state: Callable | None = None
    """(y0 (n,), n) -> the controller's state at t = 0; default zeros."""
    nominal: ArmParams | None = None
    """The controller's model of the arm; default ``params.nominal`` or the paper's."""
    filters: Mapping[str, Callable[..., "ResidualFilter"]] = field(default_factory=dict)
    """Residual filters shipped with the law, by name: factories of :class:`ResidualFilter`
    (selected with the env's ``residual_filter``)."""
    kind = "controller"

    def __post_init__(self) -> None:
        self._init_common(self.name, self.params, self.nominal)
        o = self.owner
        outs = _parts(o, "output", self.outputs)
        if "u_law" not in outs or outs["u_law"] != "n":
            raise ValueError(f"{o}: outputs must declare the torque 'u_law' with size 'n', got {dict(self.outputs)}")
        object.__setattr__(self, "outputs", outs)
        object.__setattr__(self, "states", _parts(o, "state", self.states))
        clash = set(outs) & set(self.states) | (set(outs) | set(self.states)) & set(self.param_layout)
        if clash:
            raise ValueError(f"{o}: the names {sorted(clash)} are declared twice (outputs, states, parameters)")
        if self.states and self.update is None:
            raise ValueError(f"{o} has states {list(self.states)} but no update function for their derivative")
        if self.update is not None and not self.states:
            raise ValueError(f"{o} has an update function but declares no states")
        if self.initial_state is not None and not callable(self.initial_state):
            raise ValueError(f"{o}: initial_state must be callable (y0, n) -> state, got {self.initial_state!r}")
        # public: the glue and the kernel's specialisation read which signals each function takes
        object.__setattr__(self, "output_params", _fn_params(f"{o}.output", self.output))
        object.__setattr__(self, "update_params", _fn_params(f"{o}.update", self.update) if self.update else [])

    @property
    def full_state(self) -> bool:
        """True if the law reads the true state (BC reads the velocity); results say so."""
        return bool({"qd_true", "q_true"} & {*self.output_params, *self.update_params})

    def make_filter(self, spec: "str | ResidualFilter | None") -> "ResidualFilter | None":
        """The residual filter ``spec`` names, or the object itself. A name is one of :attr:`filters`,
        optionally with parameters, ``"barrier:handback=0.0033,m0=0.3"`` (:func:`parse_filter_spec`):
        a string, so env arguments and results record it as given."""
        if spec is None or isinstance(spec, ResidualFilter):
            return spec
        name, kwargs = parse_filter_spec(spec)
        if name not in self.filters:
            raise ValueError(f"residual_filter must be None or one of the filters shipped with {self.owner}, "
                             f"{sorted(self.filters)} (or a blf_gym.plugins.blocks.ResidualFilter), got {spec!r}")
        f = self.filters[name](**kwargs)
        if not isinstance(f, ResidualFilter):
            raise ValueError(f"{self.owner}: filter {name!r} did not produce a blf_gym.plugins.blocks.ResidualFilter")
        return f

    def initial(self, y0: np.ndarray) -> np.ndarray:
        n = y0.shape[0]
        m = self.state_size(n)
        if self.initial_state is None:
            return np.zeros(m)
        x = np.asarray(self.initial_state(y0.copy(), n), dtype=np.float64).ravel()
        if x.shape != (m,) or not np.all(np.isfinite(x)):
            raise ValueError(f"{self.owner}: initial_state must return {m} finite numbers, got {x!r}")
        return x


@dataclass(frozen=True, eq=False)
class Observer(_PluginBase):
    """A state observer: ``rhs`` writes the derivative of its states from signals (any number of
    states, declared as named parts that later blocks read by name)."""

    name: str
    rhs: Callable
    states: Mapping[str, Any]
    params: Any = None
    initial_state: Callable | None = None
    """(y0 (n,), n) -> the observer's state at t = 0; default: y0 in the first state part of size n,
    zeros elsewhere."""
    nominal: ArmParams | None = None
    kind = "observer"

    def __post_init__(self) -> None:
        self._init_common(self.name, self.params, self.nominal)
        o = self.owner
        states = _parts(o, "state", self.states)
        if not states:
            raise ValueError(f"{o} declares no states")
        object.__setattr__(self, "states", states)
        clash = set(states) & set(self.param_layout)
        if clash:
            raise ValueError(f"{o}: the names {sorted(clash)} are both states and parameters")
        if self.initial_state is not None and not callable(self.initial_state):
            raise ValueError(f"{o}: initial_state must be callable (y0, n) -> state, got {self.initial_state!r}")
        object.__setattr__(self, "rhs_params", _fn_params(f"{o}.rhs", self.rhs))

    def initial(self, y0: np.ndarray) -> np.ndarray:
        n = y0.shape[0]
        m = self.state_size(n)
        if self.initial_state is not None:
            x = np.asarray(self.initial_state(y0.copy(), n), dtype=np.float64).ravel()
            if x.shape != (m,) or not np.all(np.isfinite(x)):
                raise ValueError(f"{self.owner}: initial_state must return {m} finite numbers, got {x!r}")
            return x
        x = np.zeros(m)
        for off, size in self.state_offsets(n).values():
            if size == n:
                x[off : off + n] = y0
                break
        return x


@dataclass(frozen=True, eq=False)
class ResidualFilter(_PluginBase):
    """A filter between a learned residual and the actuator, shipped with a law: ``apply`` reads the
    raw residual (``residual``, N m) and any signal, and writes the filtered one ``r_f`` and its other
    declared outputs. Two output names are monitors the kernel counts per integration step:
    ``breach`` (> 0 when the filter's own condition does not hold) and ``assumptions`` (< 0.5 when an
    assumption of its guarantee fails). Monitors may read the true state (q_true, qd_true); ``r_f``
    must be computed from measured signals."""

    name: str
    apply: Callable
    params: Any = None
    outputs: Mapping[str, Any] = field(default_factory=lambda: {"r_f": "n"})
    nominal: ArmParams | None = None
    kind = "filter"
    states = {}

    def __post_init__(self) -> None:
        self._init_common(self.name, self.params, self.nominal)
        o = self.owner
        outs = _parts(o, "output", self.outputs)
        if "r_f" not in outs or outs["r_f"] != "n" or next(iter(outs)) != "r_f":
            raise ValueError(f"{o}: outputs must declare the filtered residual 'r_f' first, with size 'n'")
        for mon in ("breach", "assumptions"):
            if mon in outs and outs[mon] != 1:
                raise ValueError(f"{o}: the monitor output {mon!r} must have size 1")
        object.__setattr__(self, "outputs", outs)
        object.__setattr__(self, "apply_params", _fn_params(f"{o}.apply", self.apply))



def _zero_output(u_law):
    for i in range(u_law.shape[0]):
        u_law[i] = 0.0


NO_CONTROLLER = Controller("none", _zero_output)
"""The inner controller of plain mode: zero torque, so the agent's action is the whole input."""

# ---------------------------------------------------------------------------------------------
# connecting blocks: signal resolution, generated glue, trial call

_GLUE_ARGS = "t, y, q, qd, xo, xc, ref, bnd, nom, og, cg, fg, u, cout, r, fout, umax, dxo, dxc, work"
"""The fixed signature of the generated glue functions the kernel calls."""


@dataclass(frozen=True, eq=False)
class Connection:
    """A controller and an observer connected for n joints: sizes, offsets and the compiled glue."""

    controller: Controller
    observer: Observer
    n: int
    n_obs: int
    n_ctrl: int
    n_out: int
    obs_offsets: dict
    out_offsets: dict
    module: Any
    digest: str
    filter: "ResidualFilter | None" = None
    n_fout: int = 0
    fout_offsets: dict = field(default_factory=dict)

    @property
    def res_filter(self):
        return self.module.res_filter

    @property
    def ctrl_output(self):
        return self.module.ctrl_output

    @property
    def obs_rhs(self):
        return self.module.obs_rhs

    @property
    def ctrl_update(self):
        return self.module.ctrl_update

    def observer_signal(self, name: str) -> tuple[int, int] | None:
        """(offset in the observer state, size) of an observer state part, or None."""
        return self.obs_offsets.get(name)




def _expr(role: str, name: str, ctrl: Controller, obs: Observer, filt: "ResidualFilter | None", n: int,
          fn_owner: str) -> str:
    """The glue's expression for a parameter ``name`` of a function of ``role`` (ctrl_out: the law's
    output, filter: the residual filter, obs: the observer's rhs, ctrl_upd: the law's update)."""
    simple = {"t": "t", "y": "y", "q_true": "q", "qd_true": "qd", "nominal": "nom", "work": "work", "u_max": "umax"}
    if name in simple:
        return simple[name]
    if name in REF:
        off, m = REF.offsets(n)[name]
        return f"_fixed(ref, {off}, {m})"
    if name in BOUND:
        return f"bnd[{BOUND.index(name)}]"
    own = {"ctrl_out": ctrl, "ctrl_upd": ctrl, "obs": obs, "filter": filt}[role]
    x, dx, g = {"ctrl_out": ("xc", "dxc", "cg"), "ctrl_upd": ("xc", "dxc", "cg"), "obs": ("xo", "dxo", "og"),
                "filter": (None, None, "fg")}[role]
    if name in own.param_layout:
        off, length = own.param_layout[name]
        return f"{g}[{off}]" if length is None else f"_fixed({g}, {off}, {length})"
    own_states = own.state_offsets(n) if x else {}
    if name == "state" and x:
        return x
    if name in own_states:
        off, m = own_states[name]
        return f"_fixed({x}, {off}, {m})"
    if x and (name == "dstate" or (name.startswith("d_") and name[2:] in own_states)):
        if role == "ctrl_out":
            raise ValueError(f"{fn_owner} cannot write {name!r}: state derivatives are written by the update function")
        if name == "dstate":
            return dx
        off, m = own_states[name[2:]]
        return f"_fixed({dx}, {off}, {m})"
    outs = ctrl.output_offsets(n)
    if name in outs:
        off, m = outs[name]
        return f"_fixed(cout, {off}, {m})"
    fouts = filt.output_offsets(n) if filt is not None else {}
    if name in fouts:
        if role in ("filter", "obs", "ctrl_upd"):
            off, m = fouts[name]
            return f"_fixed(fout, {off}, {m})"
        raise ValueError(f"{fn_owner} reads {name!r}, which the residual filter computes after it")
    if name == "residual":
        if role == "filter":
            return "r"
        raise ValueError(f"{fn_owner} reads 'residual', which only a residual filter reads")
    if name == "u":
        if role in ("obs", "ctrl_upd"):
            return "u"
        raise ValueError(f"{fn_owner} reads 'u', the commanded torque, which is computed from its own output; "
                         "read it in the controller's update (or the observer)")
    obs_states = obs.state_offsets(n)
    if role != "obs" and name in obs_states:
        off, m = obs_states[name]
        return f"_fixed(xo, {off}, {m})"
    if role == "filter" and name in ctrl.param_layout:
        off, length = ctrl.param_layout[name]
        return f"cg[{off}]" if length is None else f"_fixed(cg, {off}, {length})"
    offer = set(BASE_SIGNALS) | set(own_states) | set(own.param_layout) | set(outs) | set(fouts)
    if role != "obs":
        offer |= set(obs_states)
    raise ValueError(f"{fn_owner} reads the signal {name!r}, which no block provides with observer {obs.name!r} "
                     f"(its states: {list(obs_states)}); signals on offer: {sorted(offer)}")


def _call(role: str, fn_name: str, params: list[str], ctrl: Controller, obs: Observer, filt: Any, n: int,
          owner: str) -> str:
    args = ", ".join(_expr(role, p, ctrl, obs, filt, n, owner) for p in params)
    return f"    return {fn_name}({args})\n"


def glue_digest(src: str, functions: Sequence[Any], path: tuple[str, ...] | None = None) -> str:
    """The 12-hex-digit digest in a glue module's name: the generated source, each plug-in function's
    name and the import closure of the module that defines it (:func:`blf_gym.jit.sources.function_digest`:
    what it calls in other files, such as the CBF filter's use of ``baselines.filters``, included),
    and this module's closure. ``path``: resolve the modules in a copy on disk (the tests)."""
    h = hashlib.sha1(src.encode())
    for fn in functions:
        if fn is not None:
            py = getattr(fn, "py_func", fn)
            h.update(f"{py.__module__}.{py.__qualname__}".encode())
            h.update(sources.function_digest(fn, path).encode())
    h.update(sources.digest(__name__, path=path).encode())
    return h.hexdigest()[:12]


def parse_filter_spec(spec: Any) -> tuple[str, dict[str, float]]:
    """``"NAME"`` or ``"NAME:key=value,key=value"`` -> (NAME, {key: float(value)}): how a residual
    filter is named with its parameters in env arguments and on the command line. ValueError names
    the part that is not of that form."""
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"residual_filter must be a filter's name, optionally 'NAME:key=value,...', got {spec!r}")
    name, _, rest = spec.partition(":")
    kwargs: dict[str, float] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = item.partition("=")
        try:
            if not eq or not key.strip():
                raise ValueError
            kwargs[key.strip()] = float(value)
        except ValueError:
            raise ValueError(f"residual_filter {spec!r}: {item!r} is not key=number "
                             "(the form is 'NAME:key=value,key=value')") from None
    return name.strip(), kwargs


_MAX_INLINE_ARGS = 30
"""CPython passes a call of more arguments as one tuple (``f(*args)``), which numba cannot inline."""


def _compiled(fn: Any):
    """The plug-in function as a numba function inlined into the kernel (called, not inlined, when it
    reads more than :data:`_MAX_INLINE_ARGS` signals)."""
    py = getattr(fn, "py_func", fn)
    inline = "always" if py.__code__.co_argcount <= _MAX_INLINE_ARGS else "never"
    return njit(inline=inline, error_model="numpy", cache=False)(py)


_CONNECTIONS: dict[tuple, Connection] = {}


def connect(controller: Controller, observer: Observer, n: int,
            residual_filter: "ResidualFilter | None" = None) -> Connection:
    """Check that every signal each function reads is provided, generate and compile the glue, and
    run each function once on trial inputs; ValueError naming the plug-in and the problem.
    ``residual_filter`` goes between the residual and the actuator (in plain mode the kernel hands it
    the agent's whole torque minus the law's, a runtime flag of :class:`blf_gym.kernel.simulate.ClosedLoop`)."""
    c, o, f = controller, observer, residual_filter
    if not isinstance(c, Controller):
        raise ValueError(f"connect: controller must be a blf_gym.plugins.blocks.Controller, got {c!r}")
    if not isinstance(o, Observer):
        raise ValueError(f"connect: observer must be a blf_gym.plugins.blocks.Observer, got {o!r}")
    if not (f is None or isinstance(f, ResidualFilter)):
        raise ValueError(f"connect: residual_filter must be None or a blf_gym.plugins.blocks.ResidualFilter, got {f!r}")
    if c.nominal.n_links != n or o.nominal.n_links != n:
        raise ValueError(f"{c.owner} and {o.owner} must model an arm of {n} links like the plant")
    if not np.array_equal(c.nominal.pack(), o.nominal.pack()):
        raise ValueError(f"{c.owner} and {o.owner} must share one nominal model")
    # the compiled code depends on the functions and the layouts, not on the parameter values
    fkey = None if f is None else (f.name, f.apply, tuple(f.outputs.items()), tuple(f.param_layout.items()))
    key = (c.name, c.output, c.update, tuple(c.outputs.items()), tuple(c.states.items()),
           tuple(c.param_layout.items()), o.name, o.rhs, tuple(o.states.items()), tuple(o.param_layout.items()), n,
           fkey)
    if key in _CONNECTIONS:
        return _CONNECTIONS[key]
    bodies = {
        "ctrl_output": _call("ctrl_out", "_c_output", c.output_params, c, o, f, n, f"{c.owner}.output"),
        "res_filter": _call("filter", "_f_apply", f.apply_params, c, o, f, n, f"{f.owner}.apply") if f else None,
        "obs_rhs": _call("obs", "_o_rhs", o.rhs_params, c, o, f, n, f"{o.owner}.rhs"),
        "ctrl_update": (_call("ctrl_upd", "_c_update", c.update_params, c, o, f, n, f"{c.owner}.update") if c.update
                        else None),
    }
    src = _glue_source(f"{c.owner} + {o.owner}" + (f" + {f.owner}" if f else "") + f", n = {n}", bodies)
    digest = glue_digest(src, (c.output, c.update, o.rhs, f.apply if f else None))
    fname = "" if f is None else f"__{f.name}"
    module = load_module(f"glue_{c.name}__{o.name}{fname}__n{n}__{digest}", src, cache_dir(), {
        "_c_output": _compiled(c.output), "_o_rhs": _compiled(o.rhs),
        "_c_update": _compiled(c.update) if c.update else None,
        "_f_apply": _compiled(f.apply) if f else None,
    })
    conn = Connection(c, o, n, o.state_size(n), c.state_size(n), c.output_size(n), o.state_offsets(n),
                      c.output_offsets(n), module, digest, f, f.output_size(n) if f else 0,
                      f.output_offsets(n) if f else {})
    _trial(conn)
    _CONNECTIONS[key] = conn
    return conn


GLUE_FUNCTIONS = ("ctrl_output", "res_filter", "obs_rhs", "ctrl_update")
"""The generated glue's functions, each with the signature :data:`_GLUE_ARGS`, inlined by the kernel."""


def _glue_source(what: str, bodies: dict[str, str | None]) -> str:
    """The glue module's source (:mod:`blf_gym.jit.codegen`): the plug-ins' functions bound by name,
    then each glue function, a call of one with its signals cut out of the kernel's arrays."""
    head = [f'"""The glue between the closed loop\'s kernel and {what}: generated by',
            'blf_gym.plugins.blocks.connect (do not edit; the digest in the name is its sources\')."""',
            "", "from numba import njit", "", "from blf_gym.jit.codegen import bound",
            "from blf_gym.jit.views import fixed as _fixed", ""]
    head += [f'{name} = bound(__name__, "{name}")' for name in ("_c_output", "_o_rhs", "_c_update", "_f_apply")]
    parts = ["\n".join(head) + "\n"]
    for fn in GLUE_FUNCTIONS:
        parts.append(f'\n\n@njit(inline="always", error_model="numpy", cache=True)\ndef {fn}({_GLUE_ARGS}):\n'
                     + (bodies[fn] or "    pass\n"))
    return "".join(parts)


def _py_fixed(w, start, length):
    return w[start : start + length]


def _trial(conn: Connection) -> None:
    """Run the three functions once in Python on plausible inputs (the paper's start), so that a wrong
    output shape, an unwritten output or an exception is reported against the plug-in."""
    from blf_gym.model.bounds import bounds_into
    from blf_gym.model.params import joint_scenario, preset
    from blf_gym.model.reference import joint_reference

    c, o, n = conn.controller, conn.observer, conn.n
    # the paper's start for 3 links, a joint-space task's for any other n
    sc = preset("paper-0.1hz") if n == 3 else joint_scenario(n)
    q_d, qd_d, qdd_d = joint_reference(0.0, sc)
    y = q_d + 0.01
    ref = np.zeros(REF.length(n))
    for name, value in zip(REFERENCE_SIGNALS, (q_d, qd_d, qdd_d)):
        ref[REF.slice(name, n)] = value
    bnd = np.zeros(BOUND.length())
    bounds_into(0.0, sc.bounds.pack(), bnd)
    nom = np.zeros(nominal_length(n))
    nominal_model_into(y, c.nominal.pack(), nom, np.zeros(work_length(n)))
    arm = c.nominal.pack()
    nom[NOMINAL.slice("arm", n)] = arm
    xo = o.initial(y)
    xc = c.initial(y)
    qd = qd_d.copy()
    f = conn.filter
    u = np.zeros(n)
    cout = np.full(conn.n_out, np.nan)
    fout = np.full(conn.n_fout, np.nan)
    dxo = np.full(conn.n_obs, np.nan)
    dxc = np.full(conn.n_ctrl, np.nan)
    r = np.full(n, 1.0)
    work = np.zeros(work_length(n))
    fg = f.gains if f is not None else np.zeros(0)
    args = (0.0, y, q_d.copy(), qd, xo, xc, ref, bnd, nom, o.gains, c.gains, fg, u, cout, r, fout,
            float(sc.sim.max_torque), dxo, dxc, work)
    calls = [("ctrl_output", f"{c.owner}.output", cout, "its outputs")]
    if f is not None:
        calls.append(("res_filter", f"{f.owner}.apply", fout, "its outputs"))
    calls += [("obs_rhs", f"{o.owner}.rhs", dxo, "dstate"), ("ctrl_update", f"{c.owner}.update", dxc, "dstate")]
    for fname, owner, out, label in calls:
        glue = getattr(conn.module, fname).py_func
        g = glue.__globals__
        saved = {k: g[k] for k in ("_c_output", "_o_rhs", "_c_update", "_f_apply", "_fixed") if g.get(k) is not None}
        try:
            for k, v in saved.items():
                g[k] = v.py_func if k != "_fixed" else _py_fixed
            ret = glue(*args)
        except Exception as exc:  # noqa: BLE001 (reported against the plug-in)
            raise ValueError(f"{owner} failed on a trial call at the paper's start: {type(exc).__name__}: {exc}") from exc
        finally:
            g.update(saved)
        if ret is not None:
            raise ValueError(f"{owner} returned {ret!r}; a plug-in writes its results into the arrays it is "
                             "handed and returns nothing")
        if fname == "ctrl_output":
            np.clip(cout[:n], -1e300, 1e300, out=u)
        elif fname == "res_filter":
            np.clip(cout[:n] + fout[:n], -1e300, 1e300, out=u)
        bad = np.flatnonzero(~np.isfinite(out))
        if bad.size:
            raise ValueError(f"{owner} left entries {bad.tolist()} of {label} unwritten or non-finite on a trial "
                             f"call at the paper's start (size {out.size})")
