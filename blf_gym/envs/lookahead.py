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

**The predictive rule** (``predict=M``, in place of the demand): the law alone is run ahead, once
per episode, on the design plant (the scenario's reference and bounds, the paper's friction, dead
zone and payload, no external force, no noise: what is known before the episode), and a period is
handed back when that run's smallest normalized margin in the same window falls below ``M`` (the
barrier filter's m1, 0.5, by default: the law predicted to use more than half of a bound). It hands
back only where the law is predicted to be stressed, not at every fast stretch of the reference;
it costs one law episode per new scenario (about 0.3 s for 30 s), batched over the arms reset
together and cached.

Either rule is a schedule of what is known in advance, computed once per episode and applied to
the residual before the filter, so every env path (single, vector, evaluation, falsification)
shares it. It does not foresee what is unknown (a force step's onset, the true friction, a
payload): the innovation hand-back (``handback``) answers those after the fact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from blf_gym.model.bounds import error_bounds
from blf_gym.model.params import ArmParams, DeadZoneParams, FrictionParams, Scenario
from blf_gym.model.reference import joint_reference

__all__ = ["LookaheadParams", "LOOKAHEAD_KEYS", "reference_demand", "lookahead_gate", "split_lookahead",
           "design_scenario", "margin_gate", "predicted_gates"]

DEFAULT_HORIZON = 0.35
"""s: the law alone shrank a difference of state a hundredfold within 0.23-0.34 s on 16 draws of the
training suite (docs/fallback/derive.json, ``horizon_s``: the slowest, rounded up to 50 ms)."""

DEFAULT_DEMAND = 930.0
"""1/s^2: the smallest demand the training suite tied to a moment where the law alone used more than
half a bound's width (docs/fallback/derive.json, ``demand_star``, 932.1, rounded down)."""

LOOKAHEAD_KEYS = ("lookahead", "demand", "predict")
"""The keys of a residual filter's spec that configure this hand-back rather than the filter:
``"barrier:handback=0.0033,lookahead=0.35"`` (``lookahead`` the horizon in s, ``demand`` the
threshold in 1/s^2, default :data:`DEFAULT_DEMAND`; or ``predict=0.5``, the predictive rule's
margin)."""

GRID = 1e-3
"""s: the demand is sampled on this grid (the trajectories' own sample period)."""


@dataclass(frozen=True)
class LookaheadParams:
    """The look-ahead hand-back's horizon and demand threshold."""

    horizon: float = DEFAULT_HORIZON
    """s, > 0 and at most 5: how long before and after a demanding moment the law acts alone."""
    demand: float = DEFAULT_DEMAND
    """1/s^2, > 0: the reference demand at and above which the law acts alone."""
    predict: float | None = None
    """None (the demand rule), or the predictive rule's normalized margin in (0, 1): the law acts alone
    where the law alone on the design plant is predicted to come closer than this to a bound."""

    def __post_init__(self) -> None:
        checks = [("horizon", 0.0, 5.0, "s"), ("demand", 0.0, math.inf, "1/s^2")]
        if self.predict is not None:
            checks.append(("predict", 0.0, 1.0 - 1e-12, "(a normalized margin, below 1)"))
        for name, lo, hi, unit in checks:
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
    if "demand" in ours and "predict" in ours:
        raise ValueError(f"residual_filter {spec!r}: give 'demand' (the demand rule) or 'predict' (the predictive "
                         "rule), not both")
    rest_spec = name + (":" + ",".join(keep) if keep else "")
    return rest_spec, LookaheadParams(horizon=ours["lookahead"], demand=ours.get("demand", DEFAULT_DEMAND),
                                      predict=ours.get("predict"))


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
    return _windows_hit(ts[reference_demand(ts, scenario) >= params.demand], period, steps, params.horizon)


def _windows_hit(times: np.ndarray, period: float, steps: int, horizon: float) -> np.ndarray:
    """For each control period k, whether one of the sorted ``times`` falls in
    ``[k * period - horizon, (k + 1) * period + horizon]``: both rules' window."""
    if not len(times):
        return np.zeros(steps, dtype=bool)
    lo = np.arange(steps) * period - horizon
    hi = lo + period + 2 * horizon
    first = np.searchsorted(times, lo - 1e-12, side="left")
    return (first < len(times)) & (times[np.minimum(first, len(times) - 1)] <= hi + 1e-12)


def design_scenario(scenario: Scenario) -> Scenario:
    """What is known of ``scenario`` before its episode: its reference, bounds, duration and initial
    error, on the paper's plant (its friction, dead zone and arm with the paper's payload), with no
    external force and no noise. The predictive rule runs the law alone on it."""
    arm = ArmParams() if scenario.arm.n_links == ArmParams().n_links else scenario.arm
    force = replace(scenario.force, wrench=(0.0,) * len(scenario.force.wrench))
    return replace(scenario, name=f"{scenario.name}:design", arm=arm, friction=FrictionParams(),
                   dead_zone=DeadZoneParams(), force=force, angle_noise_std=0.0)


def margin_gate(t: np.ndarray, margin: np.ndarray, period: float, steps: int, horizon: float,
                threshold: float) -> np.ndarray:
    """Whether each of ``steps`` control periods is handed back: the smallest of ``margin`` (the law's
    normalized margin over joints, sampled at ``t``) in ``[t_k - horizon, t_k + period + horizon]``
    is below ``threshold``."""
    return _windows_hit(np.asarray(t)[np.asarray(margin) < threshold], period, steps, horizon)


def predicted_gates(scenarios: "list[Scenario]", controller: Any, observer: Any, period: float,
                    params: LookaheadParams) -> list[np.ndarray]:
    """The predictive rule's schedule for each scenario (:func:`design_scenario`, the law alone, then
    :func:`margin_gate` at ``params.predict``), the law's runs batched in one kernel call. A run that
    diverges hands back everything from its start."""
    from blf_gym.kernel.simulate import simulate_batch  # the kernel: imported when a predictive rule is asked for

    runs = simulate_batch([design_scenario(sc) for sc in scenarios], controller, observer)
    out = []
    for sc, tr in zip(scenarios, runs):
        steps = int(math.ceil(sc.sim.duration / period - 1e-9)) + 1
        if tr.diverged:
            out.append(np.ones(steps, dtype=bool))
            continue
        s = tr.signals
        tt = np.asarray(s["t"])
        e = np.asarray(s["e1"]).reshape(len(tt), -1)
        ka, kb = np.asarray(s["k_a"]).reshape(len(tt), -1), np.asarray(s["k_b"]).reshape(len(tt), -1)
        m = np.where(e >= 0.0, (ka - e) / ka, (kb + e) / kb).min(axis=1)
        out.append(margin_gate(tt, m, period, steps, params.horizon, params.predict))
    return out
