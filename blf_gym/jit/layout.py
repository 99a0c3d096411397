"""Every packed array the compiled closed loop and its readers share, declared once.

The kernel passes its data as flat float64 (and int64) arrays: the plant, the scenario's reference
and bounds, the bound and reference signals, the nominal model signal, the kernel's scratch, the
per-arm status, sums and records. Each array's layout is one :class:`Pack` here: its parts in order,
each with a size that is a fixed number or grows with the number of joints n (``a n^2 + b n + c``,
written as the triple ``(a, b, c)``). Everything else derives its offsets from these: the
parameter classes pack in this order (:mod:`blf_gym.model.params`), the compiled code reads
``at(START, n)`` with a start triple taken from here (with n a compile-time constant in the kernel,
LLVM folds it to a number), the env and the results read columns by name. No other module writes a
literal offset into one of these arrays; ``tests/test_packed_layouts.py`` looks for them.

This module sits at the bottom of blf_gym (beside the compiled caches' keys and maths) because the
model, the lowest layer that packs, already needs it.
"""

from __future__ import annotations

from typing import Iterable

from numba import njit

from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)
from blf_gym.jit.views import fixed

__all__ = [
    "Pack", "at", "part", "links_of", "ONE", "N", "NN", "ARM", "PLANT_TAIL", "PLANT", "BOUNDS_PACK", "BOUND_SIGNALS", "BOUND",
    "REFERENCE_PACK", "REFERENCE_JOINT_PACK", "REFERENCE_KINDS", "REFERENCE", "REFERENCE_SIGNALS", "REF",
    "STATE", "TRIG", "NOMINAL", "PLUGIN_WORK", "WORK_PER_LINK", "DYN_WORK", "KERNEL_WORK", "PENDING", "TRIG_ARGS", "EXP_ARGS",
    "MARGINS", "STATUS_COLUMNS", "LAST_COLUMNS", "SUM_HEAD", "CHANNELS", "FLAGS", "block_layout", "padded",
]

Size = tuple[int, int, int]
ONE: Size = (0, 0, 1)
"""One entry."""
N: Size = (0, 1, 0)
"""n entries, one per joint."""
NN: Size = (1, 0, 0)
"""n^2 entries (a matrix, row-major)."""


def _times(k: int, s: Size) -> Size:
    return (k * s[0], k * s[1], k * s[2])


def _plus(a: Size, b: Size) -> Size:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit(cache=True, error_model="numpy", inline="always")
def at(coef, n):
    """``a n^2 + b n + c`` for the triple ``coef`` = (a, b, c): an offset or a size of a
    :class:`Pack` part for n joints (a tuple global, frozen by numba as a constant)."""
    return coef[0] * n * n + coef[1] * n + coef[2]


@njit(cache=True, error_model="numpy", inline="always")
def part(arr, start, size, n):
    """The view of one part of a packed array for n joints: ``start`` and ``size`` are the part's
    triples (:meth:`Pack.start`, :meth:`Pack.size`), its length a constant where n is one."""
    return fixed(arr, at(start, n), at(size, n))


@njit(cache=True, error_model="numpy", inline="always")
def links_of(length, size):
    """n from the length of a part whose size triple is ``(0, b, c)`` (an arm's 2n + 1: n)."""
    return (length - size[2]) // size[1]


class Pack:
    """An ordered packed layout: ``parts`` of (name, size), a size an int (fixed) or a triple
    ``(a, b, c)`` meaning ``a n^2 + b n + c``."""

    def __init__(self, name: str, parts: Iterable[tuple[str, int | Size]]):
        self.name = name
        self.parts: tuple[str, ...] = ()
        self.sizes: dict[str, Size] = {}
        self.starts: dict[str, Size] = {}
        o: Size = (0, 0, 0)
        for part, size in parts:
            s = (0, 0, size) if isinstance(size, int) else tuple(size)
            if part in self.sizes:
                raise ValueError(f"{name}: part {part!r} declared twice")
            self.parts += (part,)
            self.sizes[part] = s
            self.starts[part] = o
            o = _plus(o, s)
        self.total: Size = o
        self._offsets: dict[int, dict[str, tuple[int, int]]] = {}  # offsets(n), kept: the env reads them every step
        self._slices: dict[tuple[str, int], slice] = {}

    def __len__(self) -> int:
        return len(self.parts)

    def __iter__(self):
        return iter(self.parts)

    @property
    def fixed(self) -> bool:
        """True when no part grows with n."""
        return all(s[0] == 0 and s[1] == 0 for s in self.sizes.values())

    def start(self, part: str) -> Size:
        """The part's offset as a triple (for :func:`at` in compiled code)."""
        return self.starts[part]

    def size(self, part: str) -> Size:
        return self.sizes[part]

    def index(self, part: str) -> int:
        """The part's offset in a fixed layout (an int, for compiled code and Python alike)."""
        a, b, c = self.starts[part]
        if a or b:
            raise ValueError(f"{self.name}: {part!r} starts at an offset that depends on n; use start()")
        return c

    def indices(self) -> tuple[int, ...]:
        """Every part's offset in a fixed layout, in order (to unpack into constants)."""
        return tuple(self.index(p) for p in self.parts)

    def length(self, n: int = 0) -> int:
        a, b, c = self.total
        return a * n * n + b * n + c

    def offsets(self, n: int) -> dict[str, tuple[int, int]]:
        """part -> (offset, length) for n joints (computed once per n; the caller must not change
        the dict)."""
        out = self._offsets.get(n)
        if out is None:
            out = {}
            for p in self.parts:
                (a, b, c), (sa, sb, sc) = self.starts[p], self.sizes[p]
                out[p] = (a * n * n + b * n + c, sa * n * n + sb * n + sc)
            self._offsets[n] = out
        return out

    def slice(self, part: str, n: int) -> slice:
        """The part's slice for n joints (kept per part and n)."""
        key = (part, n)
        out = self._slices.get(key)
        if out is None:
            off, m = self.offsets(n)[part]
            out = self._slices[key] = slice(off, off + m)
        return out

    def __repr__(self) -> str:
        return f"Pack({self.name!r}, {list(self.parts)})"


def padded(count: int, width: int = 4) -> int:
    """``count`` rounded up to whole vectors of ``width`` (the one-lane kernel's sincos and exp)."""
    return -(-count // width) * width


# -- the scenario's packed parameters (blf_gym.model.params packs them in these orders) -------------

ARM = Pack("arm", [("lengths", N), ("masses", N), ("gravity", ONE)])
"""The packed arm (:meth:`ArmParams.pack`): link lengths, point masses, gravity; 2n + 1 entries."""

PLANT_TAIL = (
    "viscous", "coulomb", "tanh_slope",                              # friction, FrictionParams
    "slope_right", "slope_left", "break_right", "break_left",         # dead-zone, DeadZoneParams
    "f_x", "f_y", "moment", "onset",                                  # external force, ForceParams
    "max_torque", "divergence_limit", "error_rtol", "error_atol", "unstable_steps",  # SimParams
)
"""The plant's scalars after the arm block, in their packed order (:meth:`Scenario.pack_plant`)."""
TAIL = Pack("plant tail", [(p, 1) for p in PLANT_TAIL])
"""The plant's scalars alone: the offsets within the tail (a fixed layout)."""
PLANT = Pack("plant", [*((p, ARM.size(p)) for p in ARM), *((p, 1) for p in PLANT_TAIL)])
"""The packed true plant: the arm (:data:`ARM`), then :data:`PLANT_TAIL`."""

BOUNDS_PACK = ("upper_amplitude", "upper_floor", "lower_amplitude", "lower_floor", "decay_rate")
"""The packed bounds (:meth:`BoundParams.pack`), a fixed layout."""
BOUNDS = Pack("bounds", [(p, 1) for p in BOUNDS_PACK])

REFERENCE_PACK = ("frequency", "center_x", "center_y", "radius", "orientation", "branch", "wrist_x", "wrist_y",
                  "k", "cos_beta", "sin_beta", "beta", "kind")
"""The head of the packed reference (:meth:`Scenario.pack_reference`): the circle's frequency (Hz),
centre (m), radius (m) and orientation (rad), the branch (0 smooth, 1 standard), then derived
constants: the wrist circle's centre (m), k, and the cosine, sine and value of beta, the angle of the
wrist centre; then the kind (:data:`REFERENCE_KINDS`' index). For kind "joint" only the frequency is
used, with beta = 0."""
REFERENCE_JOINT_PACK = ("cos_phase", "sin_phase", "amplitude", "offset")
"""After the head, n entries of each of these (a block of n per name): the joint sinusoids' phases
(as cosine and sine), amplitudes and offsets; zeros for kind "circle"."""
REFERENCE_KINDS = ("circle", "joint")
"""The reference kinds (:class:`blf_gym.model.params.ReferenceParams`), in the order of their code."""
REFERENCE = Pack("reference", [*((p, 1) for p in REFERENCE_PACK), *((p, N) for p in REFERENCE_JOINT_PACK)])

# -- the signals the compiled code computes and hands to the plug-ins -------------------------------

BOUND_SIGNALS = ("k_a", "k_a_dot", "k_a_ddot", "k_b", "k_b_dot", "k_b_ddot")
"""The bound signal at one time: the upper bound k_a (e1 < k_a) and its two derivatives, the lower
bound k_b (e1 > -k_b) and its two."""
BOUND = Pack("bound signal", [(p, 1) for p in BOUND_SIGNALS])

REFERENCE_SIGNALS = ("q_d", "qd_d", "qdd_d")
"""The joint reference signal at one time: angles, velocities, accelerations (n each)."""
REF = Pack("reference signal", [(p, N) for p in REFERENCE_SIGNALS])

STATE = Pack("state head", [("q", N), ("qd", N)])
"""The head of an arm's state: the true joint angles and velocities; the observer's states and the
controller's follow (their sizes are the plug-ins', :meth:`blf_gym.plugins.blocks.Block.state_size`)."""

TRIG = Pack("trig", [("cos", N), ("sin", N)])
"""The cos and sin of the absolute link angles theta_j = q_1 + ... + q_j
(:func:`blf_gym.model.dynamics.abs_trig_into`), which every model term takes instead of q."""

NOMINAL = Pack("nominal", [("M", NN), ("G", N), ("trig", _times(2, N)), ("L", NN), ("arm", ARM.total),
                           ("scratch", _times(4, N))])
"""The ``nominal`` signal handed to plug-ins: the nominal inertia M(y) (row-major), gravity G(y), the
cos and sin of the absolute link angles (:data:`TRIG`), the LDL^T factor of M(y) (unit lower part,
1/D on the diagonal), the nominal arm (:data:`ARM`) and scratch for the operators (Coriolis needs
3n). The parts before the arm are computed at each measurement."""

PLUGIN_WORK = Pack("plug-in work", [("scratch", (2, 12, 0))])
"""The ``work`` signal a plug-in function is handed: 2 n^2 + 12 n entries of scratch, its own."""

DYN_WORK = Pack("dynamics work", [("mu", N), ("omega", N), ("psi", N), ("spare", N)])
"""The ``work`` of :mod:`blf_gym.model.dynamics`: the mass carried beyond each joint, the cumulative
sums of the Coriolis operator's two vectors; :data:`WORK_PER_LINK` entries per link."""
WORK_PER_LINK = DYN_WORK.total[1]
"""Scratch entries per link that the dynamics' ``*_into`` functions need in ``work`` (from :data:`DYN_WORK`)."""

KERNEL_WORK = Pack("kernel work", [("dynamics", _times(WORK_PER_LINK, N)), ("trig", _times(2, N)), ("coriolis", N),
                                   ("gravity", N), ("wrench", N), ("rhs", N),
                                   ("nominal", _plus(_times(WORK_PER_LINK, N), NN))])
"""The kernel's per-lane scratch ``pw`` for the plant's right-hand side: the dynamics' work, the cos
and sin of the plant's link angles (:data:`TRIG`), C(q, qd) qd, G(q), J^T f, the right-hand side of M qdd = rhs,
and the work of the nominal model's terms."""

PENDING = Pack("pending sample", [("q", N), ("qd", N), ("qdd", N), ("u", N)])
"""A 1 ms sample whose true lumped disturbance is computed at the call's end (not recorded)."""

TRIG_ARGS = Pack("sincos arguments", [("plant", N), ("measured", N), ("reference", ONE)])
"""The one-lane kernel's sincos arguments per stage: the plant's absolute link angles, the measured
ones, the reference's phase; padded to whole vectors (:func:`padded`)."""
EXP_ARGS = Pack("exp arguments", [("friction", N), ("bounds", ONE)])
"""The one-lane kernel's exp arguments per stage: each joint's friction exponent, the bounds'."""

MARGINS = Pack("margins", [("e1", N), ("g_upper", N), ("g_lower", N)])
"""Per arm, what the observation filler computes besides the observation: the tracking error and
the constraint margins g_upper = e1 - k_a, g_lower = -k_b - e1 (positive: the bound is broken)."""

# -- per-arm results of one kernel call ---------------------------------------------------------------

STATUS_COLUMNS = ("steps", "diverged", "violating_steps", "first_violating_step", "saturated_steps",
                  "violating_samples", "filter_breaches", "assumption_failures")
"""Per-arm integer status of one kernel call: steps taken, divergence code (0, 1 non-finite or
beyond the limit, 2 numerically unstable, 3 a violation that ended the episode while the integration
was unstable), violating integration steps, the first one (global index, -1 if none), steps with a
saturated torque, violating 1 ms samples; with a residual filter, the integration steps where its
condition did not hold and where an assumption of its guarantee failed (its ``breach`` and
``assumptions`` monitors, blf_gym.plugins.blocks.ResidualFilter)."""
STATUS = Pack("status", [(c, 1) for c in STATUS_COLUMNS])

LAST_COLUMNS = ("u", "u_law", "saturated", "x3", "x3_hat")
"""Per-arm, per-joint signals kept after a kernel call (``ClosedLoop.last``, n entries each): the
commanded torque, the law's torque and the saturation flag at the start of the last integration
step, the true lumped disturbance and the observer's x3_hat at the last 1 ms sample (NaN if the
observer has no x3_hat). The controller's outputs follow, then the residual filter's, in their
declared orders."""
LAST = Pack("last", [(c, N) for c in LAST_COLUMNS])

SUM_HEAD = ("error_estimate_max", "samples")
"""The first per-arm float sums of one kernel call: the largest ODE3 error estimate and the number of
1 ms samples; the reward's terms follow (one column each, :data:`blf_gym.kernel.reward.TERMS`), then
each joint's sum of e1^2."""

CHANNELS = ("t", "q", "qd", "q_ref", "qd_ref", "e1", "k_a", "k_b", "u", "h_u", "u_law", "saturated",
            "x3", "x3_hat", "x2_hat", "x1_hat", "y")
"""The recorded channels, each an n-vector per 1 ms sample (the time channel repeats t)."""
RECORD = Pack("record", [(c, 1) for c in CHANNELS])

FLAGS = Pack("lane flags", [(f, 1) for f in ("noisy", "pending", "halt", "check", "ok", "stopped", "k0", "same_arm",
                                             "same_y")])
"""Per-lane flags of a block of the batched kernel (floats, 1.0 true; ``k0`` the call's first global
step)."""


def block_layout(n: int, n_obs: int, n_ctrl: int, n_out: int, n_fout: int, n_law_gains: int, n_obs_gains: int,
                 n_filter_gains: int) -> Pack:
    """The per-lane entries of a block of the batched kernel (a block of L entries per lane holds
    ``L * lanes`` numbers, lanes innermost). The sizes are numbers: the plug-ins' sizes fix them."""
    nx = STATE.length(n) + n_obs + n_ctrl
    nominal = NOMINAL.length(n)
    return Pack("block", [
        ("K0", nx), ("K1", nx), ("K2", nx), ("K3", nx), ("dx", nx), ("xs", nx), ("xn", nx), ("ep", nx), ("x", nx),
        ("y", n), ("nz", n), ("ref", REF.length(n)), ("bnd", BOUND.length()), ("u", n), ("hu", n), ("satf", n),
        ("x3", n), ("cout", n_out), ("fout", n_fout), ("rr", n), ("Mp", n * n), ("Lp", n * n), ("nom", nominal),
        ("pw", KERNEL_WORK.length(n)), ("wl", PLUGIN_WORK.length(n)), ("wo", PLUGIN_WORK.length(n)),
        ("smp", PENDING.length(n)),
        ("fr", n), ("res", n), ("plant", PLANT.length(n)), ("rp", REFERENCE.length(n)), ("bp", BOUNDS.length()),
        ("lg", n_law_gains), ("og", n_obs_gains), ("fg", n_filter_gains), ("ts", 1), ("flags", FLAGS.length()),
        ("ang", padded(TRIG_ARGS.length(n))), ("sn", padded(TRIG_ARGS.length(n))), ("cs", padded(TRIG_ARGS.length(n))),
        ("ex", padded(EXP_ARGS.length(n))), ("ev", padded(EXP_ARGS.length(n)))])

