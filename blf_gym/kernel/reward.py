"""The reward, declared as the table :data:`TERMS`, and the per-sample sums it is built from.

Each per-sample reward term is one row (a :class:`RewardTerm`): its name (the weight's field in
:class:`RewardWeights` and its key in ``info["reward_info"]``), its compiled per-sample function,
its default weight, unit, bound and meaning. The kernel calls ``accumulate_sample`` at every 1 ms
sample; that function is written from the table into each build of the kernel
(:func:`accumulate_source`) and adds each row's value to its column of :data:`SUM_COLUMNS`. The env turns one agent step's sums into the reward with :func:`step_outputs`,
which reads the weights in the table's order. A new term is one row (and its function), with a
default weight of 0 so existing agents score the same: docs/extending.md, "A reward term".
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit.layout import SUM_HEAD
from blf_gym.model.bounds import KA, KB
from blf_gym.model.params import check_bool, check_real
from blf_gym.kernel.status import ST_DIVERGED, ST_VIOL_SAMPLES, ST_VIOL_STEPS

__all__ = ["TERMS", "RewardTerm", "SUM_COLUMNS", "RewardWeights", "SCORE_REWARD", "PHI_CAP", "accumulate_source",
           "step_outputs", "score_step"]

PHI_CAP = 50.0
"""Bound on the score potential (nats): |phi| <= PHI_CAP, so a violation penalty of 2 * PHI_CAP per
unit of ``score`` weight puts every violating episode below every other."""
RMSE_FLOOR_SQ = float(np.radians(1e-12)) ** 2
"""The floor of a mean squared error (rad^2): score_vs_law's RMSE floor of 1e-12 degrees."""

@njit(cache=True, error_model="numpy", inline="always")
def tracking_sample(x, y, ref, bnd, u, cout, umax, n):
    """Sum over joints of (e1 / bound)^2, the true error normalized by the bound on its side."""
    s = 0.0
    for i in range(n):
        e = x[i] - ref[i]
        en = e / bnd[KA] if e >= 0.0 else e / bnd[KB]
        s += en * en
    return s


@njit(cache=True, error_model="numpy", inline="always")
def torque_sample(x, y, ref, bnd, u, cout, umax, n):
    """Sum over joints of (u / max_torque)^2, the applied torque."""
    s = 0.0
    for i in range(n):
        un = u[i] / umax
        s += un * un
    return s


class RewardTerm(NamedTuple):
    """One per-sample reward term: a row of :data:`TERMS`. Per agent step the term is ``-weight``
    times the mean of ``sample`` over the step's 1 ms samples and the joints."""

    name: str
    """The weight's field in :class:`RewardWeights` and the key in ``info["reward_info"]``."""
    sample: Any
    """A numba function ``(x, y, ref, bnd, u, cout, umax, n) -> float``: the term at one 1 ms sample,
    summed over the joints. ``x`` the state [q, qd, observer states, controller states] (true
    angles first), ``y`` the measured angles, ``ref`` [q_d, qd_d, qdd_d], ``bnd`` [k_a, k_a', k_a'',
    k_b, k_b', k_b''] (:data:`blf_gym.model.bounds.BOUND_SIGNALS`), ``u`` the applied torque, ``cout``
    the controller's outputs (u_law first), ``umax`` the torque limit."""
    weight: float
    """Default weight (>= 0); 0 keeps existing rewards."""
    unit: str
    """Unit of the per-step mean."""
    bound: float
    """The largest per-step mean while the arm stays inside its bounds: the ``alive`` default and
    the check that a violation never pays read it."""
    meaning: str


TERMS: tuple[RewardTerm, ...] = (
    RewardTerm("tracking", tracking_sample, 1.0, "-", 1.0,
               "(e1 / bound)^2: the tracking error normalized by the bound on its side (with ``relative``, "
               "the squared error relative to the law's; see RewardWeights)"),
    RewardTerm("torque", torque_sample, 0.01, "-", 1.0, "(u / max_torque)^2: the applied torque"),
)
"""The per-sample reward terms, declared once, in order."""
TRACKING = 0
"""The row of the tracking term, whose ``relative`` form compares with the law."""

SUM_COLUMNS = SUM_HEAD + tuple(f"sum_{t.name}" for t in TERMS)
"""Per-arm float sums of one kernel call: the largest ODE3 error estimate, the number of 1 ms
samples, each term's sum over the samples (:data:`TERMS`); then, per joint, the sum over samples
of e1^2 (rad^2)."""
SUM_ERR_MAX, SUM_SAMPLES = (SUM_COLUMNS.index(c) for c in ("error_estimate_max", "samples"))
SUM_TERM0 = len(SUM_HEAD)
"""The column of the first term's sum."""
SUM_E2_JOINT = len(SUM_COLUMNS)


@njit(cache=True, error_model="numpy", inline="always")
def errors_into(x, ref, bnd, sums, n):
    """Add each joint's e1^2 to its column of ``sums``; return whether the sample violates a bound."""
    bad = False
    for i in range(n):
        e = x[i] - ref[i]
        sums[SUM_E2_JOINT + i] += e * e
        if e >= bnd[KA] or e <= -bnd[KB]:
            bad = True
    return bad


ACCUMULATE_IMPORT = "from blf_gym.kernel.reward import SUM_SAMPLES, TERMS, errors_into"
"""What :func:`accumulate_source`'s function reads, imported at the top of a kernel's build."""


def accumulate_source() -> str:
    """The source of ``accumulate_sample``, written from :data:`TERMS` (one line per row) into each
    build of the kernel (:func:`blf_gym.kernel.simulate.build_source`), where it is compiled inline:
    it adds one 1 ms sample to the row ``sums`` (columns of SUM_COLUMNS, then e1^2 per joint), each
    term and the sample count, and returns whether the sample violates a bound. The arguments are
    RewardTerm.sample's. It reads the names of :data:`ACCUMULATE_IMPORT`."""
    lines = [f"_term_{k} = TERMS[{k}].sample  # {t.name}" for k, t in enumerate(TERMS)]
    lines += ["", "", '@njit(cache=True, error_model="numpy", inline="always")',
              "def accumulate_sample(x, y, ref, bnd, u, cout, umax, sums, n):",
              '    """One 1 ms sample into the sums: each term of TERMS, the count; True if it violates."""',
              "    bad = errors_into(x, ref, bnd, sums, n)"]
    lines += [f"    sums[{SUM_TERM0 + k}] += _term_{k}(x, y, ref, bnd, u, cout, umax, n)  # {t.name}"
              for k, t in enumerate(TERMS)]
    lines += ["    sums[SUM_SAMPLES] += 1.0", "    return bad", ""]
    return "\n".join(lines)


WVEC_HEAD = ("relative", "relative_cap", "alive", "violation", "terminate_on_violation", "violation_rate")
"""The first entries of :meth:`RewardWeights.pack`'s vector, which :func:`step_outputs` reads; each
term's weight follows, in the order of TERMS."""
W_RELATIVE, W_CAP, W_ALIVE, W_VIOLATION, W_TERMINATE, W_VIOLATION_RATE = range(len(WVEC_HEAD))
_W0 = len(WVEC_HEAD)  # the first term's weight


@dataclass(frozen=True)
class _Weights:
    """Per-agent-step reward r = alive - sum_k w_k E_k + score * (phi_k - phi_{k-1}) - violation *
    [ended by it] (- violation_rate * the step's share of violating samples, when termination is
    off), with one term per row of :data:`TERMS` (by default ``tracking`` and ``torque``):
    E_k is the row's per-sample value, averaged over the step's 1 ms samples and the joints, and
    w_k its weight, a field of this class named after the row.

    **The score term** (``score`` > 0; the env's default is :data:`SCORE_REWARD`) pays the change of
    a potential, phi_k = (1/n) sum_j 1/2 log(L_j(k) / P_j(k)), where P_j(k) and L_j(k) are the sums
    of e1_j^2 over the 1 ms samples so far of the policy's episode and of the reference law alone on
    the same scenario (the inner law in residual mode, the proposed law in plain mode; no noise),
    each floored at score_vs_law's RMSE floor and phi_0 = 0. The sum telescopes: an episode that
    runs to its end returns ``score * log(score_vs_law)`` of that episode (0 for the law itself,
    > 0 for a better policy), whatever the control period. phi is kept within +-PHI_CAP.

    Inside the bounds each E_k is at most its row's ``bound`` (the tracking term's is 1, the error
    normalized by the bound on its side; with ``relative``, ``relative_cap``), so every step inside
    the bounds loses at most ``sum_k w_k bound_k - alive`` against the alive term. Ending an episode
    early by a violation never pays when either

    * ``alive >= sum_k w_k bound_k`` (the default: every step inside the bounds earns r >= 0), or
    * ``violation >= (sum_k w_k bound_k - alive) * max_episode_steps``: the terminal penalty
      outweighs anything the rest of the episode could have cost (any discount factor).

    The env checks this at construction. The second form keeps rewards near zero, which suits
    critics when the tracking weight is large (the residual configs use it).
    """

    score: float = 0.0
    """Weight of the score term (>= 0; see above). With it, ``violation`` must be at least
    ``2 * PHI_CAP * score`` so that every violating episode returns less than any other."""
    alive: float | None = None
    """Reward per step for staying inside the bounds (>= 0); default sum_k w_k bound_k."""
    violation: float = 100.0
    """Penalty on the step that ends the episode by a violation or divergence (>= 0)."""
    violation_rate: float = 0.0
    """A violation cost for training without termination (``terminate_on_violation=False``; >= 0):
    each agent step loses ``violation_rate`` times the fraction of its 1 ms samples outside the
    bounds (the whole rate for a step shorter than 1 ms). It grows with the time spent outside, so a policy that violates for less time earns
    more, where the terminal penalty gives no slope once termination is off. With termination on
    it charges nothing (the episode ends on the first violating step and pays ``violation``)."""
    relative: bool = False
    """Measure tracking against the law, in the evaluation metric's own terms: E becomes the mean
    over joints of E_j / E_law_j, with E_j the step's mean of e1_j^2 (the squared error itself,
    not normalized by the bounds, like the RMSE) and E_law_j its mean over a whole episode of the
    reference law alone on the episode's scenario (the inner controller in residual mode, the
    proposed law in plain mode; no measurement noise). A policy at the law's level then loses
    about ``tracking`` per step on every scenario and joint, whatever their error scale, and the
    episode's sum of E is its MSE relative to the law's. Each ratio is capped at
    ``relative_cap``."""
    relative_cap: float = 100.0
    """Cap of each joint's ratio when ``relative`` (> 0); |E| <= relative_cap inside the bounds."""
    law_baseline: bool = False
    """With ``relative``: subtract the reference law's own squared error at the same agent step,
    so E_j = (e1_j^2 - e1_law_j^2) / E_law_j (each step's mean over its 1 ms samples). A policy at
    the law's level then gets about 0 per step, and the large, policy-independent swings of the
    error (the start-up transient, the elbow folds) cancel; the episode's sum of E is still its
    MSE relative to the law's, shifted by a constant. Variance reduction for learning."""

    def __post_init__(self) -> None:
        o = "RewardWeights"
        for name in ("relative", "law_baseline"):
            object.__setattr__(self, name, check_bool(o, name, getattr(self, name)))
        object.__setattr__(self, "relative_cap",
                           check_real(o, "relative_cap", self.relative_cap, lo=0.0, lo_open=True))
        for name in (*(t.name for t in TERMS), "violation", "violation_rate", "score"):
            object.__setattr__(self, name, check_real(o, name, getattr(self, name), lo=0.0))
        if self.alive is None:
            object.__setattr__(self, "alive", self.max_cost)
        object.__setattr__(self, "alive", check_real(o, "alive", self.alive, lo=0.0, none_ok=False,
                                                     hint=" (or None: sum of each term's weight times its bound)"))
        if self.law_baseline and not self.relative:
            raise ValueError("RewardWeights.law_baseline needs relative=True")

    @property
    def max_error(self) -> float:
        """The largest tracking E inside the bounds: 1, or ``relative_cap`` when ``relative``."""
        return float(self.relative_cap) if self.relative else TERMS[TRACKING].bound

    @property
    def max_cost(self) -> float:
        """sum_k w_k bound_k: the most the terms take from one step inside the bounds."""
        cost = None
        for k, t in enumerate(TERMS):
            c = getattr(self, t.name) * (self.max_error if k == TRACKING else t.bound)
            cost = c if cost is None else cost + c
        return 0.0 if cost is None else cost

    def pack(self, terminate_on_violation: bool) -> np.ndarray:
        """The weights as :func:`step_outputs` reads them (``wvec``): the entries of WVEC_HEAD, then
        each term's weight in the order of TERMS."""
        head = {"relative": float(self.relative), "relative_cap": self.relative_cap, "alive": self.alive,
                "violation": self.violation, "terminate_on_violation": float(terminate_on_violation),
                "violation_rate": self.violation_rate}
        return np.array([*(head[k] for k in WVEC_HEAD), *(getattr(self, t.name) for t in TERMS)])

    def check_episode(self, max_episode_steps: int) -> None:
        """Raise ValueError unless ending early by a violation never pays (see the class doc)."""
        if self.score > 0 and self.violation < 2 * PHI_CAP * self.score:
            raise ValueError(f"RewardWeights: with score = {self.score!r}, violation must be >= 2 * PHI_CAP * score = "
                             f"{2 * PHI_CAP * self.score:g} so that a violating episode returns less than any "
                             f"other; got violation = {self.violation!r}")
        deficit = self.max_cost - self.alive
        if deficit > 0 and self.violation < deficit * max_episode_steps:
            raise ValueError(
                f"RewardWeights: with alive = {self.alive!r} < the terms' most per step, sum of weight * bound = "
                f"{self.max_cost}, violation must be >= (that - alive) * max_episode_steps = "
                f"{deficit * max_episode_steps:g} so that a violation never pays; got violation = {self.violation!r}")


def _weights_doc() -> str:
    rows = "\n".join(f"    * ``{t.name}`` (default {t.weight:g}, bound {t.bound:g}, unit {t.unit}): {t.meaning}."
                      for t in TERMS)
    return f"{_Weights.__doc__}\n    The terms' weights (fields generated from :data:`TERMS`, each >= 0):\n\n{rows}\n"


RewardWeights = dataclasses.make_dataclass(
    "RewardWeights", [(t.name, float, dataclasses.field(default=t.weight)) for t in TERMS], bases=(_Weights,),
    frozen=True, namespace={"__module__": __name__, "__doc__": _weights_doc()})
"""The reward's weights: the fields of the base class, then one per row of :data:`TERMS`."""


STEP_ROWS = ("reward", "terminated", "truncated", "violated", "penalty", "alive") + tuple(t.name for t in TERMS)
"""The rows of :func:`step_outputs`' result, one per arm each: the reward, whether the episode
terminated or was truncated, whether the step violated a bound, then the reward's terms (the
penalty, the alive term, then one per row of :data:`TERMS`)."""
R_REWARD, R_TERMINATED, R_TRUNCATED, R_VIOLATED, R_PENALTY, R_ALIVE = range(6)
R_TERM0 = 6
"""The row of the first term of TERMS."""
_N_TERMS = len(TERMS)


@njit(cache=True, error_model="numpy")
def step_outputs(status, sums, law_e2, base, wvec, t_end, durations, out):
    """Per-arm reward terms, termination and truncation from the kernel's status and sums, into
    the rows of ``out`` (len(STEP_ROWS), N), with ``wvec`` from :meth:`RewardWeights.pack`.
    Returns flags: 1 if any arm's episode ended, 2 if any diverged."""
    N = status.shape[0]
    n = law_e2.shape[1]
    relative = wvec[W_RELATIVE] > 0.0
    cap, alive, w_violation, w_rate = wvec[W_CAP], wvec[W_ALIVE], wvec[W_VIOLATION], wvec[W_VIOLATION_RATE]
    terminate_on_violation = wvec[W_TERMINATE] > 0.0
    flags = 0
    for b in range(N):
        samples = max(sums[b, SUM_SAMPLES], 1.0)
        r = alive
        for k in range(_N_TERMS):
            if relative and k == TRACKING:
                acc = 0.0
                for j in range(n):
                    # base is zero unless law_baseline: then the law's own value at this agent step
                    rel = (sums[b, SUM_E2_JOINT + j] / samples - base[b, j]) / law_e2[b, j]
                    acc += min(max(rel, -cap), cap)
                mean = acc / n
            else:
                mean = sums[b, SUM_TERM0 + k] / (samples * n)
            term = -wvec[_W0 + k] * mean
            out[R_TERM0 + k, b] = term
            r = r + term
        v = status[b, ST_VIOL_STEPS] > 0
        term_ = status[b, ST_DIVERGED] != 0 or (v and terminate_on_violation)
        pen = w_violation if term_ else 0.0
        if v and not terminate_on_violation:
            # a step shorter than 1 ms has no sample: its violating integration steps count whole
            pen += w_rate * (status[b, ST_VIOL_SAMPLES] / samples if sums[b, SUM_SAMPLES] >= 1.0 else 1.0)
        out[R_REWARD, b] = r - pen
        out[R_TERMINATED, b] = 1.0 if term_ else 0.0
        out[R_TRUNCATED, b] = 1.0 if (not term_) and t_end[b] >= durations[b] - 1e-12 else 0.0
        out[R_VIOLATED, b] = 1.0 if v else 0.0
        out[R_PENALTY, b] = -pen
        out[R_ALIVE, b] = alive
        if term_ or out[R_TRUNCATED, b] > 0.0:
            flags |= 1
        if status[b, ST_DIVERGED] != 0:
            flags |= 2
    return flags


SCORE_REWARD = RewardWeights(score=1.0, tracking=0.0, torque=0.0, alive=0.0, violation=2 * PHI_CAP)
"""The env's default reward: the score term alone, and a violation penalty of 100. A full episode
returns log(score_vs_law), so returns rank policies as the benchmark does, any violating episode
returns less than every episode without one (<= -50 against >= -50), and the return does not
depend on ``control_period``. ``RewardWeights()`` (its field defaults) is the earlier shaped
reward (alive bonus, normalized tracking and torque), which the shipped plain agent and the configs
that list their weights were trained with."""


@njit(cache=True, error_model="numpy")
def score_step(ep_samples, ep_e2, law_cum, phi, weight, reward, term):
    """Add the score term to ``reward`` (N,) in place and write it to ``term``: per arm, the new
    potential from the episode's sample count ``ep_samples`` (N,), its per-joint sums of e1^2
    ``ep_e2`` (N, n), and the law's cumulative sums per sample ``law_cum`` (N, samples, n); ``phi``
    (N,) holds the previous potential and is updated."""
    N, n = ep_e2.shape
    for b in range(N):
        ns = int(ep_samples[b])
        new = 0.0
        if ns > 0:
            k = min(ns, law_cum.shape[1]) - 1
            fl = RMSE_FLOOR_SQ * ns
            acc = 0.0
            for j in range(n):
                p = ep_e2[b, j]
                if not p < 1e300:  # inf or NaN: a diverged episode
                    p = 1e300
                law = law_cum[b, k, j]
                if not law < 1e300:
                    law = 1e300
                acc += np.log(max(law, fl)) - np.log(max(p, fl))
            new = min(max(0.5 * acc / n, -PHI_CAP), PHI_CAP)
        d = weight * (new - phi[b])
        reward[b] += d
        term[b] = d
        phi[b] = new
