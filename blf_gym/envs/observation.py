"""The observation vector, declared once as the table :data:`OBSERVATION`, and its compiled filler.

Every entry is one row: its group name, how many entries (one per joint, or a count), a label, a
unit, the box, who gets it (``kind``), where its value comes from (``source``, a named signal) and
how it is scaled. The env's box and docstring, :func:`observation_index`, :func:`observation_layout`,
the baseline policies and the compiled filler :func:`observe_batch` all read this table; nothing
else lists the entries. ``docs/extending.md`` ("An observation entry") shows a new one.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit.layout import MARGINS, REF, STATE
from blf_gym.jit.layout import at as offset_at
from blf_gym.model.bounds import BOUND_SIGNALS, KA, KB, bounds_into
from blf_gym.model.params import REFERENCE_PACK
from blf_gym.model.reference import reference_into
from blf_gym.kernel.status import LAST_COLUMNS

__all__ = ["Entry", "OBSERVATION", "SOURCES", "optional_observations", "observation_index", "observation_layout",
           "SQUASH_VELOCITY", "SQUASH_REF_ACCELERATION", "SQUASH_DISTURBANCE", "PREVIEW_STEP", "PREVIEW_POINTS",
           "PREVIEW_EXTRAS", "unsquash", "observe_batch"]

# Squashing scales (value -> c tanh(value / c)) of the unbounded observation entries, and clips.
SQUASH_VELOCITY = 100.0
"""c for velocities (qd_d, x2_hat, privileged qd), rad/s."""
SQUASH_REF_ACCELERATION = 1000.0
"""c for the reference acceleration qdd_d, rad/s^2."""
SQUASH_DISTURBANCE = 1.0e4
"""c for lumped disturbances (x3_hat, privileged x3), rad/s^2."""
ANGLE_CLIP = 4.0 * math.pi
"""Box of the angle entries (y, q_d), rad."""
ERROR_CLIP = 10.0
"""Box of the normalized error entries."""


def unsquash(x: "np.ndarray", c: float) -> "np.ndarray":
    """A squashed entry's value (the inverse of c tanh(value / c)); entries at the box's edge give
    the largest finite value."""
    return c * np.arctanh(np.clip(np.asarray(x, dtype=np.float64) / c, -1 + 1e-12, 1 - 1e-12))


PREVIEW_STEP = 0.01
"""Spacing of the preview entries' future times, s (they give a signal at t + k PREVIEW_STEP)."""
PREVIEW_POINTS = 30
"""Future times in a preview entry (k = 1 .. PREVIEW_POINTS: 0.3 s ahead)."""

SOURCES = {
    "measured": "y (the measured angles, true angles plus the episode's noise) or e1_normalized "
                "((y - q_d) / the bound on the error's side)",
    "reference": "q_d, qd_d or qdd_d (the reference and its derivatives, per joint)",
    "bounds": f"one of {', '.join(BOUND_SIGNALS)} (the time-varying bounds, one entry each)",
    "time": "phase (sin and cos of 2 pi f t, two entries) or fraction (t / duration)",
    "state": "q or qd (the plant's true angles and velocities, per joint)",
    "observer": "<state> (a state part of the observer in use)",
    "controller": "<output> (a controller output at the start of the last integration step)",
    "last": f"<column> (one of {', '.join(LAST_COLUMNS)}: the signals of blf_gym.kernel.status.LAST_COLUMNS)",
}
"""The signals an entry's ``source`` can name, as ``kind:name``."""


class Entry(NamedTuple):
    """One group of observation entries: one row of :data:`OBSERVATION`."""

    group: str
    count: "int | None"
    """Entries: None = one per joint, else that many."""
    name: str
    """Label ("{j}" = the joint, from 1; "a|b" names each of several entries)."""
    unit: str
    low: float
    high: float
    kind: str = "base"
    """"base" (always there), "privileged" (with privileged=True) or "optional" (opt-in by name
    through the env's ``observation_extras``)."""
    source: str = ""
    """Where the value comes from, ``kind:name`` (see :data:`SOURCES`)."""
    scale: float = 0.0
    """> 0 squashes the value as scale * tanh(value / scale); < 0 divides it by the arm's
    max_torque; 0 passes it as it is. Then it is clipped to [low, high]."""
    points: int = 0
    """0: the signal now. k > 0: a preview, the signal at t + i PREVIEW_STEP for i = 1 .. k, time
    after time (k times the entries; "{s}" in the label is the offset in ms). Only reference and
    bounds signals, which are known functions of time, can be previewed."""


OBSERVATION: tuple[Entry, ...] = (
    Entry("y", None, "y_{j} (measured angle)", "rad", -ANGLE_CLIP, ANGLE_CLIP, "base", "measured:y"),
    Entry("q_d", None, "q_d_{j}", "rad", -ANGLE_CLIP, ANGLE_CLIP, "base", "reference:q_d"),
    Entry("qd_d", None, f"qd_d_{{j}} (squashed {SQUASH_VELOCITY:g})", "rad/s", -SQUASH_VELOCITY, SQUASH_VELOCITY,
          "base", "reference:qd_d", SQUASH_VELOCITY),
    Entry("qdd_d", None, f"qdd_d_{{j}} (squashed {SQUASH_REF_ACCELERATION:g})", "rad/s^2", -SQUASH_REF_ACCELERATION,
          SQUASH_REF_ACCELERATION, "base", "reference:qdd_d", SQUASH_REF_ACCELERATION),
    Entry("e1_normalized", None, "(y_{j} - q_d_{j}) / bound (measured error, clipped)", "-", -ERROR_CLIP, ERROR_CLIP,
          "base", "measured:e1_normalized"),
    Entry("k_a", 1, "k_a", "rad", 0.0, 10.0, "base", "bounds:k_a"),
    Entry("k_b", 1, "k_b", "rad", 0.0, 10.0, "base", "bounds:k_b"),
    Entry("k_a_rate", 1, "k_a'", "rad/s", -10.0, 10.0, "base", "bounds:k_a_dot"),
    Entry("k_b_rate", 1, "k_b'", "rad/s", -10.0, 10.0, "base", "bounds:k_b_dot"),
    Entry("phase", 2, "sin(2 pi f t)|cos(2 pi f t)", "-", -1.0, 1.0, "base", "time:phase"),
    Entry("time", 1, "t / duration", "-", 0.0, 1.0, "base", "time:fraction"),
    Entry("u", None, "u_{j} / max_torque (last applied)", "-", -1.0, 1.0, "base", "last:u", -1.0),
    Entry("x2_hat", None, f"x2_hat_{{j}} (squashed {SQUASH_VELOCITY:g})", "rad/s", -SQUASH_VELOCITY, SQUASH_VELOCITY,
          "base", "observer:x2_hat", SQUASH_VELOCITY),
    Entry("x3_hat", None, f"x3_hat_{{j}} (squashed {SQUASH_DISTURBANCE:g})", "rad/s^2", -SQUASH_DISTURBANCE,
          SQUASH_DISTURBANCE, "base", "observer:x3_hat", SQUASH_DISTURBANCE),
    Entry("qd", None, f"qd_{{j}} true (squashed {SQUASH_VELOCITY:g})", "rad/s", -SQUASH_VELOCITY, SQUASH_VELOCITY,
          "privileged", "state:qd", SQUASH_VELOCITY),
    Entry("x3", None, f"x3_{{j}} true (squashed {SQUASH_DISTURBANCE:g})", "rad/s^2", -SQUASH_DISTURBANCE,
          SQUASH_DISTURBANCE, "privileged", "last:x3", SQUASH_DISTURBANCE),
    # opt-in entries (observation_extras=(...)), after the others in the order the env names them
    Entry("u_law", None, "u_law_{j} / max_torque (the inner law's torque, last step)", "-", -1.0, 1.0, "optional",
          "last:u_law", -1.0),
    Entry("z2_hat", None, f"z2_hat_{{j}} = x2_hat - alpha1 (the law's, squashed {SQUASH_VELOCITY:g})", "rad/s",
          -SQUASH_VELOCITY, SQUASH_VELOCITY, "optional", "controller:z2_hat", SQUASH_VELOCITY),
    # the reference and the bounds ahead (what a predictive controller needs; offered to learners too)
    Entry("q_d_preview", None, "q_d_{j}(t+{s} ms)", "rad", -ANGLE_CLIP, ANGLE_CLIP, "optional", "reference:q_d",
          0.0, PREVIEW_POINTS),
    Entry("qd_d_preview", None, f"qd_d_{{j}}(t+{{s}} ms) (squashed {SQUASH_VELOCITY:g})", "rad/s", -SQUASH_VELOCITY,
          SQUASH_VELOCITY, "optional", "reference:qd_d", SQUASH_VELOCITY, PREVIEW_POINTS),
    Entry("k_a_preview", 1, "k_a(t+{s} ms)", "rad", 0.0, 10.0, "optional", "bounds:k_a", 0.0, PREVIEW_POINTS),
    Entry("k_b_preview", 1, "k_b(t+{s} ms)", "rad", 0.0, 10.0, "optional", "bounds:k_b", 0.0, PREVIEW_POINTS),
)
"""The observation vector, declared once, in order. Privileged groups come after the base ones and
exist only with ``privileged=True``; optional groups come last, in the order the env's
``observation_extras`` names them."""

PREVIEW_EXTRAS = tuple(e.group for e in OBSERVATION if e.points)
"""The optional preview groups: the reference and the bounds over the next 0.3 s."""


def optional_observations() -> list[str]:
    """The names accepted by the env's ``observation_extras`` (the optional groups of OBSERVATION)."""
    return [e.group for e in OBSERVATION if e.kind == "optional"]


def groups(privileged: bool, extras: Sequence[str]) -> list[Entry]:
    """The rows of OBSERVATION in an env's observation, in order."""
    rows = [e for e in OBSERVATION if e.kind == "base" or (privileged and e.kind == "privileged")]
    by = {e.group: e for e in OBSERVATION if e.kind == "optional"}
    return rows + [by[g] for g in extras]


def observation_index(n: int, privileged: bool = True, extras: Sequence[str] = ()) -> dict[str, slice]:
    """Where each group of :data:`OBSERVATION` sits in the observation vector of an arm of ``n``
    links (3 for the paper's arm; an env's ``core.n``), with the privileged groups unless
    ``privileged=False``, and the optional ones named in ``extras``."""
    out, o = {}, 0
    for e in groups(privileged, extras):
        m = (n if e.count is None else e.count) * max(e.points, 1)
        out[e.group] = slice(o, o + m)
        o += m
    return out


def observation_layout(n: int, privileged: bool = False, extras: Sequence[str] = ()) -> list[tuple[str, str, float, float]]:
    """(name, unit, low, high) of every observation entry of an arm of ``n`` links (3 for the
    paper's arm), in order."""
    rows: list[tuple[str, str, float, float]] = []
    for e in groups(privileged, extras):
        for k in range(1, e.points + 1) if e.points else [0]:
            s = f"{k * PREVIEW_STEP * 1e3:g}"
            if e.count is None:
                rows += [(e.name.format(j=j + 1, s=s), e.unit, e.low, e.high) for j in range(n)]
            else:
                names = e.name.split("|")
                rows += [((names[i] if len(names) == e.count else e.name).format(s=s), e.unit, e.low, e.high)
                         for i in range(e.count)]
    return rows


# what the compiled filler reads for a group: plan rows [where from, column, entries, first entry]
FROM_STATE, FROM_LAST, FROM_REFERENCE, FROM_BOUNDS, FROM_MEASURED, FROM_ERROR, FROM_PHASE, FROM_TIME = range(8)
_FIXED = {"measured:y": FROM_MEASURED, "measured:e1_normalized": FROM_ERROR, "time:phase": FROM_PHASE,
          "time:fraction": FROM_TIME}
_RP_FREQ = REFERENCE_PACK.index("frequency")


def plan_row(entry: Entry, n: int, observer_part, controller_part, last_width: int) -> tuple[int, int, int]:
    """(where from, column, entries) of one row, its signal resolved against the blocks in use;
    ``observer_part(name)`` and ``controller_part(name)`` give (offset, size) of a block's state or
    output, or None. ValueError naming the source when it does not exist or has the wrong size."""
    want = n if entry.count is None else entry.count
    kind, _, name = entry.source.partition(":")
    size = want
    if entry.source in _FIXED:
        frm, col = _FIXED[entry.source], 0
        size = 2 if entry.source == "time:phase" else 1 if entry.source == "time:fraction" else n
    elif kind == "reference" and name in ("q_d", "qd_d", "qdd_d"):
        frm, col = FROM_REFERENCE, ("q_d", "qd_d", "qdd_d").index(name) * n
        size = n
    elif kind == "bounds" and name in BOUND_SIGNALS:
        frm, col, size = FROM_BOUNDS, BOUND_SIGNALS.index(name), 1
    elif kind == "state" and name in ("q", "qd"):
        frm, col, size = FROM_STATE, 0 if name == "q" else n, n
    elif kind == "last" and name in LAST_COLUMNS:
        frm, col, size = FROM_LAST, LAST_COLUMNS.index(name) * n, n
    elif kind in ("observer", "controller"):
        part = (observer_part if kind == "observer" else controller_part)(name)
        if part is None:
            raise LookupError(entry.source)
        frm = FROM_STATE if kind == "observer" else FROM_LAST
        col = (2 * n if kind == "observer" else last_width) + part[0]
        size = part[1]
    else:
        raise ValueError(f"observation entry {entry.group!r}: unknown source {entry.source!r} (one of "
                         f"{', '.join(k + ':...' for k in SOURCES)}; see blf_gym.envs.observation.SOURCES)")
    if size != want:
        raise ValueError(f"observation entry {entry.group!r}: its source {entry.source!r} has {size} entries, "
                         f"not {want}")
    if entry.points:
        if frm not in (FROM_REFERENCE, FROM_BOUNDS):
            raise ValueError(f"observation entry {entry.group!r}: only reference and bounds signals can be "
                             f"previewed, not {entry.source!r}")
        return frm, col, want * entry.points
    return frm, col, want


_S_Q, _R_Q = STATE.start("q"), REF.start("q_d")
_M_E1, _M_UP, _M_LO = (MARGINS.start(k) for k in ("e1", "g_upper", "g_lower"))


@njit(cache=True, error_model="numpy")
def observe_batch(X, t, rp, bp, plant, last, noise, dur, umax, plan, scale, low, high, obs, ref, bnd, state):
    """Fill ``obs`` (N, obs_dim) float32 from the plan of :data:`OBSERVATION` (rows [where from,
    column, entries, first entry, preview points], with each row's ``scale``; ``low`` and ``high``
    the box per entry), ``ref`` and ``bnd`` with the reference and bounds at ``t``, and ``state``
    (N, 3n: :data:`blf_gym.jit.layout.MARGINS`) with per joint [e1, g_upper, g_lower] in the g <= 0 convention (positive means the bound
    is broken). One compiled call per agent step."""
    N = X.shape[0]
    n = noise.shape[1]
    ahead_ref = np.empty(ref.shape[1])
    ahead_bnd = np.empty(bnd.shape[1])
    for b in range(N):
        reference_into(t[b], rp[b], plant[b], ref[b])
        bounds_into(t[b], bp[b], bnd[b])
        ka = bnd[b, KA]
        kb = bnd[b, KB]
        for g in range(plan.shape[0]):
            frm, col, m, at, points = plan[g, 0], plan[g, 1], plan[g, 2], plan[g, 3], plan[g, 4]
            c = scale[g]
            per = m // points if points > 0 else m
            for i in range(m):
                if points > 0:
                    # a preview: the entries of time t + (i // per + 1) PREVIEW_STEP, in turn
                    j = i % per
                    if j == 0:
                        ahead = t[b] + (i // per + 1) * PREVIEW_STEP
                        if frm == FROM_REFERENCE:
                            reference_into(ahead, rp[b], plant[b], ahead_ref)
                        else:
                            bounds_into(ahead, bp[b], ahead_bnd)
                    v = ahead_ref[col + j] if frm == FROM_REFERENCE else ahead_bnd[col + j]
                elif frm == FROM_STATE:
                    v = X[b, col + i]
                elif frm == FROM_LAST:
                    v = last[b, col + i]
                elif frm == FROM_REFERENCE:
                    v = ref[b, col + i]
                elif frm == FROM_BOUNDS:
                    v = bnd[b, col + i]
                elif frm == FROM_MEASURED:
                    v = X[b, i] + noise[b, i]
                elif frm == FROM_ERROR:
                    # the error the agent can know: from the measurement, not from the true angle
                    # (info["e1"] and the privileged entries keep the true one)
                    e = (X[b, i] + noise[b, i]) - ref[b, i]
                    v = e / ka if e >= 0.0 else e / kb
                elif frm == FROM_PHASE:
                    ph = 2.0 * np.pi * rp[b, _RP_FREQ] * t[b]
                    v = np.sin(ph) if i == 0 else np.cos(ph)
                else:
                    v = t[b] / dur[b]
                if c > 0.0:
                    v = c * np.tanh(v / c)
                elif c < 0.0:
                    v = v / umax[b]
                k = at + i
                v = min(max(v, low[k]), high[k])
                obs[b, k] = min(max(np.float32(v), np.float32(low[k])), np.float32(high[k]))
        for j in range(n):
            ej = X[b, offset_at(_S_Q, n) + j] - ref[b, offset_at(_R_Q, n) + j]
            state[b, offset_at(_M_E1, n) + j] = ej
            state[b, offset_at(_M_UP, n) + j] = ej - ka
            state[b, offset_at(_M_LO, n) + j] = -kb - ej
