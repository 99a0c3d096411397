"""Scenario variations and the randomized suite.

A *variation* changes the paper's plant or task through a few named knobs, each with a unit and
a documented safe range (inside which the default 0.1 ms step stays stable with the paper's
gains; outside it the run may be reported as diverged, never silently wrong). Each knob is one row
of :data:`KNOBS`, a :class:`Knob`; everything else here (validation, :func:`apply_variations`, the
suites' draws, :func:`outside_training`, the table below) reads those rows:

{knob_table}

Payloads lighter than about 0.08 kg make the true M33 so small that the closed loop's fastest mode
leaves ODE3's stability region at h = 0.1 ms: such runs are reported as diverged. The ranges are
safe for the paper's controllers; in plain mode with termination off, large actions can spin the
arm up until the run diverges, which is reported the same way.

The **randomized suite** (``"randomized"``) draws each knob uniformly from its suite range
(:data:`SUITE_RANGES`) with a caller-supplied ``numpy.random.Generator``; the controller's nominal
model stays the paper's, and that mismatch is the point. Agents train on it; its evaluation
episodes use seeds from 10,000 (:data:`blf_gym.envs.protocol.EVAL_SEED_OFFSET`).

The **stress suite** (``"stress"``) is held out: no training, tuning, seed choice, early stopping
or sweep objective may read it. Every episode first draws every knob like the training suite, then
pushes one to three knobs outside :data:`SUITE_RANGES`, into :data:`STRESS_RANGES`: beyond the
documented safe ranges wherever the proposed law still integrates stably at 0.1 ms (the limits
were found by running the law one knob at a time, see docs/model.md "The stress suite"). A pushed
knob lands at the far end of its stress range one time in four, so corners occur; a pushed force
onset is 0 s or a fold of the reference ((2k+1)/(2f), where the elbow folds), times the training
suite never produces. Its evaluation episodes use seeds from :data:`STRESS_SEED_OFFSET`. The law is
not guaranteed there: it breaks the bounds in some stress episodes (fast references with high
friction, heavy payloads), and that is reported, not hidden.

The **certificate suite** (``"certificate"``) is held out like the stress suite, and drawn for one
question only: does a filtered residual break a bound that the law alone keeps where the filter's
assumptions fail? Each episode is one of three kinds, chosen by its generator: two in five are an
**early force** (onset uniform in 0-4 s, 40-60 N, the reference at 0.1-0.5 Hz, every other knob at
the preset's value); three in ten a **corner** of :data:`SAFE_RANGES` (every knob at one end of
its documented range, each end with probability 1/2, each joint's initial error on its own); and
three in ten a **uniform** draw over :data:`SAFE_RANGES`. Its episodes use seeds from
:data:`CERTIFICATE_SEED_OFFSET`. No suite the agents train or are selected on contains them.

**Random streams.** The first eight knobs (:data:`SHARED_KNOBS`) draw from the suite's generator
itself, in table order, then the stress suite picks among those eight which to push: the episodes
every result so far was scored on. A knob added after them names a stream of its own
(``Knob.stream``): a generator seeded from the suite generator's state and that name, which draws
without advancing the suite's generator. It draws its training value there, and in the stress
suite is pushed there one time in four (the eight's rate: one to three of eight). Adding a knob
therefore changes no existing knob's draw in either suite (docs/extending.md, "A scenario knob").
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping

import numpy as np

from blf_gym.envs.protocol import CERTIFICATE_SEED_OFFSET, HELD_OUT_SUITES, STRESS_SEED_OFFSET, SUITES
from blf_gym.model.family import (FAMILY_LINKS, PAPER_LINKS, check_n_links, family_base, family_preset, family_presets,
                                  preset_links)
from blf_gym.model.params import PRESETS, Scenario, check_bool, check_real, is_real, preset, real_text

__all__ = ["Knob", "KNOBS", "SHARED_KNOBS", "VARIATIONS", "SAFE_RANGES", "SUITE_RANGES", "STRESS_RANGES",
           "STRESS_SEED_OFFSET", "CERTIFICATE_SEED_OFFSET", "CERTIFICATE_KINDS", "HELD_OUT_SUITES", "UNITS", "VARIATION_LABEL_MAX", "apply_variations", "check_variations", "variation_label", "varied_name", "sample_suite",
           "outside_training", "resolve_scenario", "SUITES", "widen_bounds"]


@dataclass(frozen=True)
class Knob:
    """One scenario knob, declared once as a row of :data:`KNOBS`.

    ``target`` names the :class:`~blf_gym.model.params.Scenario` fields it sets, as paths:
    ``"reference.frequency"``, ``"force.wrench[0]"`` (one entry of a tuple), ``"arm.masses[-1]"``,
    ``"initial_error"``. With ``scale`` the value multiplies the base scenario's value of each
    target; with ``per_joint`` it is one value per joint (a single number is given to all). The
    ranges are (low, high) in ``unit``: ``safe`` is what :func:`check_variations` accepts,
    ``suite`` the randomized suite's uniform range, ``stress`` where the stress suite pushes it.
    ``physical`` is the lowest value the plant accepts (None: no limit) with ``strict=False``, and
    whether that value itself is excluded. ``stress_value``, if given, replaces the stress suite's
    uniform push: ``(rng, knob, frequency, duration) -> value``. ``stream``: :data:`SHARED` for the
    first eight knobs, a name of its own for any later one (see the module docstring)."""

    name: str
    unit: str
    meaning: str
    target: tuple[str, ...]
    safe: tuple[float, float]
    suite: tuple[float, float]
    stress: tuple[float, float]
    physical: tuple[float | None, bool] = (None, False)
    scale: bool = False
    per_joint: bool = False
    stress_value: Callable[..., float] | None = None
    stream: str = ""
    paths: tuple[tuple[str, str | None, int | None], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.stream:
            raise ValueError(f"Knob {self.name!r}: stream must name its random stream (a knob added after the "
                             f"first eight draws from a stream of its own)")
        if not (self.safe[0] <= self.suite[0] <= self.suite[1] <= self.safe[1]):
            raise ValueError(f"Knob {self.name!r}: the suite range {self.suite} must lie inside the safe range "
                             f"{self.safe}")
        if self.suite[0] - self.stress[0] <= 0 and self.stress[1] - self.suite[1] <= 0:
            raise ValueError(f"Knob {self.name!r}: the stress range {self.stress} does not extend the suite "
                             f"range {self.suite}")
        object.__setattr__(self, "paths", tuple(_parse_path(t) for t in self.target))

    def read(self, sc: Scenario, base: Scenario) -> tuple[float, ...]:
        """The knob's value(s) in ``sc`` (relative to ``base`` when it scales), read from its first target."""
        v = _get(sc, self.paths[0])
        if self.scale:
            v = v / _get(base, self.paths[0])
        return tuple(v) if self.per_joint else (v,)


def _parse_path(path: str) -> tuple[str, str | None, int | None]:
    """``"a.b[i]"`` -> ("a", "b", i); ``"a"`` -> ("a", None, None)."""
    index = None
    if path.endswith("]"):
        path, _, i = path[:-1].partition("[")
        index = int(i)
    top, _, sub = path.partition(".")
    return top, sub or None, index


def _get(sc: Scenario, path: tuple[str, str | None, int | None]) -> Any:
    top, sub, index = path
    v = getattr(sc, top)
    if sub is not None:
        v = getattr(v, sub)
    return v if index is None else v[index]


def _onset_outside(rng: np.random.Generator, knob: Knob, frequency: float, duration: float) -> float:
    """A pushed force onset: 0 s, or a fold of the reference outside the training window."""
    lo, hi = knob.suite
    folds = [(2 * k + 1) / (2 * frequency) for k in range(int(duration * frequency) + 1)]
    folds = [t for t in folds if (t < lo or t > hi) and t < duration]
    return float(rng.choice([0.0, *folds]))


SHARED = "suite"
"""``Knob.stream`` of the first eight knobs: the suite's own generator, in table order."""

KNOBS: tuple[Knob, ...] = (
    Knob("frequency", "Hz", "reference circle frequency f", ("reference.frequency",),
         safe=(0.05, 0.5), suite=(0.1, 0.5), stress=(0.05, 1.0), physical=(0.0, True), stream=SHARED),
    Knob("force", "N", "magnitude of f_ext along +x (paper: 40)", ("force.wrench[0]",),
         safe=(0.0, 60.0), suite=(0.0, 60.0), stress=(0.0, 150.0), stream=SHARED),
    Knob("force_onset", "s", "switch-on time of f_ext (paper: 20)", ("force.onset",),
         safe=(0.0, 30.0), suite=(5.0, 25.0), stress=(0.0, 30.0), physical=(0.0, False),
         stress_value=_onset_outside, stream=SHARED),
    Knob("friction_scale", "", "multiplies viscous b and Coulomb c", ("friction.viscous", "friction.coulomb"),
         safe=(0.5, 2.0), suite=(0.5, 1.5), stress=(0.25, 3.0), physical=(0.0, False), scale=True, stream=SHARED),
    Knob("dead_zone_scale", "", "multiplies both break points tau_r, tau_l",
         ("dead_zone.break_right", "dead_zone.break_left"),
         safe=(0.5, 2.0), suite=(0.5, 1.5), stress=(0.25, 4.0), physical=(0.0, False), scale=True, stream=SHARED),
    Knob("payload", "kg", "point mass m3 at the end effector (0.10)", ("arm.masses[-1]",),
         safe=(0.08, 0.3), suite=(0.08, 0.2), stress=(0.02, 0.5), physical=(0.0, True), stream=SHARED),
    Knob("initial_error", "rad", "e1(0) per joint (n values or one for all)", ("initial_error",),
         safe=(-0.1, 0.1), suite=(-0.02, 0.02), stress=(-0.2, 0.2), per_joint=True, stream=SHARED),
    Knob("angle_noise_std", "rad", "measurement noise on the angles", ("angle_noise_std",),
         safe=(0.0, 2e-4), suite=(0.0, 1e-4), stress=(0.0, 5e-4), physical=(0.0, False), stream=SHARED),
)
"""The scenario knobs, one row each (:class:`Knob`). The stress ranges are measured limits of the
proposed law at h = 0.1 ms, one knob at a time on both presets (30 s): it integrates stably up to
1 Hz (but breaks the bounds from about 0.6 Hz), down to a 0.01 kg payload (BC is numerically
unstable from about 0.02 kg), up to 150 N, friction x4, dead-zone x5, |e1(0)| = 0.3 rad (the
torque saturates), and angle noise 1e-3 rad (its RMSE grows); the ranges stop short of those
limits."""

SHARED_KNOBS = 8
"""The knobs that draw from the suite's own generator: the first eight rows, frozen (see the
module docstring). A knob added later names a stream of its own."""

if [k.stream == SHARED for k in KNOBS] != [True] * SHARED_KNOBS + [False] * (len(KNOBS) - SHARED_KNOBS):
    raise ValueError(f"the first {SHARED_KNOBS} rows of KNOBS, and only they, draw from the shared stream")
if len({k.name for k in KNOBS}) != len(KNOBS) or len({k.stream for k in KNOBS[SHARED_KNOBS:]}) != len(KNOBS) - SHARED_KNOBS:
    raise ValueError("every knob of KNOBS needs a name and a stream of its own")

_BY_NAME = {k.name: k for k in KNOBS}

VARIATIONS = tuple(_BY_NAME)
"""The knobs' names, in table order."""

SAFE_RANGES: dict[str, tuple[float, float]] = {k.name: k.safe for k in KNOBS}
"""Documented ranges; values outside raise ValueError (pass ``strict=False`` to allow them).
Every value must be a finite real number (a bool or a string is refused)."""

SUITE_RANGES: dict[str, tuple[float, float]] = {k.name: k.suite for k in KNOBS}
"""Uniform ranges of the randomized suite (a subset of :data:`SAFE_RANGES`)."""

STRESS_RANGES: dict[str, tuple[float, float]] = {k.name: k.stress for k in KNOBS}
"""Where the stress suite's pushed knobs are drawn: outside :data:`SUITE_RANGES`, inside these
(see :data:`KNOBS` for how they were measured)."""

UNITS: dict[str, str] = {k.name: k.unit for k in KNOBS}
"""Unit of each knob of :data:`VARIATIONS` (empty: dimensionless)."""

CERTIFICATE_KINDS = (("early force", 0.4), ("corner", 0.3), ("uniform", 0.3))
"""The certificate suite's episode kinds and their probabilities (see the module docstring)."""


def _knob_table() -> str:
    """:data:`KNOBS` as a Markdown table (read as text by ``help()``, rendered by the docs site)."""
    def rng(r: tuple[float, float], k: Knob) -> str:
        return f"[{r[0]:g}, {r[1]:g}]" + (" per joint" if k.per_joint else "")

    rows = [(f"``{k.name}``", k.unit or "-", rng(k.safe, k), rng(k.suite, k), k.meaning) for k in KNOBS]
    head = ("knob", "unit", "safe range", "training suite", "meaning")
    line = lambda r: "| " + " | ".join(c.replace("|", "\\|") for c in r) + " |"  # a cell's own | is escaped
    return "\n".join([line(head), "|" + "---|" * len(head), *map(line, rows)])


__doc__ = __doc__.replace("{knob_table}", _knob_table())

_OUTSIDE_HINT = (" (its safe range, see blf_gym.envs.scenarios; to run outside it, build the Scenario "
                 "with blf_gym.envs.scenarios.apply_variations(scenario, {...}, strict=False) and pass it "
                 "as scenario=)")


def _knob(kind: str, name: str, value: Any, strict: bool, index: int | None = None) -> float:
    label = f"{kind} {name!r}" + ("" if index is None else f"[{index}]")
    knob = _BY_NAME[name]
    if strict:
        lo, hi = knob.safe
        return check_real("", label, value, lo, hi, unit=knob.unit, hint=_OUTSIDE_HINT)
    lo, lo_open = knob.physical
    return check_real("", label, value, lo, lo_open=lo_open, unit=knob.unit)


def check_variations(variations: Any, n_links: int | None = None, strict: bool = True,
                     kind: str = "variation") -> dict[str, Any]:
    """A validated copy of ``variations`` (a mapping of knobs of :data:`VARIATIONS` to values),
    each value a float (``initial_error``: a tuple of ``n_links`` floats, the arm's number of
    links, which a per-joint knob needs). ValueError naming the knob and its accepted range
    otherwise: every value must be a finite real number (not a bool or a string) inside
    :data:`SAFE_RANGES` when ``strict``. ``kind`` names the knobs in messages ("variation",
    "reset option")."""
    if not isinstance(variations, Mapping):
        raise ValueError(f"{kind}s must be a mapping (dict) from names in {list(VARIATIONS)} to "
                         f"numbers, got {variations!r}")
    strict = check_bool("apply_variations:", "strict", strict)
    unknown = [k for k in variations if not (isinstance(k, str) and k in VARIATIONS)]
    if unknown:
        raise ValueError(f"unknown {kind}(s) {sorted(unknown, key=repr)}; accepted: {list(VARIATIONS)}")
    out: dict[str, Any] = {}
    for name, value in variations.items():
        knob = _BY_NAME[name]
        if not knob.per_joint:
            out[name] = _knob(kind, name, value, strict)
            continue
        if n_links is None:
            raise ValueError(f"check_variations: the per-joint {kind} {name!r} needs n_links, the arm's number "
                             "of links")
        if is_real(value):
            out[name] = (_knob(kind, name, value, strict),) * n_links
            continue
        seq = isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim == 1)
        if not (seq and len(value) == n_links):
            lo, hi = knob.safe if strict else (None, None)
            raise ValueError(
                f"{kind} {name!r} must be one real number (the same for every joint) or a "
                f"sequence of {n_links} (one per joint), each {real_text(lo, hi, unit=knob.unit)}"
                f"{_OUTSIDE_HINT if strict else ''}, got {value!r}")
        out[name] = tuple(_knob(kind, name, v, strict, i) for i, v in enumerate(value))
    return out


VARIATION_LABEL_MAX = 40
"""The longest variation suffix a scenario's name carries; longer ones become ``+custom``."""


def _label_value(value: Any) -> str:
    """A knob's value as a label writes it: a whole number without its ``.0``, a per-joint value
    that is the same on every joint as one number, else ``[a,b,c]``."""
    if isinstance(value, (tuple, list, np.ndarray)):
        vals = [float(v) for v in value]
        if vals and all(v == vals[0] for v in vals):
            return _label_value(vals[0])
        return "[" + ",".join(_label_value(v) for v in vals) + "]"
    v = float(value)
    return str(int(v)) if v.is_integer() and abs(v) < 1e15 else repr(v)


def variation_label(variations: Mapping[str, Any]) -> str:
    """The suffix a varied scenario's name gains: its knobs and their values, sorted
    (``+force=20,frequency=0.5``), or ``+custom`` past :data:`VARIATION_LABEL_MAX` characters or
    with characters a file name should not hold; empty without variations. The same label names a
    varied scenario everywhere: the env's ``info["scenario"]`` and render title, blf-eval's rows,
    records and plots. A 0.1 Hz preset varied to 0.5 Hz reads ``paper-0.1hz+frequency=0.5``."""
    if not variations:
        return ""
    text = ",".join(f"{k}={_label_value(v)}" for k, v in sorted(variations.items()))
    if len(text) > VARIATION_LABEL_MAX or not re.fullmatch(r"[\w.,=\[\]+-]+", text):
        return "+custom"
    return "+" + text


_LABEL_ITEM = re.compile(r"(\w+)=(\[[^\]]*\]|[^,]+)")


def varied_name(name: str, variations: Mapping[str, Any]) -> str:
    """``name`` with ``variations`` in its label: a name that already carries a label (the scenario
    was varied before) gets one label for both, the later value of a knob replacing the earlier,
    so no label is ever doubled (``paper-0.1hz+force=20`` varied by frequency 0.5 reads
    ``paper-0.1hz+force=20,frequency=0.5``)."""
    root, plus, tail = name.partition("+")
    if not plus:
        return name + variation_label(variations)
    if tail == "custom":
        return root + "+custom"
    old: dict[str, Any] = {}
    for key, text in _LABEL_ITEM.findall(tail):
        old[key] = [float(t) for t in text[1:-1].split(",")] if text.startswith("[") else float(text)
    return root + variation_label({**old, **variations})


def apply_variations(base: Scenario, variations: Mapping[str, Any], strict: bool = True,
                     name: str | None = None) -> Scenario:
    """``base`` with the named knobs of :data:`VARIATIONS` applied (validated by
    :func:`check_variations`), and named ``name`` if one is given, else ``base``'s name with the
    variations in its label (:func:`varied_name`). Each knob sets its targets (:class:`Knob`); the
    new scenario is built and checked once, whatever the number of knobs (a reset draws all of
    them)."""
    v = check_variations(variations, base.arm.n_links, strict)
    if name is None and v:
        name = varied_name(base.name, v)
    parts: dict[str, Any] = {}  # top-level field -> its new value, or a dict of its changed fields
    for knob in KNOBS:
        if knob.name not in v:
            continue
        value = v[knob.name]
        for path in knob.paths:
            top, sub, index = path
            new = _get(base, path) * value if knob.scale else value
            if sub is None:
                cur = parts.get(top, getattr(base, top))
            else:
                fields = parts.setdefault(top, {})
                cur = fields.get(sub, getattr(getattr(base, top), sub))
            if index is not None:
                items = list(cur)
                items[index] = new
                new = tuple(items)
            if sub is None:
                parts[top] = new
            else:
                parts[top][sub] = new
    changes: dict[str, Any] = {} if name is None else {"name": name}
    for top, new in parts.items():
        changes[top] = replace(getattr(base, top), **new) if isinstance(new, dict) else new
    return replace(base, **changes) if changes else base


def widen_bounds(scenario: Scenario, scale: float) -> Scenario:
    """``scenario`` with its funnel ``scale`` times as wide: both bounds' amplitudes and floors
    multiplied by ``scale`` (> 0), the decay rate kept. A training curriculum's tool
    (``bound_scale``); the benchmark's bounds are the scenario's own."""
    b = scenario.bounds
    return replace(scenario, bounds=replace(b, upper_amplitude=b.upper_amplitude * scale,
                                            upper_floor=b.upper_floor * scale,
                                            lower_amplitude=b.lower_amplitude * scale,
                                            lower_floor=b.lower_floor * scale))


def _own_stream(rng: np.random.Generator, name: str) -> np.random.Generator:
    """The random stream of a knob with a stream of its own: seeded from ``rng``'s current state
    and the stream's name, without advancing ``rng``."""
    digest = hashlib.sha256(f"{rng.bit_generator.state!r}|{name}".encode()).digest()
    return np.random.default_rng(np.frombuffer(digest, dtype=np.uint32))


def _draw(rng: np.random.Generator, knob: Knob, n_links: int) -> Any:
    lo, hi = knob.suite
    if knob.per_joint:
        return tuple(float(x) for x in rng.uniform(lo, hi, size=n_links))
    return float(rng.uniform(lo, hi))


def _outside(rng: np.random.Generator, knob: Knob, frequency: float, duration: float) -> float:
    """A value of ``knob`` outside its training range and inside its stress range."""
    if knob.stress_value is not None:
        return knob.stress_value(rng, knob, frequency, duration)
    lo, hi = knob.suite
    slo, shi = knob.stress
    below, above = lo - slo, shi - hi
    side_low = rng.uniform() < below / (below + above)
    if rng.uniform() < 0.25:  # a corner: the far end of the stress range
        return float(slo if side_low else shi)
    return float(rng.uniform(slo, lo) if side_low else rng.uniform(hi, shi))


def _push(rng: np.random.Generator, knob: Knob, draws: dict[str, Any], base: Scenario) -> None:
    if knob.per_joint:
        draws[knob.name] = tuple(_outside(rng, knob, 0.0, 0.0) for _ in range(base.arm.n_links))
    else:
        draws[knob.name] = _outside(rng, knob, draws["frequency"], base.sim.duration)


def _certificate_case(rng: np.random.Generator, n: int) -> dict[str, Any]:
    """The knobs of one certificate-suite episode (the module docstring), from ``rng`` alone (it
    has already drawn the training suite's values, which this discards)."""
    u = rng.uniform()
    if u < CERTIFICATE_KINDS[0][1]:  # an early force on a reference of the training suite's speeds
        return {"force_onset": float(rng.uniform(0.0, 4.0)), "force": float(rng.uniform(40.0, 60.0)),
                "frequency": float(rng.uniform(0.1, 0.5))}
    corner = u < CERTIFICATE_KINDS[0][1] + CERTIFICATE_KINDS[1][1]
    draws: dict[str, Any] = {}
    for k in KNOBS:
        lo, hi = k.safe
        if k.per_joint:
            draws[k.name] = tuple(float(lo if rng.integers(2) == 0 else hi) if corner else float(rng.uniform(lo, hi))
                                  for _ in range(n))
        else:
            draws[k.name] = float(lo if rng.integers(2) == 0 else hi) if corner else float(rng.uniform(lo, hi))
    return draws


def sample_suite(rng: np.random.Generator, base: Scenario | None = None, name: str = "randomized") -> Scenario:
    """Draw one scenario of the suite ``name`` from ``rng`` (the only source of randomness):
    ``"randomized"``, the training suite, ``"stress"``, the held-out stress suite, or
    ``"certificate"``, the held-out cases of the filters' certificate (see the module docstring)."""
    if not (isinstance(name, str) and name in SUITES):
        raise ValueError(f"unknown suite {name!r}; accepted: {list(SUITES)}")
    base = base if base is not None else preset("paper-0.1hz")
    n = base.arm.n_links
    own = {k.name: _own_stream(rng, k.stream) for k in KNOBS[SHARED_KNOBS:]}  # before rng draws
    draws = {k.name: _draw(rng, k, n) for k in KNOBS[:SHARED_KNOBS]}
    for k in KNOBS[SHARED_KNOBS:]:
        draws[k.name] = _draw(own[k.name], k, n)
    if name == "randomized":
        return apply_variations(base, draws, name=name)
    if name == "certificate":
        return apply_variations(base, _certificate_case(rng, n), name=name)
    pushed = rng.choice(SHARED_KNOBS, size=int(rng.integers(1, 4)), replace=False)
    for i in sorted(int(i) for i in pushed):
        _push(rng, KNOBS[i], draws, base)
    for k in KNOBS[SHARED_KNOBS:]:
        if own[k.name].uniform() < 0.25:
            _push(own[k.name], k, draws, base)
    return apply_variations(base, draws, strict=False, name=name)


def outside_training(sc: Scenario, base: Scenario | None = None) -> list[str]:
    """The knobs of ``sc`` that lie outside :data:`SUITE_RANGES` (compared with ``base``, the
    paper's 0.1 Hz preset by default, for the scaled knobs)."""
    base = base if base is not None else preset("paper-0.1hz")
    return [k.name for k in KNOBS
            if any(not (k.suite[0] - 1e-12 <= v <= k.suite[1] + 1e-12) for v in k.read(sc, base))]


def resolve_scenario(spec: "str | Scenario", n_links: int | None = None) -> tuple[Scenario, str | None]:
    """(base scenario, suite name or None) for a preset name (the paper's, or a task-family
    member's such as ``"n5-0.1hz"``), a suite name or a Scenario. With ``n_links`` (2 to 7,
    :mod:`blf_gym.model.family`) a suite is drawn around that member's 0.1 Hz preset and a paper
    preset's name stands for that member's preset of the same frequency (``"paper-0.5hz"`` is
    ``"n5-0.5hz"`` at 5 links); a Scenario or a member's preset of another arm is refused, naming
    n_links."""
    if n_links is not None:
        n_links = check_n_links("scenario:", n_links)
    if isinstance(spec, Scenario):
        if n_links is not None and spec.arm.n_links != n_links:
            raise ValueError(f"scenario: n_links={n_links} but the Scenario's arm has {spec.arm.n_links} links; give "
                             "one of them, or a Scenario of that arm")
        return spec, None
    if isinstance(spec, str) and spec in SUITES:
        return family_base(n_links if n_links is not None else PAPER_LINKS), spec
    links = preset_links(spec) if isinstance(spec, str) else None
    if links is not None:
        if n_links is not None and links != n_links:
            if links != PAPER_LINKS or spec not in PRESETS:
                raise ValueError(f"scenario: the preset {spec!r} is the {links}-link arm's, not n_links={n_links}'s "
                                 f"(its presets: {list(family_presets(n_links))})")
            spec = family_presets(n_links)[list(PRESETS).index(spec)]
        return family_preset(spec), None
    names = [p for m in FAMILY_LINKS for p in family_presets(m)]
    raise ValueError(f"unknown scenario {spec!r}: scenario must be one of {names + list(SUITES)} or a "
                     "blf_gym.model.params.Scenario")
