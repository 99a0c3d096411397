"""The closed loop: plant + observer + inner controller, integrated by fixed-step ODE3.

One compiled kernel serves everything: the reproduction (one arm, a whole 30 s episode per call),
the Gymnasium env (one arm, one agent period per call) and the vector env (N arms per call, split
over threads: the compiled kernel releases the GIL). Arms are stepped in blocks of lanes in
lockstep, laid out lanes innermost (:func:`lane_layout`): one lane by default, :data:`LANES` with
``ClosedLoop(lanes=LANES)``, where the per-arm code vectorises across arms (docs/model.md
section 6).

Integration (docs/model.md section 6): Bogacki-Shampine ODE3, fixed step h, with the law and the observer
evaluated at every stage on the measured angles y = q(stage) + noise (the noise sample is held
over a step). Constraints are checked after every step; trajectories and metrics use the 1 ms
grid. A step outside ODE3's stability region is detected from the method's embedded error
estimate, even when the actuator limit keeps the state finite.

**How a kernel is built: generated modules, one style for the kernel and the glue.** The kernel is
specialised per connection (controller, observer, residual filter, n) and block width, so that every
size, offset and plug-in call is a compile-time constant numba can inline and LLVM can unroll. Each
specialisation, the kernel here and the plug-ins' glue in :func:`blf_gym.plugins.blocks.connect`,
is Python source generated as text and imported from a file by :mod:`blf_gym.jit.codegen`:
:func:`build_source` writes a module that imports the helpers of :mod:`blf_gym.kernel.templates`,
assigns the build's constants (:data:`blf_gym.kernel.templates.BUILD_NAMES`), binds the glue,
writes the reward's per-sample sum from :data:`blf_gym.kernel.reward.TERMS`, and copies the source
of the templates. Why this style and not the two others we had (cloning the templates' function
objects with injected globals; ``exec`` of a string): a generated module is a file, so numba caches it
like any other (the file's name carries the digest of everything that went into it) and a person
can open, read, lint and step through exactly the code that runs; every name in it, and every name
in the templates (where the build's names are placeholders), resolves for a linter or an editor;
and nothing calls ``exec``. tests/test_codegen.py lints a generated kernel and glue with pyflakes.

State layout per arm, ``X[b]``: ``[q, qd, observer states, controller states]`` (5n with the LESO).
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import os
import sys
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit.codegen import load_module
from blf_gym.jit.layout import BOUNDS, CHANNELS, PLANT, REFERENCE, STATE, block_layout
from blf_gym.kernel import reward, templates
from blf_gym.kernel.reward import SUM_E2_JOINT
from blf_gym.kernel.status import (N_LAST, N_STATUS, ST_ASSUMPTION_FAILURES, ST_DIVERGED, ST_FILTER_BREACHES,
                                   ST_FIRST_VIOL, ST_SAT_STEPS, ST_STEPS, ST_VIOL_STEPS)
from blf_gym.kernel.templates import LANES, N_CHANNELS, ONCE_A_CALL, TEMPLATES
from blf_gym.model.params import Scenario, check_int, usable_cores
from blf_gym.plugins.blocks import Connection, Controller, Observer, ResidualFilter, connect
from blf_gym.plugins.registry import make_controller, make_observer
from blf_gym.results.io import cache_dir

__all__ = [
    "Batch",
    "CHANNELS",
    "ClosedLoop",
    "Trajectory",
    "SimulationDiverged",
    "simulate",
    "simulate_batch",
]
def lane_layout(n: int, n_obs: int, n_ctrl: int, n_out: int, n_fout: int, n_law_gains: int, n_obs_gains: int,
                n_filter_gains: int) -> dict[str, tuple[int, int]]:
    """The per-lane entries of a block of the batched kernel, name -> (offset, length) in lane
    entries (:func:`blf_gym.jit.layout.block_layout`; a block of L entries per lane holds
    ``L * LANES`` numbers), and ``"_total"``: (L, 0)."""
    pack = block_layout(n, n_obs, n_ctrl, n_out, n_fout, n_law_gains, n_obs_gains, n_filter_gains)
    return {**pack.offsets(n), "_total": (pack.length(n), 0)}



# ---------------------------------------------------------------------------------------------
# specialisation: a generated module per connection and width, compiled with a disk cache


def kernel_digest(conn: Connection) -> str:
    """The 10-hex-digit digest in a kernel's name: the sources of this module's import closure
    (:func:`blf_gym.jit.sources.digest`: the templates, every block they inline, every packed layout's
    declaration, found by following the imports, not from a list) and the connection's own digest
    (the plug-ins' closures and the generated glue, :func:`blf_gym.plugins.blocks.connect`). An edit to any
    of those files, a comment included, builds a new kernel; an edit to a module the kernel does not
    import (the env, agents/, docs/) does not."""
    return hashlib.sha1((sources.digest(__name__) + conn.digest).encode()).hexdigest()[:10]


def _cache_dir(dispatcher) -> Path:
    """Where numba keeps this dispatcher's cache: beside its source file if that folder is writable
    (a build's module lies in blf-gym's cache folder), otherwise its fallback (``NUMBA_CACHE_DIR``)."""
    return Path(dispatcher._cache._cache_path)


def _is_cached(dispatcher) -> bool:
    """True if machine code for this dispatcher is in memory or in numba's disk cache under its
    current source stamp (an index written for other sources is stale: numba would recompile)."""
    if dispatcher.signatures:
        return True
    try:
        return bool(dispatcher._cache._cache_file._load_index())
    except Exception:  # noqa: BLE001 (an unreadable index is a miss: numba rebuilds it)
        return False


def remove_stale_cache(folder: Path, prefix: str, digest: str) -> list[Path]:
    """Delete the files of older builds of one kernel in ``folder`` and its ``__pycache__``: the
    generated module ``{prefix}{digest}.py``, its compile lock and numba's cache files
    (``{prefix}{digest}.advance-....nbi``), for every 10-hex-digit digest but ``digest`` (they are
    never used again); return what was deleted.

    Only that exact name with another digest is stale. Other kernels whose names merely start with
    the prefix stay: the unfiltered ``advance1__n3__proposed__leso__`` is a prefix of the filtered
    ``advance1__n3__proposed__leso__barrier__...``, and a glob on the prefix would delete those, so every
    run that built one kernel would recompile the other."""
    import re

    pattern = re.compile(rf"{re.escape(prefix)}([0-9a-f]{{10}})[.-]")
    gone = []
    for where in (folder, folder / "__pycache__"):
        if not where.is_dir():
            continue
        for f in where.glob(f"{prefix}*"):
            m = pattern.match(f.name)
            if m and m.group(1) != digest:
                try:
                    f.unlink()
                    gone.append(f)
                except OSError:
                    pass
    return gone


def kernel_label(controller: str, observer: str, residual_filter: str | None = None) -> str:
    """A compiled closed loop in a user's words: the law (or none, for plain torques), the filter and
    what it acts on, the observer. One build of a filtered loop serves both of the filter's uses."""
    law = "plain torques (no inner law)" if controller == "none" else f"the {controller} law"
    filt = ("" if residual_filter is None else
            f", its {residual_filter} filter (on the agent's residual, or in plain mode its whole torque)")
    return f"{law}{filt}, with the {observer} observer"


def compile_notice(label: str, cache: Path) -> None:
    """Tell the user why the first run waits (printed once per kernel, on standard error); ``label``
    is :func:`kernel_label`'s."""
    print(f"blf-gym: compiling the closed loop for {label} (first run only, about 15-50 s; "
          f"cached in {cache})", file=sys.stderr, flush=True)


@contextlib.contextmanager
def _compile_lock(kernel, label: str):
    """Hold an exclusive lock on one kernel's entry in numba's cache while it compiles, so that
    processes started together (pytest workers, sweep trials, subprocess vector envs) compile it
    once: the others wait, then load it from the cache. Without ``fcntl`` (not POSIX) or with a
    cache folder that cannot hold the lock file, each process compiles its own, as before. ``label``
    (:func:`kernel_label`'s) names the kernel in the waiting notice: one process may compile one
    kernel while it waits for another."""
    try:
        import fcntl
    except ImportError:
        fcntl = None
    f = None
    if fcntl is not None:
        # named like the kernel's cache files, so that remove_stale_cache drops it with them
        path = Path(inspect.getfile(kernel.py_func)).with_suffix(".compile.lock")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            f = open(path, "a")
        except OSError:
            f = None
    if f is None:
        yield
        return
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"blf-gym: another process is compiling the closed loop for {label}; waiting for it",
                  file=sys.stderr, flush=True)
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


_KERNELS: dict[tuple, object] = {}
_NOTICED: set = set()


def _build_values(conn: Connection, lanes: int) -> dict[str, int | bool]:
    """The constants of one build (the sizes, offsets and flags of :data:`templates.BUILD_NAMES`)."""
    n = conn.n
    head = STATE.length(n)
    off = {k: head + conn.obs_offsets[k][0] if k in conn.obs_offsets and conn.obs_offsets[k][1] == n else -1
           for k in ("x1_hat", "x2_hat", "x3_hat")}
    fo = conn.fout_offsets
    layout = _layout(conn)
    values: dict[str, int | bool] = {
        "_N": n, "_NO": conn.n_obs, "_NC": conn.n_ctrl, "_NX": head + conn.n_obs + conn.n_ctrl, "_NOUT": conn.n_out,
        "_NFOUT": conn.n_fout, "_LN": lanes, "_X1H": off["x1_hat"], "_X2H": off["x2_hat"], "_X3H": off["x3_hat"],
        "_BREACH": fo["breach"][0] if "breach" in fo else -1,
        "_ASSUME": fo["assumptions"][0] if "assumptions" in fo else -1, "_FILTER": conn.filter is not None}
    for name, part in (("_NPL", "plant"), ("_NRP", "rp"), ("_NBP", "bp"), ("_NLG", "lg"), ("_NOG", "og"), ("_NFG", "fg"),
                       ("_NPW", "pw"), ("_NANG", "ang"), ("_NEX", "ex"), ("_NREF", "ref"), ("_NSMP", "smp")):
        values[name] = layout[part][1]
    values.update({f"_L_{k}": o for k, (o, _) in layout.items() if k != "_total"})
    return values


def _template_imports() -> list[str]:
    """The helpers the templates read from their module (every global name they use that a build
    does not define), as import lines of a build's module."""
    own = {fn.__name__ for fn in TEMPLATES} | set(templates.BUILD_NAMES)
    names, modules = set(), {}
    for fn in TEMPLATES:
        for name in fn.__code__.co_names:
            if name in own or name not in vars(templates):
                continue
            value = vars(templates)[name]
            if isinstance(value, types.ModuleType):
                modules[name] = value.__name__
            else:
                names.add(name)
    lines = [f"import {mod} as {name}" if mod.rsplit(".", 1)[-1] != name or "." in mod else f"import {mod}"
             for name, mod in sorted(modules.items())]
    rows, row = [], "from blf_gym.kernel.templates import ("
    for name in sorted(names):
        if len(row) + len(name) + 2 > 110:
            rows.append(row.rstrip())
            row = "    "
        row += f"{name}, "
    return lines + rows + [row.rstrip(", ") + ")"]


_INLINED = '@njit(cache=True, error_model="numpy", inline="always")'
_CALLED = '@njit(cache=True, error_model="numpy", nogil=True, _nrt=False)'
"""A build's two decorators: a part inlined into the loop; the loop, and a part it calls."""


def build_source(conn: Connection, lanes: int) -> str:
    """The source of one build's module (:mod:`blf_gym.jit.codegen`): the templates' helpers
    imported, the build's constants, the lane view, the plug-ins' glue and the reward's per-sample sum
    bound, then a copy of each template: the parts inlined into the time loop :func:`advance`, but for
    :data:`~blf_gym.kernel.templates.ONCE_A_CALL`'s, which it calls."""
    label = kernel_label(conn.controller.name, conn.observer.name, conn.filter.name if conn.filter else None)
    lines = [f'"""The closed loop for {label}, n = {conn.n}, {lanes} arm(s) per block: generated by',
             "blf_gym.kernel.simulate.build_source from blf_gym.kernel.templates (do not edit; the digest in the",
             'name is that of its sources)."""', "", "from numba import njit", "",
             "from blf_gym.jit.codegen import bound", reward.ACCUMULATE_IMPORT,
             "from blf_gym.kernel.templates import lane_view", *_template_imports(), "",
             "# the build's sizes, offsets and flags (blf_gym.kernel.templates.BUILD_NAMES)"]
    lines += [f"{name} = {value!r}" for name, value in _build_values(conn, lanes).items()]
    lines += ["", f"_lane = lane_view[{lanes}]", "",
              "# the plug-ins' glue (blf_gym.plugins.blocks.connect), bound by the loader"]
    lines += [f'{name} = bound(__name__, "{name}")' for name in ("_ctrl_output", "_obs_rhs", "_ctrl_update",
                                                                 "_res_filter")]
    lines += ["", "", reward.accumulate_source().rstrip()]
    parts = [fn for fn in TEMPLATES if fn.__name__ != "advance"]
    for fn in parts:
        # the block's load and store run once a call, not once a step: called, not inlined (numba's
        # inlining copies a function's IR, and each of these is a large one)
        lines += ["", "", _CALLED if fn in ONCE_A_CALL else _INLINED, inspect.getsource(fn).rstrip()]
    lines += ["", "", _CALLED, inspect.getsource(templates.advance).rstrip(), ""]
    return "\n".join(lines)


def kernel_folder() -> Path:
    """Where this copy of blf_gym keeps its kernels' builds: ``kernels/<tree>`` in blf-gym's cache
    folder, one folder per copy of the package on disk (a digest of its path), so that two checkouts
    sharing the cache folder never delete each other's builds as stale."""
    tree = str(Path(templates.__file__).resolve().parents[1])
    return cache_dir() / "kernels" / hashlib.sha1(tree.encode()).hexdigest()[:10]


def _specialise(conn: Connection, lanes: int = LANES):
    """The compiled kernel for one connection (controller, observer, n) and block width ``lanes``
    (1 or :data:`LANES`): :func:`build_source`'s module, imported from :func:`kernel_folder`, its
    function ``advance`` compiled with a disk cache."""
    key = (conn, lanes)
    if key not in _KERNELS:
        n = conn.n
        digest = kernel_digest(conn)
        pair = f"{conn.controller.name}__{conn.observer.name}"
        if conn.filter is not None:
            pair += f"__{conn.filter.name}"
        prefix = f"advance{lanes}__n{n}__{pair}__"
        folder = kernel_folder()
        remove_stale_cache(folder, prefix, digest)
        module = load_module(f"{prefix}{digest}", build_source(conn, lanes), folder, {
            "_ctrl_output": conn.ctrl_output, "_obs_rhs": conn.obs_rhs, "_ctrl_update": conn.ctrl_update,
            "_res_filter": conn.res_filter})
        _KERNELS[key] = module.advance
    return _KERNELS[key]


def kernels_cached(controller: str = "proposed", observer: str = "leso") -> bool:
    """Whether the closed loop of ``controller`` and ``observer``, as the registry makes them (for
    their default nominal arm's joints), is compiled for the current sources (in numba's disk cache,
    one arm or a block), without compiling it: how a command or the test suite tells a user that a
    first run compiles before it starts."""
    law = make_controller(controller)
    conn = connect(law, make_observer(observer), law.nominal.n_links)
    return _is_cached(_specialise(conn, 1)) or _is_cached(_specialise(conn, LANES))


def _choose_lanes(conn: Connection, n_arms: int) -> int:
    """The block width for ``n_arms`` arms when the caller leaves it open: :data:`LANES` for two
    arms or more (two arms in a block of four cost what two single arms cost); for a single arm 1
    (a block would charge it for four), unless only the batch build is compiled already, since
    both give the same numbers and a build costs tens of seconds."""
    if n_arms >= 2:
        return LANES
    if not _is_cached(_specialise(conn, 1)) and _is_cached(_specialise(conn, LANES)):
        return LANES
    return 1


def _layout(conn: Connection) -> dict[str, tuple[int, int]]:
    """:func:`lane_layout` for one connection."""
    return lane_layout(conn.n, conn.n_obs, conn.n_ctrl, conn.n_out, conn.n_fout, len(conn.controller.gains),
                       len(conn.observer.gains), len(conn.filter.gains) if conn.filter is not None else 0)


# ---------------------------------------------------------------------------------------------
# Python-side shells


def _compile_error(conn: Connection, exc: Exception) -> str:
    """A one-paragraph message for a kernel numba could not compile, naming the plug-in at fault
    (each of its functions is compiled alone on the kernel's argument types to find it)."""
    from numba import njit as _njit
    from numba import types as _t

    c, o = conn.controller, conn.observer
    arr = _t.float64[::1]
    for fn, params, owner in ((c.output, c.output_params, f"{c.owner}.output"),
                              (c.update, c.update_params, f"{c.owner}.update"),
                              (o.rhs, o.rhs_params, f"{o.owner}.rhs")):
        if fn is None:
            continue
        layouts = o.param_layout if fn is o.rhs else c.param_layout
        sig = tuple(_t.float64 if (p == "t" or p.startswith(("k_a", "k_b")) or (p in layouts and layouts[p][1] is None))
                    else arr for p in params)
        try:
            _njit(error_model="numpy")(getattr(fn, "py_func", fn)).compile(sig)
        except Exception as e:  # noqa: BLE001
            first = str(e).strip().splitlines()
            return (f"{owner} could not be compiled by numba (write it as loops over numpy arrays, without "
                    f"allocating, Python objects or unsupported calls): {' '.join(first[:3])}")
    first = str(exc).strip().splitlines()
    return f"the closed loop for {c.owner} + {o.owner} could not be compiled by numba: {' '.join(first[:3])}"


class SimulationDiverged(RuntimeError):
    """Raised on request when the state became non-finite or exceeded the divergence limit."""


@dataclass
class Trajectory:
    """Signals of one run on the 1 ms grid (docs/model.md section 8), plus how the run ended.

    Every array has the sample axis first; joint signals are (samples, n). ``u`` is the torque
    commanded to the actuators (law + residual, after the limit), ``h_u`` what the dead-zone passes,
    ``x3`` the true lumped disturbance against the controller's nominal model and ``x3_hat`` the
    observer's estimate.
    """

    scenario: str
    controller: str
    dt: float
    signals: dict[str, np.ndarray]
    diverged: bool = False
    diverged_at: float | None = None
    step_violations: int = 0
    """Integration steps whose end state broke a bound (finer than the 1 ms samples)."""
    first_violation_step_time: float | None = None
    saturated_steps: int = 0
    divergence_code: int = 0
    """0 healthy, 1 non-finite or beyond SimParams.divergence_limit, 2 numerically unstable, 3 a
    bound broken (ending the episode) while the integration was unstable."""
    wall_s: float = 0.0
    message: str = ""
    filter_breaches: int = 0
    """With a residual filter: integration steps where its condition did not hold (should be 0)."""
    assumption_failures: int = 0
    """With a residual filter: integration steps where an assumption of its guarantee failed."""
    residual_filter: str | None = None
    """The residual filter the run went through (None: none)."""

    def __getattr__(self, name: str) -> np.ndarray:
        signals = self.__dict__.get("signals", {})
        if name in signals:
            return signals[name]
        raise AttributeError(name)

    @property
    def n_samples(self) -> int:
        return int(self.signals["t"].shape[0])

    def save_npz(self, path: str | os.PathLike) -> None:
        """Write the signals and metadata atomically to ``path`` (.npz)."""
        from blf_gym.results.io import atomic_write_npz

        meta = dict(scenario=self.scenario, controller=self.controller, dt=self.dt,
                    diverged=self.diverged, diverged_at=self.diverged_at)
        atomic_write_npz(path, {**self.signals, **{f"meta_{k}": np.asarray(v if v is not None else np.nan)
                                                  for k, v in meta.items()}})


@dataclass
class Batch:
    """The arms' packed per-arm parameters as the kernel reads them, one row per arm: the plant,
    the controller's nominal model, the reference, the bounds and the law's, observer's and filter's
    gains. Written by :meth:`ClosedLoop.reset`; :attr:`ClosedLoop.batch` gives it to readers."""

    plant: np.ndarray
    nominal: np.ndarray
    ref: np.ndarray
    bnd: np.ndarray
    law_gains: np.ndarray
    obs_gains: np.ndarray
    filter_gains: np.ndarray


class ClosedLoop:
    """N arms with one controller and one observer, stepped by the compiled kernel.

    Each arm has its own scenario (plant, reference, bounds); all share ``dt``. The state, the
    global step counter and the last applied torques live here; :meth:`advance` runs the kernel,
    splitting the arms over ``threads`` (default: one per CPU, at most one per arm).

    ``lanes`` is the number of arms the kernel steps together in one block: 1 or :data:`LANES`.
    Blocks of LANES arms run the per-arm arithmetic on vector registers, about 1.7 times faster
    per arm on a mixed batch of 64 (docs/speed.md), with the same numbers bit for bit. The two are
    separate builds of the kernel, each compiled on first use. The default, None, is
    :func:`_choose_lanes`: blocks for two arms or more, one lane for a single arm unless only the
    batch build is compiled already.
    """

    def __init__(
        self,
        scenarios: Sequence[Scenario],
        controller: str | Controller = "proposed",
        observer: str | Observer = "leso",
        threads: int | None = None,
        residual_filter: "str | ResidualFilter | None" = None,
        plain: bool = False,
        lanes: int | None = None,
    ) -> None:
        if len(scenarios) == 0:
            raise ValueError("ClosedLoop needs at least one scenario")
        if lanes is not None and lanes not in (1, LANES):
            raise ValueError(f"ClosedLoop.lanes must be 1, {LANES} or None (chosen by the arms per thread), "
                             f"got {lanes!r}")
        self.controller = make_controller(controller)
        self.observer = make_observer(observer)
        self.n = scenarios[0].arm.n_links
        dts = {s.sim.dt for s in scenarios}
        if len(dts) != 1:
            raise ValueError(f"all scenarios of a ClosedLoop must share SimParams.dt, got {sorted(dts)}")
        self.dt = dts.pop()
        sps = {s.sim.steps_per_sample for s in scenarios}
        if len(sps) != 1:
            raise ValueError("all scenarios of a ClosedLoop must share SimParams.sample_period")
        self.steps_per_sample = sps.pop()
        cores = usable_cores()
        if threads is None:
            threads = min(len(scenarios), cores)
        self.threads = check_int("ClosedLoop", "threads", threads, lo=1, hi=cores,
                                 hint=" (the cores this process may use: more threads than cores only wait)")
        self._pool = None
        self._helpers = 0  # threads beside the caller's that step blocks of this batch
        n = self.n
        if self.controller.nominal.n_links != n or self.observer.nominal.n_links != n:
            raise ValueError("controller/observer nominal model must have as many links as the plant")
        self.residual_filter = self.controller.make_filter(residual_filter)
        """The residual filter between the residual and the actuator (None: none)."""
        if plain and self.residual_filter is None:
            raise ValueError("ClosedLoop: plain=True needs a residual filter (it acts on the agent's torque minus the law's)")
        self.plain = bool(plain)
        """With a filter: the residual passed to advance() is the agent's whole torque, and the filter
        sees it minus the law's. A runtime flag: the residual and the plain mode share one build."""
        self.connection = connect(self.controller, self.observer, n, self.residual_filter)
        if lanes is None:
            lanes = _choose_lanes(self.connection, len(scenarios))
        self.lanes = int(lanes)
        """Arms per block of the kernel (1 or :data:`LANES`)."""
        self._kernel = _specialise(self.connection, self.lanes)
        fresh = not _is_cached(self._kernel)
        label = kernel_label(self.controller.name, self.observer.name,
                             self.residual_filter.name if self.residual_filter else None)
        # a batch's kernel and a single arm's are two builds of the same code: say which
        label += ", stepping one arm" if self.lanes == 1 else f", stepping {self.lanes} arms at once"
        if fresh and self._kernel not in _NOTICED:
            _NOTICED.add(self._kernel)
            compile_notice(label, _cache_dir(self._kernel))
        c = self.connection
        self.N = len(scenarios)
        self.nx = STATE.length(n) + c.n_obs + c.n_ctrl
        """State entries per arm: [q, qd, observer states, controller states]."""
        self.X = np.zeros((self.N, self.nx))
        self.ksteps = np.zeros(self.N, dtype=np.int64)
        self.unstable_run = np.zeros(self.N, dtype=np.int64)
        """Per arm, the consecutive integration steps the instability check has failed so far
        (carried across calls, reset with the arm)."""
        self.last = np.zeros((self.N, N_LAST * n + c.n_out + c.n_fout))
        """Per arm, the columns of blf_gym.kernel.status.LAST_COLUMNS (n each), then the controller's
        outputs in its declared order (see :meth:`outputs`)."""
        self._block = _layout(c)["_total"][0] * self.lanes
        self._scratch = np.zeros((-(-self.N // self.lanes), self._block))
        self._zeros_residual = np.zeros((self.N, n))
        self._no_noise = np.zeros((self.N, 0, n))
        self._no_record = np.zeros((self.N, 0, N_CHANNELS, n))
        self.set_scenarios(scenarios)
        if fresh:
            with _compile_lock(self._kernel, label):
                self._compile()  # after another process built it: loaded from numba's cache

    def _compile(self) -> None:
        """Compile the kernel now (a call of zero steps), reporting a plug-in numba cannot compile as
        a ValueError that names it."""
        from numba.core.errors import NumbaError

        X, k, last = self.X.copy(), self.ksteps.copy(), self.last.copy()
        try:
            self.advance(0, record_samples=0)
        except NumbaError as exc:
            raise ValueError(_compile_error(self.connection, exc)) from None
        finally:
            self.X[:], self.ksteps[:], self.last[:] = X, k, last

    def outputs(self) -> dict[str, np.ndarray]:
        """The controller's outputs at the start of the last integration step, by name ((N, size)
        views of a copy)."""
        base = N_LAST * self.n
        last = self.last.copy()
        return {name: last[:, base + off : base + off + m] for name, (off, m) in self.connection.out_offsets.items()}

    @property
    def batch(self) -> Batch:
        """The arms' packed parameters as the kernel reads them (:class:`Batch`), set by
        :meth:`set_scenarios`; the env's observation filler reads the reference and bounds here."""
        return self._batch

    def set_scenarios(self, scenarios: Sequence[Scenario], which: Sequence[int] | None = None,
                      start_steps: Sequence[int] | None = None) -> None:
        """Install scenarios (all, or the arms listed in ``which``) and reset those arms.

        ``start_steps`` (one per reset arm, default all 0) starts an arm at that global integration
        step instead of t = 0: the arm on its reference at that time (angles plus the scenario's
        initial error, the reference's velocities), the observer's ``x2_hat`` (when it has one) at
        those velocities, its other states and the controller's as at t = 0 from those angles; the
        bounds are then those of that time, since they are functions of time. A training aid
        (EnvCore's ``start_time``); 0 is the usual start, unchanged."""
        idx = list(range(self.N)) if which is None else list(which)
        if len(scenarios) != len(idx):
            raise ValueError("one scenario per reset arm is required")
        if start_steps is None:
            start_steps = [0] * len(idx)
        elif len(start_steps) != len(idx):
            raise ValueError("one start step per reset arm is required")
        if not hasattr(self, "_batch"):
            n = self.n
            self._batch = Batch(
                plant=np.zeros((self.N, PLANT.length(n))),
                nominal=np.tile(self.controller.nominal.pack(), (self.N, 1)),
                ref=np.zeros((self.N, REFERENCE.length(n))),
                bnd=np.zeros((self.N, BOUNDS.length())),
                law_gains=np.tile(self.controller.gains, (self.N, 1)),
                obs_gains=np.tile(self.observer.gains, (self.N, 1)),
                filter_gains=np.tile(self.residual_filter.gains if self.residual_filter else np.zeros(0),
                                     (self.N, 1)),
            )
        b = self._batch
        for i, sc, k0 in zip(idx, scenarios, start_steps):
            if sc.arm.n_links != self.n or sc.sim.dt != self.dt or sc.sim.steps_per_sample != self.steps_per_sample:
                raise ValueError("a replacement scenario must keep n links, dt and sample_period")
            if not (isinstance(k0, (int, np.integer)) and 0 <= k0 < sc.sim.n_steps):
                raise ValueError(f"a start step must be an integer in [0, {sc.sim.n_steps}) (the scenario's "
                                 f"integration steps), got {k0!r}")
            b.plant[i] = sc.pack_plant()
            b.ref[i] = sc.pack_reference()
            b.bnd[i] = sc.bounds.pack()
            self._reset_arm(i, sc, int(k0))

    def _reset_arm(self, i: int, sc: Scenario, k0: int = 0) -> None:
        from blf_gym.model.reference import joint_reference

        n = self.n
        q_d0, qd_d0, _ = joint_reference(k0 * self.dt, sc)
        q0 = q_d0 + np.asarray(sc.initial_error)
        no = self.connection.n_obs
        head = STATE.length(n)
        self.X[i] = 0.0
        self.X[i, STATE.slice("q", n)] = q0
        obs0 = self.observer.initial(q0.copy())
        if k0:
            self.X[i, STATE.slice("qd", n)] = qd_d0
            x2 = self.observer.state_offsets(n).get("x2_hat")
            if x2 is not None and x2[1] == n:
                obs0[x2[0] : x2[0] + n] = qd_d0
        self.X[i, head : head + no] = obs0
        self.X[i, head + no :] = self.controller.initial(q0.copy())
        self.ksteps[i] = k0
        self.unstable_run[i] = 0
        self.last[i] = 0.0

    @property
    def time(self) -> np.ndarray:
        """Simulated time of each arm, s (global step counter times dt, never accumulated)."""
        return self.ksteps * self.dt

    def advance(
        self,
        n_steps: int,
        residual: np.ndarray | None = None,
        noise: np.ndarray | None = None,
        terminate: bool = False,
        record_samples: int | None = None,
        out: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Run ``n_steps`` ODE3 steps on every arm.

        ``residual`` (N, n) N m is added to the law's torque over the whole call; ``noise``
        (N, n_steps, n) rad is added to the measured angles step by step. Returns
        ``(rec, nrec, status)``: recorded samples (N, S, channels, n), how many per arm, and the
        status columns [steps, diverged (0, 1 non-finite, 2 unstable, 3 a terminating violation on an unstable integration), violating steps, first
        violating step or -1, saturated steps, violating 1 ms samples]. ``self.sums`` then holds
        per arm [max ODE3 error estimate, sum of (e1/bound)^2, sum of (u/max_torque)^2, samples,
        then the sum of e1^2 (rad^2) of each joint] over the call's 1 ms samples, and
        ``self.last`` [u, u_law, saturated] at the start of the
        last integration step and [x3, x3_hat] at the last 1 ms sample.

        ``out``, a C-contiguous float64 array of shape (N, record_samples, channels, n), receives the
        samples instead of a new array (of arm i, only the first ``nrec[i]`` are written).
        """
        N, n = self.N, self.n
        if residual is None:
            res = self._zeros_residual
        else:
            res = residual if (type(residual) is np.ndarray and residual.dtype == np.float64
                               and residual.flags.c_contiguous) else np.ascontiguousarray(residual, dtype=np.float64)
            if res.shape != (N, n):
                raise ValueError(f"residual must have shape {(N, n)}, got {res.shape}")
        if noise is None:
            nz = self._no_noise
        else:
            nz = np.ascontiguousarray(noise, dtype=np.float64)
            if nz.shape[1] not in (0, n_steps) or nz.shape[0] != N:
                raise ValueError(f"noise must have shape {(N, n_steps, n)}, got {nz.shape}")
        if record_samples is None:
            record_samples = n_steps // self.steps_per_sample + 1
        if out is not None:
            if (type(out) is not np.ndarray or out.dtype != np.float64 or not out.flags.c_contiguous
                    or out.shape != (N, record_samples, N_CHANNELS, n)):
                raise ValueError(f"out must be a C-contiguous float64 array of shape "
                                 f"{(N, record_samples, N_CHANNELS, n)}")
            rec = out
        else:
            rec = np.zeros((N, record_samples, N_CHANNELS, n)) if record_samples else self._no_record
        nrec = np.zeros(N, dtype=np.int64)
        status = np.empty((N, N_STATUS), dtype=np.int64)  # every column is set by the kernel
        sums = np.empty((N, SUM_E2_JOINT + n))
        b = self._batch
        taken = np.zeros(1, dtype=np.int64)  # blocks taken so far (the kernel's _claim)
        args = (self.X, self.ksteps, int(n_steps), float(self.dt), int(self.steps_per_sample), b.plant, b.nominal,
                b.ref, b.bnd, b.law_gains, b.obs_gains, b.filter_gains, res, nz, bool(terminate), self.plain, rec,
                nrec, status, self.last, self._scratch, sums, self.unstable_run, taken)
        blocks = self._scratch.shape[0]
        if self.threads > 1 and blocks > 1:
            # The kernel releases the GIL: helper threads run it on the same arrays, each block
            # going to whichever thread takes it first, and the caller runs it too (one hand-over
            # fewer). Each arm's arithmetic is the same as alone, whichever thread steps it.
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._helpers = min(self.threads, blocks) - 1
                self._pool = ThreadPoolExecutor(max_workers=self._helpers, thread_name_prefix="blf")
            futures = [self._pool.submit(self._kernel, *args) for _ in range(self._helpers)]
            self._kernel(*args)
            for f in futures:
                f.result()
        else:
            self._kernel(*args)
        self.sums = sums
        return rec, nrec, status


def divergence_message(code: int, t: float, dt: float, unstable_steps: int = 100,
                       controller: str | None = None) -> str:
    """Human-readable reason for a kernel divergence code (status column ``diverged``).

    ``controller`` is the inner law's name, ``"none"`` in plain mode (the agent's action is the
    whole torque), or None when unknown; it selects the likely cause named in the message. For
    code 2 the run is stopped ``unstable_steps`` steps after the instability began; the message
    gives both times. Code 3 is a violation that ended the episode (``terminate``) while ODE3's
    error estimate was above its tolerance: the integration broke the bound, so it is reported as
    a divergence, not as the arm's violation."""
    if code not in (1, 2, 3):
        return ""
    if controller == "none":
        cause = ("With no inner law, the actions are the likely cause: they spin the arm up to extreme "
                 "speeds (plain mode, termination off).")
    else:
        law = f"the {controller} law's" if controller else "the controller's"
        cause = (f"The likely cause is the step: dt = {dt:g} s is too large for {law} gains (the paper's "
                 f"gains need dt <= 1.5e-4 s; the default is 1e-4 s).")
    if code == 1:
        what = (f"simulation diverged at t = {t:.6f} s: the state became non-finite or exceeded "
                f"SimParams.divergence_limit.")
    elif code == 3:
        what = (f"simulation diverged numerically at t = {t:.6f} s: a bound was broken while ODE3's error "
                f"estimate was above its tolerance, so the integration, not the arm, broke it (the episode "
                f"ended on that violation before {unstable_steps} consecutive unstable steps, the count "
                f"that stops a run as unstable, were reached).")
    else:
        onset = max(0.0, t - unstable_steps * dt)
        what = (f"simulation diverged numerically (unstable from t = {onset:.6f} s, stopped at t = {t:.6f} s): "
                f"ODE3's error estimate stayed above tolerance for {unstable_steps} consecutive steps, so "
                f"the step is outside the integrator's stability region; the torque limit kept the state "
                f"finite, but the numbers are meaningless.")
    return f"{what} {cause} The signals up to that time are kept."


def _trajectory(sc: Scenario, controller: str, dt: float, rec: np.ndarray, nrec: int,
                status: np.ndarray, wall: float) -> Trajectory:
    r = rec[:nrec]
    signals = {name: (r[:, i, 0].copy() if name == "t" else r[:, i, :].copy())
               for i, name in enumerate(CHANNELS)}
    code = int(status[ST_DIVERGED])
    diverged = code != 0
    steps = int(status[ST_STEPS])
    fv = int(status[ST_FIRST_VIOL])
    msg = divergence_message(code, steps * dt, dt, sc.sim.unstable_steps, controller)
    return Trajectory(
        scenario=sc.name, controller=controller, dt=dt, signals=signals, diverged=diverged,
        diverged_at=steps * dt if diverged else None,
        step_violations=int(status[ST_VIOL_STEPS]),
        first_violation_step_time=None if fv < 0 else fv * dt,
        saturated_steps=int(status[ST_SAT_STEPS]), divergence_code=code, wall_s=wall, message=msg,
        filter_breaches=int(status[ST_FILTER_BREACHES]), assumption_failures=int(status[ST_ASSUMPTION_FAILURES]),
    )


def simulate_batch(
    scenarios: Sequence[Scenario],
    controller: str | Controller = "proposed",
    observer: str | Observer = "leso",
    noise_seeds: Sequence[int] | None = None,
    threads: int | None = None,
    residual: np.ndarray | None = None,
    residual_filter: "str | ResidualFilter | None" = None,
    lanes: int | None = None,
) -> list[Trajectory]:
    """Run whole episodes (each scenario's ``sim.duration``) for N scenarios in one kernel call.

    The law is evaluated at every ODE3 stage; episodes are not terminated on violation (they are
    counted). A diverging arm stops early and its trajectory says so (``diverged``, ``message``).
    ``residual`` (N, n) N m, held over the whole episode, is added to the law's torque, through
    ``residual_filter`` if given (one of the controller's filters). ``lanes`` is
    :class:`ClosedLoop`'s (None: chosen by the number of arms).
    """
    loop = ClosedLoop(scenarios, controller, observer, threads=threads, residual_filter=residual_filter, lanes=lanes)
    steps = {s.sim.n_steps for s in scenarios}
    if len(steps) != 1:
        raise ValueError("simulate_batch needs scenarios of one duration")
    n_steps = steps.pop()
    noise = None
    if any(s.angle_noise_std > 0 for s in scenarios):
        seeds = noise_seeds if noise_seeds is not None else range(len(scenarios))
        noise = np.stack([np.random.default_rng(sd).standard_normal((n_steps, loop.n)) * s.angle_noise_std
                          for sd, s in zip(seeds, scenarios)])
    t0 = time.perf_counter()
    rec, nrec, status = loop.advance(n_steps, residual=residual, noise=noise, record_samples=scenarios[0].sim.n_samples)
    wall = time.perf_counter() - t0
    name = loop.controller.name
    trajs = [_trajectory(sc, name, loop.dt, rec[i], int(nrec[i]), status[i], wall / len(scenarios))
             for i, sc in enumerate(scenarios)]
    if loop.residual_filter is not None:
        for tr in trajs:
            tr.residual_filter = loop.residual_filter.name
    return trajs


def simulate(
    scenario: Scenario | str = "paper-0.1hz",
    controller: str | Controller = "proposed",
    observer: str | Observer = "leso",
    noise_seed: int = 0,
    raise_on_divergence: bool = False,
) -> Trajectory:
    """Run one whole episode and return its :class:`Trajectory` on the 1 ms grid.

    >>> traj = simulate("paper-0.1hz", "proposed")
    >>> traj.e1.shape
    (30000, 3)
    """
    if isinstance(scenario, str):
        from blf_gym.model.params import preset

        scenario = preset(scenario)
    traj = simulate_batch([scenario], controller, observer, noise_seeds=[noise_seed], threads=1)[0]
    if traj.diverged and raise_on_divergence:
        raise SimulationDiverged(traj.message)
    return traj

