"""The reward and the per-sample sums it is built from, in one file (docs/extending.md, "A reward term").

The compiled kernel calls :func:`accumulate_sample` at every 1 ms sample and adds its terms to the
columns of :data:`SUM_COLUMNS`; the env turns one agent step's sums into the reward with
:func:`step_outputs` and the weights of :class:`RewardWeights`. A new reward term built from
per-sample signals is a change in this file only: a column, its line in ``accumulate_sample``, a
weight (default 0, so existing agents score the same) and its line in ``step_outputs``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .bounds import KA, KB
from .params import check_bool, check_real
from .status import ST_DIVERGED, ST_VIOL_STEPS

__all__ = ["SUM_COLUMNS", "RewardWeights", "SCORE_REWARD", "PHI_CAP", "accumulate_sample", "step_outputs",
           "score_step"]

PHI_CAP = 50.0
"""Bound on the score potential (nats): |phi| <= PHI_CAP, so a violation penalty of 2 * PHI_CAP per
unit of ``score`` weight puts every violating episode below every other."""
RMSE_FLOOR_SQ = float(np.radians(1e-12)) ** 2
"""The floor of a mean squared error (rad^2): score_vs_law's RMSE floor of 1e-12 degrees."""

SUM_COLUMNS = ("error_estimate_max", "sum_e1_over_bound_sq", "sum_u_over_max_sq", "samples")
"""Per-arm float sums of one kernel call, declared once: the largest ODE3 error estimate, the sums
over 1 ms samples and joints of (e1/bound)^2 and (u/max_torque)^2, the number of samples; then,
per joint, the sum over samples of e1^2 (rad^2)."""
SUM_ERR_MAX, SUM_EN2, SUM_UN2, SUM_SAMPLES = (SUM_COLUMNS.index(c) for c in SUM_COLUMNS)
SUM_E2_JOINT = len(SUM_COLUMNS)


@njit(cache=True, error_model="numpy", inline="always")
def accumulate_sample(x, y, ref, bnd, u, cout, umax, sums, n):
    """Add one 1 ms sample's terms to the row ``sums`` (columns of SUM_COLUMNS, then e1^2 per joint);
    returns whether the sample violates a bound. The signals at the sample: ``x`` the state [q, qd,
    observer states, controller states] (true angles first), ``y`` the measured angles, ``ref``
    [q_d, qd_d, qdd_d], ``bnd`` [k_a, k_a', k_a'', k_b, k_b', k_b''], ``u`` the commanded torque,
    ``cout`` the controller's outputs (u_law first), ``umax`` the torque limit."""
    en2 = 0.0
    un2 = 0.0
    bad = False
    for i in range(n):
        e = x[i] - ref[i]
        en = e / bnd[KA] if e >= 0.0 else e / bnd[KB]
        en2 += en * en
        sums[SUM_E2_JOINT + i] += e * e
        un = u[i] / umax
        un2 += un * un
        if e >= bnd[KA] or e <= -bnd[KB]:
            bad = True
    sums[SUM_EN2] += en2
    sums[SUM_UN2] += un2
    sums[SUM_SAMPLES] += 1.0
    return bad


@dataclass(frozen=True)
class RewardWeights:
    """Per-agent-step reward r = alive - tracking * E - torque * U + score * (phi_k - phi_{k-1})
    - violation * [ended by it].

    **The score term** (``score`` > 0; the env's default is :data:`SCORE_REWARD`) pays the change of
    a potential, phi_k = (1/n) sum_j 1/2 log(L_j(k) / P_j(k)), where P_j(k) and L_j(k) are the sums
    of e1_j^2 over the 1 ms samples so far of the policy's episode and of the reference law alone on
    the same scenario (the inner law in residual mode, the proposed law in plain mode; no noise),
    each floored at score_vs_law's RMSE floor and phi_0 = 0. The sum telescopes: an episode that
    runs to its end returns ``score * log(score_vs_law)`` of that episode (0 for the law itself,
    > 0 for a better policy), whatever the control period. phi is kept within +-PHI_CAP.

    E is the mean over the step's 1 ms samples and the joints of (e1 / bound)^2, the error
    normalized by the bound on its side (so E <= 1 while inside the bounds); U is the mean of
    (u / max_torque)^2 (<= 1). With ``relative`` (below) E is a ratio to the law's error instead,
    capped at ``relative_cap`` in size, so "max E" below is 1 or ``relative_cap``. Every step
    inside the bounds therefore loses at most ``tracking * max E + torque - alive`` against the
    alive term. Ending an episode early by a violation
    never pays when either

    * ``alive >= tracking * max E + torque`` (the default: every step inside the bounds earns
      r >= 0), or
    * ``violation >= (tracking * max E + torque - alive) * max_episode_steps``: the terminal penalty
      outweighs anything the rest of the episode could have cost (any discount factor).

    The env checks this at construction. The second form keeps rewards near zero, which suits
    critics when the tracking weight is large (the residual configs use it).
    """

    tracking: float = 1.0
    """Weight of the normalized squared tracking error (>= 0)."""
    score: float = 0.0
    """Weight of the score term (>= 0; see above). With it, ``violation`` must be at least
    ``2 * PHI_CAP * score`` so that every violating episode returns less than any other."""
    torque: float = 0.01
    """Weight of the normalized squared torque (>= 0)."""
    alive: float | None = None
    """Reward per step for staying inside the bounds (>= 0); default tracking * max E + torque."""
    violation: float = 100.0
    """Penalty on the step that ends the episode by a violation or divergence (>= 0)."""
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
        for name in ("tracking", "torque", "violation", "score"):
            object.__setattr__(self, name, check_real(o, name, getattr(self, name), lo=0.0))
        if self.alive is None:
            object.__setattr__(self, "alive", self.tracking * self.max_error + self.torque)
        object.__setattr__(self, "alive", check_real(o, "alive", self.alive, lo=0.0, none_ok=False,
                                                     hint=" (or None: tracking * max E + torque)"))
        if self.law_baseline and not self.relative:
            raise ValueError("RewardWeights.law_baseline needs relative=True")

    @property
    def max_error(self) -> float:
        """The largest E inside the bounds: 1, or ``relative_cap`` when ``relative``."""
        return float(self.relative_cap) if self.relative else 1.0

    def pack(self, terminate_on_violation: bool) -> np.ndarray:
        """The weights as :func:`step_outputs` reads them (``wvec``)."""
        return np.array([float(self.relative), self.relative_cap, self.alive, self.tracking, self.torque,
                         self.violation, float(terminate_on_violation)])

    def check_episode(self, max_episode_steps: int) -> None:
        """Raise ValueError unless ending early by a violation never pays (see the class doc)."""
        if self.score > 0 and self.violation < 2 * PHI_CAP * self.score:
            raise ValueError(f"RewardWeights: with score = {self.score!r}, violation must be >= 2 * PHI_CAP * score = "
                             f"{2 * PHI_CAP * self.score:g} so that a violating episode returns less than any "
                             f"other; got violation = {self.violation!r}")
        deficit = self.tracking * self.max_error + self.torque - self.alive
        if deficit > 0 and self.violation < deficit * max_episode_steps:
            raise ValueError(
                f"RewardWeights: with alive = {self.alive!r} < tracking * max E + torque = "
                f"{self.tracking * self.max_error + self.torque}, violation must be >= (tracking * max E "
                f"+ torque - alive) * max_episode_steps = {deficit * max_episode_steps:g} so that a "
                f"violation never pays; got violation = {self.violation!r}")


STEP_ROWS = ("reward", "terminated", "truncated", "violated", "tracking", "torque", "penalty", "alive")
"""The rows of :func:`step_outputs`' result, one per arm each: the reward, whether the episode
terminated or was truncated, whether the step violated a bound, then the reward's terms."""
R_REWARD, R_TERMINATED, R_TRUNCATED, R_VIOLATED, R_TRACKING, R_TORQUE, R_PENALTY, R_ALIVE = (
    STEP_ROWS.index(r) for r in STEP_ROWS)


@njit(cache=True, error_model="numpy")
def step_outputs(status, sums, law_e2, base, wvec, t_end, durations, out):
    """Per-arm reward terms, termination and truncation from the kernel's status and sums, into
    the rows of ``out`` (len(STEP_ROWS), N). ``wvec`` = [relative, relative_cap, alive, tracking, torque,
    violation, terminate_on_violation]. Returns flags: 1 if any arm's episode ended, 2 if any
    diverged."""
    N = status.shape[0]
    n = law_e2.shape[1]
    relative = wvec[0] > 0.0
    cap, alive, w_tracking, w_torque, w_violation = wvec[1], wvec[2], wvec[3], wvec[4], wvec[5]
    terminate_on_violation = wvec[6] > 0.0
    flags = 0
    for b in range(N):
        samples = max(sums[b, SUM_SAMPLES], 1.0)
        if relative:
            acc = 0.0
            for j in range(n):
                # base is zero unless law_baseline: then the law's own value at this agent step
                r = (sums[b, SUM_E2_JOINT + j] / samples - base[b, j]) / law_e2[b, j]
                acc += min(max(r, -cap), cap)
            tr = acc / n
        else:
            tr = sums[b, SUM_EN2] / (samples * n)
        tq = sums[b, SUM_UN2] / (samples * n)
        v = status[b, ST_VIOL_STEPS] > 0
        term = status[b, ST_DIVERGED] != 0 or (v and terminate_on_violation)
        pen = w_violation if term else 0.0
        out[R_REWARD, b] = alive - w_tracking * tr - w_torque * tq - pen
        out[R_TERMINATED, b] = 1.0 if term else 0.0
        out[R_TRUNCATED, b] = 1.0 if (not term) and t_end[b] >= durations[b] - 1e-12 else 0.0
        out[R_VIOLATED, b] = 1.0 if v else 0.0
        out[R_TRACKING, b] = -w_tracking * tr
        out[R_TORQUE, b] = -w_torque * tq
        out[R_PENALTY, b] = -pen
        out[R_ALIVE, b] = alive
        if term or out[R_TRUNCATED, b] > 0.0:
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
