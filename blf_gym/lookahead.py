"""The look-ahead hand-back: a residual is withheld, and the law acts alone, from ``horizon`` seconds
before any moment where the reference is demanding until ``horizon`` after it (docs/model.md
section 11, "The look-ahead hand-back").

Where the law only just keeps the bounds (the fast folds of the reference at high frequency), a
residual acting beforehand moves the state, and from the moved state the law alone can fail
where from its own it did not. The rule here removes that: the reference and the bounds are known
in advance (the law already reads their derivatives), so the hand-back can come before the
demanding moment rather than at it. Once the law acts alone, the difference between the state the
residual left and the law's own trajectory decays at the law's closed-loop rate; ``horizon`` is
the time for it to fall a hundredfold (``docs/fallback/derive.py`` measures it on the training
suite), so through the demanding moment the residual's trace is about 1 % of what it was (not
less: friction's and the dead-zone's switching leave a floor, 1e-4 rad at most where the law was
stressed on those draws).

The demand at time t is ``max_j |qdd_d,j(t)| / min(k_a(t), k_b(t))`` (1/s^2): the reference's largest
joint acceleration per radian of the narrower bound. A control period is handed back when the
demand reaches ``demand`` anywhere in ``[t_k - horizon, t_k + T + horizon]`` (the period's own hold
time ``T`` included). The default threshold is the smallest demand that, on 80 draws of the training
suite, came within ``horizon`` before a moment where the law alone used more than half of a
bound's width, away from a force step (``docs/fallback/derive.py``; no held-out suite is read).

It is a schedule of the scenario's known signals, computed once per episode (a few ms) and applied
to the residual before the filter, so every env path (single, vector, evaluation, falsification)
shares it. It does not foresee what is unknown in advance (a force step's onset, a payload): the
innovation hand-back (``handback``) answers those after the fact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .bounds import error_bounds
from .params import Scenario
from .reference import joint_reference

__all__ = ["LookaheadParams", "LOOKAHEAD_KEYS", "reference_demand", "lookahead_gate", "split_lookahead"]

DEFAULT_HORIZON = 0.35
"""s: the law alone shrank a difference of state a hundredfold within 0.23-0.34 s on 16 draws of the
training suite (docs/fallback/derive.json, ``horizon_s``: the slowest, rounded up to 50 ms)."""

DEFAULT_DEMAND = 930.0
"""1/s^2: the smallest demand the training suite tied to a moment where the law alone used more than
half a bound's width (docs/fallback/derive.json, ``demand_star``, 932.1, rounded down)."""

LOOKAHEAD_KEYS = ("lookahead", "demand")
"""The keys of a residual filter's spec that configure this hand-back rather than the filter:
``"barrier:handback=0.0033,lookahead=0.3"`` (``lookahead`` the horizon in s, ``demand`` the
threshold in 1/s^2, default :data:`DEFAULT_DEMAND`)."""

GRID = 1e-3
"""s: the demand is sampled on this grid (the trajectories' own sample period)."""


@dataclass(frozen=True)
class LookaheadParams:
    """The look-ahead hand-back's horizon and demand threshold."""

    horizon: float = DEFAULT_HORIZON
    """s, > 0 and at most 5: how long before and after a demanding moment the law acts alone."""
    demand: float = DEFAULT_DEMAND
    """1/s^2, > 0: the reference demand at and above which the law acts alone."""

    def __post_init__(self) -> None:
        for name, lo, hi, unit in (("horizon", 0.0, 5.0, "s"), ("demand", 0.0, math.inf, "1/s^2")):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo < v <= hi:
                raise ValueError(f"LookaheadParams.{name} must be a number in ({lo:g}, {hi:g}] {unit}, got {v!r}")
            object.__setattr__(self, name, float(v))


def split_lookahead(spec: "str | None") -> "tuple[str | None, LookaheadParams | None]":
    """A residual filter's spec without the look-ahead keys, and the look-ahead they ask for (None
    when ``lookahead`` is absent): ``"barrier:handback=0.0033,lookahead=0.3"`` ->
    ``("barrier:handback=0.0033", LookaheadParams(horizon=0.3))``. Any other spec is returned as it is."""
    if not isinstance(spec, str) or ":" not in spec:
        return spec, None
    name, _, rest = spec.partition(":")
    keep, ours = [], {}
    for part in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = part.partition("=")
        if key.strip() in LOOKAHEAD_KEYS:
            try:
                ours[key.strip()] = float(value)
            except ValueError:
                raise ValueError(f"residual_filter {spec!r}: {part!r} is not key=number") from None
        else:
            keep.append(part)
    if not ours:
        return spec, None
    if "lookahead" not in ours:
        raise ValueError(f"residual_filter {spec!r}: 'demand' sets the look-ahead hand-back's threshold and needs "
                         "'lookahead=SECONDS' beside it")
    rest_spec = name + (":" + ",".join(keep) if keep else "")
    return rest_spec, LookaheadParams(horizon=ours["lookahead"], demand=ours.get("demand", DEFAULT_DEMAND))


def reference_demand(t: "np.ndarray | float", scenario: Scenario) -> np.ndarray:
    """The reference's demand at times ``t``: ``max_j |qdd_d,j| / min(k_a, k_b)``, 1/s^2."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    _, _, qdd = joint_reference(t, scenario)
    ka, kb = error_bounds(t, scenario.bounds)
    return np.abs(np.asarray(qdd).reshape(len(t), -1)).max(axis=1) / np.minimum(ka, kb)


def lookahead_gate(scenario: Scenario, period: float, params: LookaheadParams) -> np.ndarray:
    """Whether each control period ``k`` of ``scenario``'s episode (``t_k = k * period``, k = 0 ..
    ceil(duration / period)) is handed back: the demand reaches ``params.demand`` somewhere in
    ``[t_k - horizon, t_k + period + horizon]``, sampled every :data:`GRID` s."""
    if not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
        raise ValueError(f"lookahead_gate: period must be a number > 0 s, got {period!r}")
    duration = scenario.sim.duration
    steps = int(math.ceil(duration / period - 1e-9)) + 1
    ts = np.arange(0.0, steps * period + params.horizon + GRID, GRID)
    hot = reference_demand(ts, scenario) >= params.demand
    # hot samples' times, then for each period whether one falls in its window
    t_hot = ts[hot]
    lo = np.arange(steps) * period - params.horizon
    hi = np.arange(steps) * period + period + params.horizon
    first = np.searchsorted(t_hot, lo - 1e-12, side="left")
    return (first < len(t_hot)) & (t_hot[np.minimum(first, max(len(t_hot) - 1, 0))] <= hi + 1e-12) \
        if len(t_hot) else np.zeros(steps, dtype=bool)
