"""The batched environment logic shared by :class:`~blf_gym.envs.env.PlanarBLFEnv` (one arm) and
:class:`~blf_gym.envs.vector.PlanarBLFVectorEnv` (N arms): scenario handling, the agent step over the
compiled closed loop, observations, rewards and info. There is no other copy of this logic.
"""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)

from blf_gym.jit.layout import LAST, MARGINS, REF, STATE
from blf_gym.model.bounds import BOUND_LEN, KA, KB
from blf_gym.plugins.blocks import NO_CONTROLLER, Controller, Observer, ResidualFilter
from blf_gym.plugins.registry import available_controllers, available_observers, make_controller, make_observer
from blf_gym.kernel.reward import (R_ALIVE, R_PENALTY, R_REWARD, R_TERM0, R_TERMINATED, R_TRUNCATED, R_VIOLATED, SCORE_REWARD,
                     STEP_ROWS, SUM_E2_JOINT, SUM_SAMPLES, TERMS, RewardWeights, score_step, step_outputs)
from blf_gym.model.family import PAPER_LINKS, preset_links
from blf_gym.model.params import (ArmParams, DT_MIN, MAX_DURATION, PRESETS, Scenario, check_bool, check_int, check_real, check_reals,
                     usable_cores)
from blf_gym.envs.observation import (OBSERVATION, SQUASH_DISTURBANCE, SQUASH_REF_ACCELERATION, SQUASH_VELOCITY,
                          groups, observation_index, observation_layout, observe_batch, optional_observations,
                          plan_row)
from blf_gym.envs.levels import DEFAULT_LEVEL, apply_level, check_level
from blf_gym.envs.lookahead import design_scenario, lookahead_gate, predicted_gates, split_lookahead
from blf_gym.envs.scenarios import (SUITES, VARIATIONS, apply_variations, check_variations, resolve_scenario, sample_suite,
                        widen_bounds)
from blf_gym.kernel.simulate import CHANNELS, ClosedLoop, divergence_message
from blf_gym.kernel.status import (N_LAST, ST_ASSUMPTION_FAILURES, ST_DIVERGED,
                     ST_FILTER_BREACHES, ST_FIRST_VIOL, ST_SAT_STEPS, ST_VIOL_SAMPLES, ST_VIOL_STEPS)

__all__ = ["RewardWeights", "EnvCore", "ARGUMENTS", "INFO_KEYS", "Argument", "InfoKey", "MAX_ARMS", "MAX_BOUND_SCALE", "MAX_REFERENCE_BYTES", "OBSERVATION", "observation_layout",
           "observation_index", "SQUASH_VELOCITY", "SQUASH_REF_ACCELERATION", "SQUASH_DISTURBANCE"]




MAX_BOUND_SCALE = 15.0
"""The widest funnel a training curriculum may ask for (``bound_scale``): 15 times the paper's is
0.3 and 0.6 rad at the floors, and keeps the observation's bound entries inside their boxes
(k_b(0) = 15 x 0.64 = 9.6 rad of at most 10)."""
CORE_BOUND_SCALE = property(
    lambda env: env.core.bound_scale,
    lambda env, value: setattr(env.core, "bound_scale", value),
    doc="""The factor on the funnel's width of the episodes started from now on (a training
    curriculum's knob, 1 to :data:`MAX_BOUND_SCALE`; 1, the default, is the benchmark), read and
    set on the env's core: see :attr:`EnvCore.bound_scale`. The single and the vector env both
    expose it as ``bound_scale``.""")
MAX_ARMS = 65_536
"""Most arms in one env core (``num_envs``). Every arm keeps its episode's arrays (the default score
reward's reference, 0.7 MB per arm at 30 s); larger batches are refused at construction, not
allocated (10**400 arms used to raise OverflowError)."""
MAX_REFERENCE_BYTES = 8 * 2 ** 30
"""Most memory the reward's per-episode references (the law's running error for the score term,
its per-step error for the relative one) may take over all arms, bytes; beyond it the env refuses
to be built and says which arguments to lower (``num_envs``, ``duration``) or which reward needs
none (``reward_weights={}``, the shaped reward)."""

class Argument(NamedTuple):
    """One keyword argument of the env (``gym.make("PlanarBLF-v0", **kwargs)`` and the vector env):
    a row of :data:`ARGUMENTS`. Its default is :class:`EnvCore`'s own (read from the signature)."""

    name: str
    unit: str
    accepted: str
    meaning: str


ARGUMENTS: tuple[Argument, ...] = (
    Argument("scenario", "-", '"paper-0.1hz", "paper-0.5hz", a task-family preset ("n5-0.1hz"), "randomized", "stress" '
             'or a Scenario',
             'the episode\'s plant, reference, bounds and disturbances; "randomized" draws the training suite per '
             'episode, "stress" the held-out stress suite (for evaluation only)'),
    Argument("n_links", "-", "None (the scenario's arm: 3 for the paper's) or 2 to 7",
             "the task family's arm of that many links (blf_gym.model.family, docs/family.md): a suite is drawn "
             'around its 0.1 Hz preset and "paper-0.1hz" / "paper-0.5hz" stand for its presets; laws and observers '
             "given by name take that arm as their model, with their gains carried to it"),
    Argument("controller", "-", 'None or "none", "bc", "lesobc", "proposed", a registered plug-in\'s name or a '
             'Controller',
             "None (or \"none\"): plain mode, the action is the torque. A law: residual mode, u = u_law + residual_scale * a, "
             "the law run at every integration stage"),
    Argument("observer", "-", '"leso", a registered name or an Observer providing x2_hat and x3_hat',
             "the state observer inside the env (the observation's velocity and disturbance estimates)"),
    Argument("residual_scale", "N m", "> 0", "the residual's torque at action 1 (residual mode)"),
    Argument("control_period", "s", "> 0, at most the duration; a whole number of 1 ms samples, or a divisor of 1 ms "
             "down to one integration step", "the agent's step: the action is held this long"),
    Argument("privileged", "-", "True or False", "append the true velocity and disturbance to the observation"),
    Argument("terminate_on_violation", "-", "True or False",
             "end the episode at the first integration step outside the bounds; False counts violations in "
             'info["cost"] and info["violating_samples"] and runs on'),
    Argument("angle_noise_std", "rad", ">= 0 or None (the scenario's)",
             "Gaussian noise on the measured angles (observer, law and observation)"),
    Argument("duration", "s", "> 0, at most blf_gym.model.params.MAX_DURATION (3600), or None (the scenario's, 30)",
             "the episode's simulated time; a whole number of control periods"),
    Argument("max_torque", "N m", "> 0 or None (the scenario's, 150)",
             "the actuator's limit; plain mode's action scale unless action_scale says otherwise"),
    Argument("action_scale", "N m", 'None (max_torque), "law" (blf_gym.envs.envcore.law_action_scale), a number or one '
             "per joint, each > 0 and at most max_torque",
             "plain mode: the torque per joint at action 1 (a learner's exploration in the torques the task "
             "needs); the actuator's limit stays max_torque. Refused in residual mode (residual_scale)"),
    Argument("start_time", "s", "None, a time or a (low, high) range, in [0, duration - control_period]",
             "a training aid: each episode starts at that time of the reference (a range: drawn per episode from "
             "the arm's generator), rounded to whole control periods, the arm on the reference; needs a reward "
             "without the law's reference (reward_weights with score 0 and relative off). Scoring always starts at 0"),
    Argument("dt", "s", ">= 1e-7 or None (the scenario's, 1e-4)", "the ODE3 integration step"),
    Argument("variations", "-", "a dict of blf_gym.envs.scenarios.VARIATIONS",
             "changes to the scenario (with \"randomized\", they override the suite's draw); reset(options=...) "
             "takes the same per episode"),
    Argument("reward_weights", "-", "None, a RewardWeights or a dict of its fields",
             "None: the score reward; a dict: the shaped reward with those weights"),
    Argument("observation_extras", "-", "names of optional entries of blf_gym.envs.observation.OBSERVATION",
             "optional observation entries appended after the others, in the order named"),
    Argument("residual_filter", "-", 'None, "barrier", "cbf" or a registered filter of the law, optionally with '
             'parameters ("barrier:handback=0.0033"); in residual mode also lookahead=SECONDS[,demand=D or ,predict=M]',
             "a safety filter between the action and the actuator (residual mode: on the residual; plain mode: on "
             "the torque minus the proposed law's); lookahead: the look-ahead hand-back (blf_gym.envs.lookahead)"),
    Argument("bound_scale", "-", "1 to MAX_BOUND_SCALE (15)",
             "a training curriculum's factor on the funnel's width; the benchmark is 1. Also settable between "
             "episodes as env.unwrapped.bound_scale"),
    Argument("level", "-", "0 to 3 (blf_gym.envs.levels.LEVELS)",
             "difficulty level, applied to every scenario the env draws or resets to from its own scenario: "
             "0 the nominal plant in 10x wider bounds, 1 the scenario's plant in 10x wider bounds, 2 without the "
             "external force, 3 the full benchmark (docs/levels.md)"),
    Argument("threads", "-", "1 to the cores the process may use (blf_gym.model.params.usable_cores), or None (1 for "
             "the single env, half the cores for the vector env)",
             "numba threads the arms are split over"),
    Argument("record", "-", "True or False", "keep the episode's 1 ms signals for env.unwrapped.trajectory()"),
    Argument("record_channels", "-", "names of blf_gym.kernel.simulate.CHANNELS, or None (all)",
             "the signals kept with record; fewer keep less memory"),
)
"""The env's keyword arguments, declared once (the docs' table is made from it; a test checks
that its names are :class:`EnvCore`'s)."""


class InfoKey(NamedTuple):
    """One key of the env's ``info`` dict: a row of :data:`INFO_KEYS`."""

    name: str
    unit: str
    when: str
    meaning: str


INFO_KEYS: tuple[InfoKey, ...] = (
    InfoKey("time", "s", "always", "simulated time"),
    InfoKey("e1", "rad", "always", "the true tracking error q - q_d, per joint"),
    InfoKey("k_a", "rad", "always", "the upper bound (e1 < k_a)"),
    InfoKey("k_b", "rad", "always", "the lower bound (e1 > -k_b)"),
    InfoKey("g_upper", "rad", "always", "constraint margin e1 - k_a (<= 0 is safe)"),
    InfoKey("g_lower", "rad", "always", "constraint margin -k_b - e1 (<= 0 is safe)"),
    InfoKey("scenario", "-", "reset", "the episode's Scenario"),
    InfoKey("cost", "-", "step", "1.0 if any integration step of this agent step broke a bound, else 0.0"),
    InfoKey("violating_samples", "-", "step", "violating 1 ms samples in this agent step"),
    InfoKey("u", "N m", "step", "the applied torque, at the start of the step's last integration step"),
    InfoKey("u_law", "N m", "step", "the inner law's torque, at the same instant"),
    InfoKey("u_residual", "N m", "step", "the residual's torque (residual mode), after any filter"),
    InfoKey("saturated", "-", "step", "the actuator limit clipped the torque at some integration step"),
    InfoKey("x3", "rad/s^2", "step",
            "the true lumped disturbance against the nominal model, at the step's last 1 ms sample (t_end - 1 ms)"),
    InfoKey("x3_hat", "rad/s^2", "step", "the observer's estimate of x3, at the same sample"),
    InfoKey("controller_outputs", "-", "step",
            "the inner law's published outputs besides u_law, by name, at the start of the step's last "
            "integration step (the proposed law's z1 rad, z2_hat rad/s, barrier 1/rad)"),
    InfoKey("reward_info", "-", "step", "the reward's terms by name: alive, one per reward term, score, violation"),
    InfoKey("termination_reason", "-", "step", '"violation", "diverged" or None'),
    InfoKey("truncation_reason", "-", "step", '"time_limit" or None'),
    InfoKey("filter_outputs", "-", "step, with residual_filter",
            "the filter's outputs by name (the filtered residual, theta, the budget, its monitors)"),
    InfoKey("lookahead_handback", "-", "step, with lookahead in residual_filter",
            "True when the look-ahead hand-back withheld the residual over this step (blf_gym.envs.lookahead)"),
    InfoKey("qd", "rad/s", "reset and step, with privileged=True", "the true joint velocities"),
    InfoKey("diverged_message", "-", "the step that diverged", "what diverged and when"),
    InfoKey("episode_metrics", "-", "the episode's last step",
            "the episode's totals in blf-eval's terms: RMSE per joint (deg), violating samples and steps, the "
            "first violation, divergence, filter breaches and assumption failures, how it ended"),
)
"""The env's ``info`` keys, declared once (the docstring's and the docs' tables are made from it; a
test checks them against what the env returns)."""


# per-arm episode totals: integer columns and float columns (then the per-joint sums of e1^2)
(EP_VIOL_STEPS, EP_FIRST_VIOL, EP_SAT_STEPS, EP_VIOL_SAMPLES, EP_DIV_CODE, EP_DIV_STEP, EP_BREACHES,
 EP_ASSUME_FAIL) = range(8)
N_EP_INT = 8
EP_SAMPLES, EP_E2_JOINT = range(2)


@njit(cache=True, error_model="numpy")
def _accumulate_episode(status, sums, ksteps, ep_int, ep_f):
    """Add one kernel call's status and sums to the episode totals (one compiled call per step)."""
    N = status.shape[0]
    n = ep_f.shape[1] - EP_E2_JOINT
    for b in range(N):
        ep_int[b, EP_VIOL_STEPS] += status[b, ST_VIOL_STEPS]
        if ep_int[b, EP_FIRST_VIOL] < 0 and status[b, ST_FIRST_VIOL] >= 0:
            ep_int[b, EP_FIRST_VIOL] = status[b, ST_FIRST_VIOL]
        ep_int[b, EP_SAT_STEPS] += status[b, ST_SAT_STEPS]
        ep_int[b, EP_VIOL_SAMPLES] += status[b, ST_VIOL_SAMPLES]
        ep_int[b, EP_BREACHES] += status[b, ST_FILTER_BREACHES]
        ep_int[b, EP_ASSUME_FAIL] += status[b, ST_ASSUMPTION_FAILURES]
        if ep_int[b, EP_DIV_CODE] == 0 and status[b, ST_DIVERGED] != 0:
            ep_int[b, EP_DIV_CODE] = status[b, ST_DIVERGED]
            ep_int[b, EP_DIV_STEP] = ksteps[b]
        ep_f[b, EP_SAMPLES] += sums[b, SUM_SAMPLES]
        for j in range(n):
            ep_f[b, EP_E2_JOINT + j] += sums[b, SUM_E2_JOINT + j]


@njit(cache=True, error_model="numpy")
def _clip_finite(a):
    """Clip ``a`` (N, n) to [-1, 1] in place; False if any entry is NaN or infinite."""
    for b in range(a.shape[0]):
        for j in range(a.shape[1]):
            v = a[b, j]
            if not np.isfinite(v):
                return False
            a[b, j] = min(max(v, -1.0), 1.0)
    return True


_WARNED: list[bool] = []


def warn_if_oversubscribed(env_threads: int, owner: str) -> None:
    """Once per process: if torch is already imported and its threads plus the env's exceed the
    cores, say so, with the fix. Torch's default (one thread per core) beside the env slowed SB3's
    PPO through ``gym.make`` from about 1,300-1,600 to 40-280 steps/s on a loaded 2-core machine
    (docs/conventions.md, "Threads")."""
    import sys

    torch = sys.modules.get("torch")
    cpus = usable_cores()
    if _WARNED or torch is None or not hasattr(torch, "get_num_threads"):
        return
    t = int(torch.get_num_threads())
    if t > max(1, cpus - env_threads):  # torch has more threads than the cores the env leaves it
        import gymnasium as gym

        _WARNED.append(True)
        gym.logger.warn(
            f"{owner}: torch uses {t} threads beside the env's {env_threads} on {cpus} cores; a "
            f"training loop slows down when they compete. Call torch.set_num_threads({max(1, cpus - env_threads)}) "
            "(or set OMP_NUM_THREADS) before training, or pass threads= to the env")


def named_block(owner: str, kind: str, spec: Any, arm: ArmParams) -> Any:
    """The controller or observer (``kind``) ``spec`` for an env on ``arm``: an object as it is; a
    registered name built by its factory, with ``arm`` as its model (``nominal``) when the arm has
    other than the paper's 3 links (at 3 links as always: the factory's own, the paper's Table 1
    arm). A factory that cannot serve the arm (a gain it needs per joint, a plug-in written for 3
    joints) is reported as one ValueError naming the block and the arm's links."""
    make = make_controller if kind == "controller" else make_observer
    if not isinstance(spec, str) or spec == "none" or arm.n_links == PAPER_LINKS:
        return make(spec)
    try:
        return make(spec, nominal=arm)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{owner} {kind} {spec!r} does not serve an arm of {arm.n_links} links (n_links): {exc}") from None


def check_env_kwargs(kwargs: Mapping[str, Any]) -> None:
    """ValueError naming any keyword argument the env does not know, with the accepted ones."""
    import inspect

    accepted = [p for p in inspect.signature(EnvCore.__init__).parameters
                if p not in ("self", "num_envs", "single")]
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        raise ValueError(f"unknown argument(s) {unknown} for PlanarBLF; accepted: {accepted}")


LAW_SCALE_EPISODES = 16
"""Noise-free draws of the training scenario over which :func:`law_action_scale` reads the law's torques."""
LAW_SCALE_MARGIN = 2.0
""":func:`law_action_scale`'s factor on the largest torque the law applies."""
LAW_SCALE_SKIP = 0.05
"""The start-up transient :func:`law_action_scale` leaves out, s: the law's answer to an initial
error peaks at t = 0 (up to 78 N m on the first joint of the training suite, against at most 17
afterwards) and decays within 50 ms; a policy capped below it saturates for those few steps."""
_LAW_SCALES: dict[tuple, tuple[float, ...]] = {}


def law_action_scale(scenario: "str | Scenario" = "randomized", level: int = DEFAULT_LEVEL,
                     max_torque: float | None = None, episodes: int = LAW_SCALE_EPISODES,
                     margin: float = LAW_SCALE_MARGIN, seed: int = 0) -> tuple[float, ...]:
    """Plain mode's per-joint action scale read from the proposed law's own torques (N m).

    Per joint: ``margin`` times the largest |u| the proposed law (with the LESO, noise-free, run
    whole, not terminated) applies after the start-up transient (:data:`LAW_SCALE_SKIP`) over ``episodes`` draws of ``scenario``'s training suite (drawn
    with ``numpy.random.default_rng(seed)``; a fixed scenario is run once) at ``level``, at most
    ``max_torque`` (the scenario's actuator limit by default). This is ``action_scale="law"``.

    Why: plain actions are scaled to ``max_torque`` (150 N m) on every joint by default, while the
    law that keeps every bound uses about a tenth of that on the first joints and a few percent on
    the last (docs/plain_audit.md). An agent whose action 1 is the whole actuator range spends
    its exploration noise on torques no good policy uses. The law's largest torques, with a
    margin, are a range a policy is known to need and a law is known to suffice with, measured
    per arm on the suite it trains on rather than written down as numbers. The result is cached
    per process."""
    base, suite = resolve_scenario(scenario) if isinstance(scenario, str) else (scenario, None)
    return _law_scale(base, suite, level, max_torque, episodes, margin, seed)


def _law_scale(base: Scenario, suite: str | None, level: int, max_torque: float | None, episodes: int,
               margin: float, seed: int) -> tuple[float, ...]:
    """:func:`law_action_scale` of the suite ``suite`` drawn around ``base`` (None: ``base`` itself)."""
    # every argument checked before it enters the cache's key (ValueError naming it)
    o = "law_action_scale"
    level = check_level(o, level)
    episodes = check_int(o, "episodes", episodes, lo=1, hi=1024)
    margin = check_real(o, "margin", margin, lo=1.0)
    seed = check_int(o, "seed", seed, lo=0)
    max_torque = check_real(o, "max_torque", max_torque, lo=0.0, lo_open=True, unit="N m", none_ok=True)
    if max_torque is not None:
        base = replace(base, sim=replace(base.sim, max_torque=float(max_torque)))
    key = (base, suite, level, episodes, margin, seed)
    if key in _LAW_SCALES:
        return _LAW_SCALES[key]
    rng = np.random.default_rng(seed)
    scs = [apply_level(replace(sample_suite(rng, base, suite) if suite else base, angle_noise_std=0.0), level)
           for _ in range(episodes if suite else 1)]
    steps = {sc.sim.n_steps for sc in scs}
    if len(steps) != 1:
        raise ValueError("law_action_scale: the draws must share one duration")
    loop = ClosedLoop(scs, named_block(o, "controller", "proposed", base.arm), named_block(o, "observer", "leso", base.arm),
                      threads=min(len(scs), usable_cores()))
    u, tc = CHANNELS.index("u"), CHANNELS.index("t")
    top = np.zeros(loop.n)
    total, chunk = steps.pop(), 10 * loop.steps_per_sample * 100
    done = 0
    while done < total:
        k = min(chunk, total - done)
        rec, nrec, _ = loop.advance(k, record_samples=k // loop.steps_per_sample + 1)
        for i in range(len(scs)):
            later = rec[i, : nrec[i], u][rec[i, : nrec[i], tc, 0] >= LAW_SCALE_SKIP - 1e-12]
            if len(later):
                top = np.maximum(top, np.abs(later).max(axis=0))
        done += k
    umax = base.sim.max_torque
    out = tuple(float(min(margin * t, umax)) for t in top)
    _LAW_SCALES[key] = out
    return out


LAW_CHUNK = 200
"""Most 1 ms samples of the score term's reference law simulated in one go once a run has grown
(it starts with what the episode's first step needs and doubles): about 15 agent steps' worth of
simulation at the default 10 ms. The rewards do not depend on it: the running sums keep the
1000-sample grouping they have always had."""


class _LawRun:
    """The score term's reference law for a group of arms reset together: a ClosedLoop of the
    distinct noise-free scenarios, advanced :data:`LAW_CHUNK` samples at a time, with each row's
    running sum of e1^2. ``arms[r]`` holds the env arms that read row r (an arm leaves when it is
    reset). The running sum is grouped in blocks of 1000 samples from the episode's start (within a
    block, a sequential sum from the block's start; then the total at the block's start added), so
    the values are the same to the bit whatever the chunk size."""

    def __init__(self, loop: ClosedLoop, keys: list, arms: list, samples: int, n: int) -> None:
        self.loop = loop
        self.keys = keys
        self.arms = [set(a) for a in arms]
        self.samples = samples
        self.h = 0
        rows = loop.N
        self._inner = np.zeros((rows, n))  # sum since the current 1000-sample block began
        self._acc = np.zeros((rows, n))    # the running sum at that block's start
        self._e1 = CHANNELS.index("e1")

    def restart(self, keys: list, arms: list) -> None:
        """Reuse this run's loop (same number of rows) for new scenarios and arms, from the start."""
        self.loop.set_scenarios(keys)
        self.keys = keys
        self.arms = [set(a) for a in arms]
        self.h = 0
        self._inner[:] = 0.0
        self._acc[:] = 0.0

    def detach(self, i: int) -> None:
        for a in self.arms:
            a.discard(i)

    def advance(self, want: int = LAW_CHUNK) -> tuple[int, int, np.ndarray]:
        """Simulate at least ``want`` more samples (within the block of 1000 and the episode), and at
        least as many as so far up to :data:`LAW_CHUNK` (a run grows geometrically: an episode that
        ends after a step or two pays for those steps only); return (h0, h1, the running sums of
        samples h0..h1-1 per row, (rows, h1 - h0, n))."""
        h0 = self.h
        m = min(max(want, min(h0, LAW_CHUNK)), self.samples - h0, 1000 - h0 % 1000)
        rec, nrec, _ = self.loop.advance(m * self.loop.steps_per_sample, record_samples=m)
        e2 = rec[:, :m, self._e1, :] ** 2
        for r in range(e2.shape[0]):
            e2[r, nrec[r]:] = np.inf  # the law stopped (it diverged): its error counts as unbounded
        e2[~np.isfinite(e2)] = np.inf
        if h0 % 1000 == 0:
            self._acc = self._inner + self._acc if h0 else self._acc
            local = np.cumsum(e2, axis=1)
        else:
            local = np.cumsum(np.concatenate([self._inner[:, None, :], e2], axis=1), axis=1)[:, 1:]
        self._inner = local[:, -1].copy()
        self.h = h0 + m
        return h0, self.h, local + self._acc[:, None, :]


class _Record:
    """The 1 ms samples of N arms' current episodes, kept for :meth:`EnvCore.trajectory`.

    Each agent step has a slab: the C-contiguous (N, m, channels, n) array that the kernel writes
    the step's samples into, so recording copies nothing. Arm i's episode is the slabs from
    ``start[i]`` on, with ``nrec[j, i]`` samples in slab j (all m until the arm stops). Slabs are
    allocated for ``steps`` agent steps at a time; the system gives their pages only once they are
    written. When they run out, the slabs that no episode reads any more are dropped, and the store
    grows only if there are none."""

    def __init__(self, N: int, m: int, n: int, steps: int, channels: int = len(CHANNELS)) -> None:
        self.shape = (N, m, channels, n)
        self.steps = max(1, steps)
        self._clear()

    def _clear(self) -> None:
        self.buf = np.empty((0, *self.shape))
        self.nrec = np.zeros((0, self.shape[0]), dtype=np.int64)
        self.pos = 0
        self.start = np.zeros(self.shape[0], dtype=np.int64)

    def slab(self) -> np.ndarray:
        """The array the next step writes into."""
        if self.pos == len(self.buf):
            keep = int(self.start.min())
            k = self.pos - keep
            buf = np.empty((max(self.steps, 2 * k), *self.shape))
            nrec = np.zeros((len(buf), self.shape[0]), dtype=np.int64)
            buf[:k] = self.buf[keep:self.pos]
            nrec[:k] = self.nrec[keep:self.pos]
            self.buf, self.nrec, self.pos = buf, nrec, k
            self.start -= keep
        return self.buf[self.pos]

    def commit(self, nrec: np.ndarray) -> None:
        """The slab of :meth:`slab` holds ``nrec[i]`` samples of arm i."""
        self.nrec[self.pos] = nrec
        self.pos += 1

    def restart(self, idx: Sequence[int]) -> None:
        """Arms ``idx`` begin a new episode with the next step."""
        self.start[list(idx)] = self.pos

    def samples(self, i: int, release: bool = False) -> np.ndarray:
        """Arm i's samples so far, (samples, channels, n): a copy, except with one arm and no partial
        step, where it is a view of the store (copy out what is kept). ``release`` forgets them (the
        arm's later steps are kept); the memory goes once no arm's episode reads those slabs."""
        s = int(self.start[i])
        rows, k = self.buf[s:self.pos, i], self.nrec[s:self.pos, i]
        m = self.shape[1]
        if bool((k == m).all()):
            out = rows.reshape(-1, *self.shape[2:])  # a copy when N > 1: the slabs interleave the arms
        else:
            out = rows[np.arange(m)[None, :] < k[:, None]]
        if release:
            self.start[i] = self.pos
            if bool((self.start == self.pos).all()):
                self._clear()
        return out


def _record_channels(o: str, record_channels: Any) -> tuple[str, ...]:
    """The channels a recording env keeps (None: all of :data:`CHANNELS`), 't' always among them;
    ValueError naming the argument otherwise."""
    from collections.abc import Sequence

    if record_channels is None:
        return CHANNELS
    # a list or tuple of names: a string is one name spelled as a sequence of letters, and a set or a
    # dict has no order the trajectory's channels could follow
    names = tuple(record_channels) if (isinstance(record_channels, Sequence)
                                       and not isinstance(record_channels, (str, bytes))) else None
    if (names is None or len(set(map(repr, names))) != len(names)
            or any(not isinstance(c, str) or c not in CHANNELS for c in names)):
        raise ValueError(f"{o} record_channels must be a list or tuple of distinct names among "
                         f"{list(CHANNELS)}, or None (all; 't' is always kept), got {record_channels!r:.80}")
    return names if "t" in names else ("t", *names)


def _check_kinds(o: str, scenario: Any, controller: Any, observer: Any, observation_extras: Any,
                 variations: Any, reward_weights: Any, residual_filter: Any) -> None:
    """The env's arguments that name things (a scenario, blocks, observation entries, knobs, reward
    weights, a filter) are of a kind it accepts; ValueError naming the argument otherwise."""
    if not (isinstance(scenario, Scenario) or (isinstance(scenario, str) and (scenario in SUITES
                                                                             or preset_links(scenario) is not None))):
        raise ValueError(f"{o} scenario must be one of {sorted(PRESETS) + list(SUITES)}, a task-family preset "
                         f"(blf_gym.model.family.family_presets: 'n2-0.1hz' ... 'n7-0.5hz') or a "
                         f"blf_gym.model.params.Scenario, got {scenario!r}")
    if not (controller is None or isinstance(controller, (str, Controller))):
        raise ValueError(f"{o} controller must be None, one of {available_controllers()} or a "
                         f"blf_gym.plugins.blocks.Controller, got {controller!r}")
    if not isinstance(observer, (str, Observer)):
        raise ValueError(f"{o} observer must be one of {available_observers()} or a "
                         f"blf_gym.plugins.blocks.Observer, got {observer!r}")
    optional = optional_observations()
    if (isinstance(observation_extras, (str, bytes)) or not isinstance(observation_extras, Sequence)
            or not all(isinstance(g, str) for g in observation_extras)):
        raise ValueError(f"{o} observation_extras must be a sequence of names from {optional}, "
                         f"got {observation_extras!r}")
    bad = [g for g in observation_extras if g not in optional]
    if bad or len(set(observation_extras)) != len(observation_extras):
        raise ValueError(f"{o} observation_extras must name each optional entry at most once, from "
                         f"{optional}; got {list(observation_extras)!r}")
    if not (variations is None or isinstance(variations, Mapping)):
        raise ValueError(f"{o} variations must be None or a mapping (dict) from names in "
                         f"{list(VARIATIONS)} to numbers, got {variations!r}")
    if not (reward_weights is None or isinstance(reward_weights, (RewardWeights, Mapping))):
        raise ValueError(f"{o} reward_weights must be None, a blf_gym.kernel.reward.RewardWeights or a mapping "
                         f"(dict) of its fields {[f.name for f in fields(RewardWeights)]}, got {reward_weights!r}")
    if isinstance(reward_weights, Mapping):
        names = [f.name for f in fields(RewardWeights)]
        unknown = [k for k in reward_weights if k not in names]
        if unknown:
            raise ValueError(f"{o} reward_weights has unknown field(s) {sorted(unknown, key=repr)}; "
                             f"accepted: {names}")
    if not (residual_filter is None or isinstance(residual_filter, (str, ResidualFilter))):
        raise ValueError(f"{o} residual_filter must be None, the name of a filter shipped with the law "
                         f"(the proposed law's 'barrier' or 'cbf') or a blf_gym.plugins.blocks.ResidualFilter, got "
                         f"{residual_filter!r}")


class EnvCore:
    """N arms of the PlanarBLF task stepped together by one compiled kernel call.

    This is the one place the environment's defaults live; :class:`~blf_gym.envs.env.PlanarBLFEnv`
    and :class:`~blf_gym.envs.vector.PlanarBLFVectorEnv` pass their keyword arguments through.
    """

    def __init__(
        self,
        num_envs: int,
        scenario: "str | Scenario" = "paper-0.1hz",
        n_links: int | None = None,
        controller: "str | Controller | None" = None,
        observer: "str | Observer" = "leso",
        residual_scale: float = 2.0,
        control_period: float = 0.01,
        privileged: bool = False,
        terminate_on_violation: bool = True,
        angle_noise_std: float | None = None,
        duration: float | None = None,
        max_torque: float | None = None,
        action_scale: "float | Sequence[float] | None" = None,
        start_time: "float | Sequence[float] | None" = None,
        dt: float | None = None,
        variations: Mapping[str, Any] | None = None,
        reward_weights: RewardWeights | Mapping[str, float] | None = None,
        observation_extras: Sequence[str] = (),
        residual_filter: str | None = None,
        bound_scale: float = 1.0,
        level: int = DEFAULT_LEVEL,
        threads: int | None = None,
        record: bool = False,
        record_channels: Sequence[str] | None = None,
        single: bool = False,
    ) -> None:
        # every argument is checked here, before anything is built: ValueError naming it and
        # what it accepts (bools are not numbers, strings are neither)
        self.single = check_bool("EnvCore:", "single", single)
        o = self.owner = "PlanarBLFEnv:" if self.single else "PlanarBLFVectorEnv:"
        self.num_envs = check_int(o, "num_envs", num_envs, lo=1, hi=MAX_ARMS,
                                  hint=" (blf_gym.envs.envcore.MAX_ARMS; each arm keeps per-episode arrays)")
        self.record = check_bool(o, "record", record)
        self.record_channels = _record_channels(o, record_channels)
        if self.single and self.num_envs != 1:
            raise ValueError("a single env core has num_envs == 1")
        _check_kinds(o, scenario, controller, observer, observation_extras, variations, reward_weights,
                     residual_filter)
        residual_scale = check_real(o, "residual_scale", residual_scale, lo=0.0, lo_open=True, unit="N m")
        control_period = check_real(o, "control_period", control_period, lo=0.0, lo_open=True, unit="s")
        privileged = check_bool(o, "privileged", privileged)
        terminate_on_violation = check_bool(o, "terminate_on_violation", terminate_on_violation)
        angle_noise_std = check_real(o, "angle_noise_std", angle_noise_std, lo=0.0, unit="rad", none_ok=True)
        duration = check_real(o, "duration", duration, lo=0.0, hi=MAX_DURATION, lo_open=True, unit="s", none_ok=True,
                              hint=" (blf_gym.model.params.MAX_DURATION: an episode's signals and the score reward's "
                                   "reference are kept per 1 ms sample)")
        max_torque = check_real(o, "max_torque", max_torque, lo=0.0, lo_open=True, unit="N m", none_ok=True)
        dt = check_real(o, "dt", dt, lo=DT_MIN, unit="s", none_ok=True,
                        hint=" dividing the 0.001 s sample period (e.g. 1e-4, 5e-5)")
        threads = check_int(o, "threads", threads, lo=1, hi=usable_cores(), none_ok=True,
                            hint=" (the cores this process may use: more threads than cores only wait)")
        self.bound_scale = bound_scale  # checked by the property's setter
        self.level = check_level(o, level)
        self._set_scenario(scenario, duration, max_torque, dt, variations, angle_noise_std, n_links)
        self._set_period(control_period)
        self.controller = NO_CONTROLLER if controller is None else named_block(o, "controller", controller,
                                                                                self.nominal)
        self.observer = named_block(o, "observer", observer, self.nominal)
        self.residual = self.controller is not NO_CONTROLLER
        if not self.residual and self.observer.nominal != NO_CONTROLLER.nominal:
            # plain mode on another arm: the zero-torque inner controller shares the observer's model
            self.controller = replace(NO_CONTROLLER, nominal=self.observer.nominal)
        self.residual_scale = float(residual_scale)
        self.action_scale = self._check_action_scale(action_scale)
        self.privileged = bool(privileged)
        self.terminate_on_violation = bool(terminate_on_violation)
        self._set_reward(reward_weights)
        self.start_time = self._check_start_time(start_time)
        self.n = self.base.arm.n_links
        self._build_loop(residual_filter, threads)
        self._set_observation(observation_extras)
        self._allocate()
        self._threads = threads

    @property
    def bound_scale(self) -> float:
        """A training aid, never the benchmark: the factor on the funnel's amplitudes and floors
        (k_a, k_b) of every episode the env starts from now on (1 to :data:`MAX_BOUND_SCALE`;
        default 1, the benchmark's own bounds). A curriculum starts wide and lowers it to 1
        (``agents.train``'s ``curriculum``); setting it takes effect at each arm's next reset.
        blf-eval and the learning curves always score at 1."""
        return self._bound_scale

    @bound_scale.setter
    def bound_scale(self, value: float) -> None:
        self._bound_scale = check_real(self.owner, "bound_scale", value, lo=1.0, hi=MAX_BOUND_SCALE,
                                       hint=" (a factor on the funnel's width; 1 is the benchmark's)")

    def _set_scenario(self, scenario: "str | Scenario", duration: float | None, max_torque: float | None,
                      dt: float | None, variations: Mapping[str, Any] | None, angle_noise_std: float | None,
                      n_links: int | None) -> None:
        """The base scenario (a preset, or a suite's base) with the simulation overrides and the
        variations applied, the suite to draw from (None: the base itself every episode), and the
        arm the blocks given by name take as their model (:attr:`nominal`)."""
        try:
            base, suite = resolve_scenario(scenario, n_links)
        except ValueError as exc:
            raise ValueError(f"{self.owner} {exc}") from None
        self.nominal = base.arm
        """The arm a law or observer given by name models: the scenario's before any variation (the
        paper's Table 1 arm at 3 links, whatever the scenario, as the paper's laws always had)."""
        sim_over = {k: v for k, v in (("duration", duration), ("max_torque", max_torque), ("dt", dt))
                    if v is not None}
        if sim_over:
            base = replace(base, sim=replace(base.sim, **sim_over))
        self.variations = check_variations({} if variations is None else variations, base.arm.n_links)
        if angle_noise_std is not None:
            self.variations["angle_noise_std"] = angle_noise_std
        # validated now; re-applied after every suite draw so they override it
        self.base = apply_variations(base, self.variations) if self.variations else base
        self.suite = suite
        self.sim = self.base.sim

    def _set_period(self, control_period: float) -> None:
        """The agent's period as whole integration steps and samples, and the episode's steps."""
        o = self.owner
        # agent period (docs/model.md section 6): a whole number of integration steps that is either a
        # whole number of 1 ms samples or divides 1 ms (down to a single step, for sampled
        # controllers such as the baseline policies)
        control_period = check_real(o, "control_period", control_period, lo=0.0, hi=self.sim.duration,
                                    lo_open=True, unit="s", hint=" (at most the duration)")
        steps = control_period / self.sim.dt
        sps = self.sim.steps_per_sample
        whole = abs(steps - round(steps)) <= 1e-9 * max(steps, 1.0) and round(steps) >= 1
        steps_i = int(round(steps))
        if not whole or (steps_i % sps and sps % steps_i):
            raise ValueError(
                f"{o} control_period must be a whole multiple of the {self.sim.sample_period} s sample "
                f"period (e.g. 0.002, 0.005, 0.01) or divide it into whole integration steps of "
                f"{self.sim.dt} s (e.g. 1e-4, 5e-4), got {control_period!r}")
        self.control_period = float(control_period)
        self.steps_per_period = steps_i
        self.samples_per_period = max(1, steps_i // sps)
        if self.sim.n_steps % self.steps_per_period:
            raise ValueError(
                f"{o} duration ({self.sim.duration} s) must be a whole number of control periods "
                f"({self.control_period} s)")
        self.max_episode_steps = self.sim.n_steps // self.steps_per_period

    def _set_reward(self, reward_weights: RewardWeights | Mapping[str, float] | None) -> None:
        """The reward's weights (default: the score reward), checked against the episode's length
        and against the memory its reference to the law would take."""
        o = self.owner
        if reward_weights is None:
            reward_weights = SCORE_REWARD
        elif not isinstance(reward_weights, RewardWeights):
            reward_weights = RewardWeights(**dict(reward_weights))
        reward_weights.check_episode(self.max_episode_steps)
        self.weights = reward_weights
        self._wvec = reward_weights.pack(self.terminate_on_violation)
        per_arm = 8 * self.base.arm.n_links * ((self.sim.n_samples if reward_weights.score > 0 else 0)
                                               + (self.max_episode_steps if reward_weights.relative else 0))
        if per_arm * self.num_envs > MAX_REFERENCE_BYTES:
            raise ValueError(
                f"{o} num_envs={self.num_envs} arms of {self.sim.duration:g} s episodes would need "
                f"{per_arm * self.num_envs / 2 ** 30:.1f} GiB for the reward's reference to the law "
                f"(blf_gym.envs.envcore.MAX_REFERENCE_BYTES is {MAX_REFERENCE_BYTES / 2 ** 30:g} GiB); use fewer arms, "
                "shorter episodes, or reward_weights={} (the shaped reward, which needs none)")

    def _build_loop(self, residual_filter: "str | ResidualFilter | None", threads: int | None) -> None:
        """The compiled closed loop of the arms (the law, its filter, the observer), and where its
        outputs sit in the loop's last-signal columns."""
        o = self.owner
        self.residual_filter = residual_filter.name if isinstance(residual_filter, ResidualFilter) else residual_filter
        try:
            residual_filter, self.lookahead = split_lookahead(residual_filter)
        except ValueError as exc:
            raise ValueError(f"{o} {exc}") from None
        self._gates: dict[Scenario, np.ndarray] = {}
        self._gate_of: list[np.ndarray | None] = [None] * self.num_envs
        if self.lookahead is not None and not self.residual:
            raise ValueError(f"{o} residual_filter={self.residual_filter!r}: the look-ahead hand-back withholds a "
                             "residual; it needs residual mode (a controller), not plain mode")
        if residual_filter is not None and not self.residual:
            # plain mode: the filter acts on the agent's torque minus the proposed law's, computed alongside
            inner, plain = named_block(o, "controller", "proposed", self.nominal), True
        else:
            inner, plain = self.controller, False
        if residual_filter is not None and not inner.filters:
            raise ValueError(f"{o} residual_filter={residual_filter!r}: the {inner.name!r} law ships no residual "
                             "filter (the proposed law has 'barrier' and 'cbf')")
        try:
            self.loop = ClosedLoop([self.base] * self.num_envs, inner, self.observer, threads=threads,
                                   residual_filter=residual_filter, plain=plain)
        except ValueError as exc:
            raise ValueError(f"{o} {exc}") from None
        self._filter_slices = [(name, slice(N_LAST * self.n + self.loop.connection.n_out + off,
                                            N_LAST * self.n + self.loop.connection.n_out + off + m))
                               for name, (off, m) in self.loop.connection.fout_offsets.items()]
        n = self.n
        self._last_slices = tuple(LAST.slice(c, n) for c in ("u", "u_law", "x3", "x3_hat"))
        # the law's outputs besides u_law (already info["u_law"]), for info["controller_outputs"]
        self._out_slices = [(name, slice(N_LAST * self.n + off, N_LAST * self.n + off + m))
                            for name, (off, m) in self.loop.connection.out_offsets.items() if name != "u_law"]

    def _set_observation(self, observation_extras: Sequence[str]) -> None:
        """The observation's layout, its box and the compiled filler's plan: each row of
        :data:`~blf_gym.envs.observation.OBSERVATION` in use, its source resolved against the blocks."""
        self.observation_extras = tuple(observation_extras)
        n, conn = self.n, self.loop.connection
        plan, scale, at = [], [], 0
        for e in groups(self.privileged, self.observation_extras):
            try:
                frm, col, m = plan_row(e, n, conn.observer_signal, conn.out_offsets.get, N_LAST * n)
            except LookupError:
                kind, _, name = e.source.partition(":")
                block = (f"observer {self.observer.name!r} does not provide (its states: {list(self.observer.states)})"
                         if kind == "observer" else f"controller {self.controller.name!r} does not provide "
                         f"(its outputs: {list(conn.out_offsets)})")
                what = f"{name!r}" if name == e.group else f"{e.source!r} (entry {e.group!r})"
                raise ValueError(f"{self.owner} the observation reads {what}, which {block}") from None
            plan.append((frm, col, m, at, e.points))
            scale.append(e.scale)
            at += m
        self._plan = np.array(plan, dtype=np.int64).reshape(-1, 5)
        self._plan_scale = np.array(scale, dtype=np.float64)
        layout = observation_layout(n, self.privileged, self.observation_extras)
        self.obs_dim = len(layout)
        self._box64 = (np.array([r[2] for r in layout]), np.array([r[3] for r in layout]))
        self.obs_low = self._box64[0].astype(np.float32)
        self.obs_high = self._box64[1].astype(np.float32)

    def _allocate(self) -> None:
        """The per-arm arrays of the episodes: scenarios, generators, counters, the record, the
        episode's sums and the reward's reference to the law."""
        N, n = self.num_envs, self.n
        self.scenarios: list[Scenario] = [self.base] * N
        self.rngs: list[np.random.Generator] = [np.random.default_rng() for _ in range(N)]
        self.steps = np.zeros(N, dtype=np.int64)
        self.done = np.zeros(N, dtype=bool)
        self._ref = np.zeros((N, REF.length(n)))
        self._bnd = np.zeros((N, BOUND_LEN))
        self._obs_noise = np.zeros((N, n))
        self._record = (_Record(N, self.samples_per_period, n, self.max_episode_steps, len(self.record_channels))
                        if self.record else None)
        # with some channels recorded, the kernel writes a step's samples here and they are copied out
        self._rec_all = (np.empty((N, self.samples_per_period, len(CHANNELS), n))
                         if self.record and self.record_channels != CHANNELS else None)
        # the recorded channels as runs of consecutive ones: [first in the record, first in CHANNELS, count]
        self._rec_runs: list[list[int]] = []
        for d, c in enumerate(CHANNELS.index(name) for name in self.record_channels):
            if self._rec_runs and sum(self._rec_runs[-1][1:]) == c:
                self._rec_runs[-1][2] += 1
            else:
                self._rec_runs.append([d, c, 1])
        self._ep_int = np.zeros((N, N_EP_INT), dtype=np.int64)
        self._ep_int[:, EP_FIRST_VIOL] = -1
        self._ep_f = np.zeros((N, EP_E2_JOINT + n))
        self._durations = np.zeros(N)
        self._umax = np.zeros(N)
        self._law_e2 = np.ones((N, n))
        self._law_steps = np.zeros((N, self.max_episode_steps if self.weights.relative else 0, n))
        self._stds = np.zeros(N)
        self._no_base = np.zeros((N, n))
        self._arms = np.arange(N)
        self._noisy: list[int] = []
        self._law_cache: dict[Scenario, tuple[np.ndarray, np.ndarray]] = {}
        # the score term: the law's cumulative e1^2 per 1 ms sample, and each arm's potential
        self._score_w = float(self.weights.score)
        self._law_cum = np.zeros((N, self.base.sim.n_samples if self._score_w > 0 else 0, n))
        self._cum_cache: dict[Scenario, np.ndarray] = {}
        self._law_run: list[_LawRun | None] = [None] * N  # each arm's lazily extended reference run
        self._law_h = np.zeros(N, dtype=np.int64)  # samples of _law_cum filled so far, per arm
        self._law_partial = False  # some arm's reference is not complete yet (else a step checks nothing)
        self._ref_law: Controller | None = None
        self._idle_runs: list[_LawRun] = []  # reference runs whose loops a later reset may reuse
        self._phi = np.zeros(N)
        self._score_term = np.zeros(N)


    # ------------------------------------------------------------------ reset
    def check_options(self, options: Any) -> dict[str, Any]:
        """``reset(options=...)`` validated: None or a mapping of :data:`VARIATIONS` knobs, each
        inside its safe range (ValueError naming the option otherwise); a normalized copy."""
        if options is None:
            return {}
        return check_variations(options, self.n, kind="reset option")

    def scenario_for(self, rng: np.random.Generator, options: Mapping[str, Any] | None) -> Scenario:
        """The episode's scenario: the suite draw (if any), then option variations, then the level
        (the same draw at every level: the level is applied last)."""
        sc = self.base
        if self.suite:
            sc = sample_suite(rng, self.base, self.suite)
            if self.variations:
                sc = apply_variations(sc, self.variations)
        if options:
            sc = apply_variations(sc, options)  # validates them (reset_envs checked the type)
        return apply_level(sc, self.level)

    def reset_envs(self, idx: Sequence[int], options: Mapping[str, Any] | None = None,
                   scenarios: Sequence[Scenario] | None = None) -> None:
        """Reset the arms ``idx``: each draws its scenario (suite, variations, ``options``), or
        takes the given ``scenarios`` as they are (evaluation on fixed scenarios)."""
        if scenarios is not None and len(scenarios) != len(idx):
            raise ValueError("one scenario per reset arm is required")
        options = self.check_options(options)
        scs = list(scenarios) if scenarios is not None else [self.scenario_for(self.rngs[i], options) for i in idx]
        if self._bound_scale != 1.0:
            scs = [widen_bounds(sc, self._bound_scale) for sc in scs]
        for i, sc in zip(idx, scs):
            self.scenarios[i] = sc
            self._durations[i] = sc.sim.duration
            self._umax[i] = sc.sim.max_torque
            self._stds[i] = sc.angle_noise_std
        self._noisy = [int(i) for i in np.flatnonzero(self._stds > 0)]
        self.loop.set_scenarios(scs, which=list(idx),
                                start_steps=None if scenarios is not None else self._start_steps(idx, scs))
        if self.weights.relative:
            self._law_e2[list(idx)], self._law_steps[list(idx)] = self.law_level(scs)
        if self.lookahead is not None:
            for i, gate in zip(idx, self.lookahead_gates(scs)):
                self._gate_of[i] = gate
        if self._score_w > 0:
            self._start_law(idx, scs)
        if self._record is not None:
            self._record.restart(idx)
        for i in idx:
            self._phi[i] = 0.0
            self.steps[i] = 0
            self.done[i] = False
            self._ep_int[i] = 0
            self._ep_int[i, EP_FIRST_VIOL] = -1
            self._ep_f[i] = 0.0

    def _reference_runs(self, scenarios: Sequence[Scenario], cache: Mapping[Scenario, Any]):
        """The reference law's runs that ``scenarios`` need: (each scenario without noise, the
        distinct ones not in ``cache``, a ClosedLoop of the law over those or None). The law is the
        inner controller in residual mode, the proposed law in plain mode."""
        keys = [replace(sc, angle_noise_std=0.0) for sc in scenarios]
        todo = list(dict.fromkeys(k for k in keys if k not in cache))
        if not todo:
            return keys, todo, None
        ref = self._reference_law()
        return keys, todo, ClosedLoop(todo, ref, self.observer, threads=self._threads)

    def law_level(self, scenarios: Sequence[Scenario]) -> tuple[np.ndarray, np.ndarray]:
        """The reference law alone on each scenario, without noise (see
        ``RewardWeights.relative``): each joint's mean of e1^2 (rad^2) over the whole episode,
        (len(scenarios), n), and its mean over each agent step's 1 ms samples,
        (len(scenarios), max_episode_steps, n). Each distinct scenario is simulated once."""
        keys, todo, loop = self._reference_runs(scenarios, self._law_cache)
        done: dict[Scenario, tuple[np.ndarray, np.ndarray]] = {}
        if loop is not None:
            per = np.zeros((len(todo), self.max_episode_steps, self.n))
            total = np.zeros((len(todo), self.n))
            samples = np.zeros((len(todo), 1))
            for j in range(self.max_episode_steps):
                loop.advance(self.steps_per_period, record_samples=0)
                e2 = loop.sums[:, SUM_E2_JOINT : SUM_E2_JOINT + self.n]
                ns = loop.sums[:, SUM_SAMPLES : SUM_SAMPLES + 1]
                per[:, j] = e2 / np.maximum(ns, 1.0)
                total += e2
                samples += ns
            # a floor keeps the ratio finite for a law that tracks perfectly
            level = np.maximum(total / np.maximum(samples, 1.0), 1e-16)
            for i, sc in enumerate(todo):
                done[sc] = (level[i], per[i])
                if len(self._law_cache) < 64:
                    self._law_cache[sc] = (level[i].copy(), per[i].copy())
        mean = np.empty((len(scenarios), self.n))
        steps = np.empty((len(scenarios), self.max_episode_steps, self.n))
        for k, sc in enumerate(keys):
            mean[k], steps[k] = done[sc] if sc in done else self._law_cache[sc]
        return mean, steps

    def lookahead_gates(self, scenarios: Sequence[Scenario]) -> list[np.ndarray]:
        """Which control periods of each scenario the look-ahead hand-back gives to the law alone
        (blf_gym.envs.lookahead: the demand rule, or the predictive rule's law runs batched over the
        scenarios not seen before), indexed by the period's start time over the control period;
        kept for the last 64 (or twice the arms) distinct scenarios as the rule sees them (design_scenario)."""
        keys = [replace(design_scenario(sc), name="") for sc in scenarios]
        todo = {k: sc for k, sc in zip(keys, scenarios) if k not in self._gates}
        if todo:
            if self.lookahead.predict is not None:
                made = predicted_gates(list(todo.values()), self.controller, self.observer, self.control_period,
                                       self.lookahead)
            else:
                made = [lookahead_gate(sc, self.control_period, self.lookahead) for sc in todo.values()]
            for k, gate in zip(todo, made):
                while len(self._gates) >= max(64, 2 * self.num_envs):
                    self._gates.pop(next(iter(self._gates)))
                self._gates[k] = gate
        return [self._gates[k] for k in keys]

    def handed_back(self) -> np.ndarray:
        """(N,) bool: whether the look-ahead hand-back withholds each arm's residual over the period
        that starts now (all False without ``lookahead``)."""
        out = np.zeros(self.num_envs, dtype=bool)
        if self.lookahead is None:
            return out
        k = np.rint(np.asarray(self.loop.time, dtype=float) / self.control_period).astype(np.int64)
        for i, gate in enumerate(self._gate_of):
            if gate is not None:
                out[i] = gate[min(max(int(k[i]), 0), len(gate) - 1)]
        return out

    def with_episode_length(self, spec: Any) -> Any:
        """``spec`` (an EnvSpec, or None) with ``max_episode_steps`` set to this env's episode length
        in agent steps when it names none: what the single and vector envs report to wrappers."""
        if spec is None or spec.max_episode_steps is not None:
            return spec
        return replace(spec, max_episode_steps=int(self.max_episode_steps))

    def _reference_law(self) -> Controller:
        """The reward's reference law: the inner controller in residual mode, the proposed law in
        plain mode (made once: a registry look-up reads the installed packages' entry points)."""
        if self._ref_law is None:
            self._ref_law = self.controller if self.residual else named_block(self.owner, "controller", "proposed",
                                                                              self.nominal)
        return self._ref_law

    def _start_law(self, idx: Sequence[int], scenarios: Sequence[Scenario]) -> None:
        """Start the score term's reference for the reset arms ``idx``: the reference law alone on
        each one's scenario without noise (as :meth:`law_level`), whose running sums of e1^2 per
        joint fill ``_law_cum`` lazily, as the episode reaches them (:meth:`_extend_law`, in chunks
        that double up to :data:`LAW_CHUNK` samples). With a suite, a reset simulates nothing (it
        used to simulate the whole episode, 0.3-0.6 s per new scenario); a fixed scenario's reference
        is simulated whole at its first reset and cached; a cached scenario costs nothing."""
        S = self._law_cum.shape[1]
        keys = [replace(sc, angle_noise_std=0.0) for sc in scenarios]
        todo: dict[Scenario, list[int]] = {}
        for i, key in zip(idx, keys):
            old = self._law_run[i]
            if old is not None:
                old.detach(i)
            hit = self._cum_cache.get(key)
            if hit is not None:
                self._law_cum[i] = hit
                self._law_h[i] = S
                self._law_run[i] = None
            else:
                todo.setdefault(key, []).append(int(i))
        if not todo:
            self._law_partial = bool((self._law_h < S).any())
            return
        run = next((r for r in self._idle_runs if r.loop.N == len(todo) and not any(r.arms)), None)
        if run is not None:  # a finished or abandoned run of the same size: its loop is reused
            run.restart(list(todo), list(todo.values()))
        else:
            run = _LawRun(ClosedLoop(list(todo), self._reference_law(), self.observer, threads=self._threads),
                          list(todo), list(todo.values()), S, self.n)
            if len(self._idle_runs) < 4:
                self._idle_runs.append(run)
        for row in run.arms:
            for i in row:
                self._law_run[i] = run
                self._law_h[i] = 0
        if not self.suite:
            # a fixed scenario repeats: its reference is simulated whole once, then served from the
            # cache, so its steps carry none of it (a suite draws a new scenario at every reset, and
            # there the reference comes lazily, with the episode)
            while run.h < S:
                self._extend_law(run, LAW_CHUNK)
        self._law_partial = bool((self._law_h < S).any())

    def _extend_law(self, run: "_LawRun", want: int) -> None:
        """Advance a reference run by at least ``want`` samples (:meth:`_LawRun.advance`) and write
        the new running sums into its arms' rows of ``_law_cum``; a run that reaches the episode's
        end is cached (up to 16 scenarios)."""
        h0, h1, cum = run.advance(want)
        for r, arms in enumerate(run.arms):
            for i in arms:
                self._law_cum[i, h0:h1] = cum[r]
                self._law_h[i] = h1
        self._law_partial = bool((self._law_h < run.samples).any())
        if h1 == run.samples:
            for r, arms in enumerate(run.arms):
                key = run.keys[r]
                if arms and len(self._cum_cache) < 16 and key not in self._cum_cache:
                    self._cum_cache[key] = self._law_cum[next(iter(arms))].copy()
            for arms in run.arms:
                for i in arms:
                    self._law_run[i] = None
            run.arms = [set() for _ in run.arms]

    def _catch_up_law(self) -> None:
        """Extend the reference where the episodes got past it (an arm stepped past its end, as the
        vector env's next-step autoreset does before resetting it, reads the last sample)."""
        ns = np.minimum(self._ep_f[:, EP_SAMPLES], self._law_cum.shape[1])
        for i in np.flatnonzero(ns > self._law_h):
            while ns[i] > self._law_h[i]:
                self._extend_law(self._law_run[i], int(ns[i] - self._law_h[i]))

    def law_cumulative(self, scenarios: Sequence[Scenario]) -> np.ndarray:
        """The reference law alone on each scenario, without noise (as :meth:`law_level`): each
        joint's running sum of e1^2 (rad^2) through every 1 ms sample of the episode,
        (len(scenarios), samples, n), the score term's reference, computed whole (the env itself
        computes it lazily, chunk by chunk, to the same bits). A non-finite error, and every sample
        after the law's run stopped (it diverged), count as +inf."""
        S = self._law_cum.shape[1]
        keys, todo, loop = self._reference_runs(scenarios, {})
        run = _LawRun(loop, todo, [set() for _ in todo], S, self.n)
        out = np.empty((len(todo), S, self.n))
        while run.h < S:
            h0, h1, cum = run.advance(LAW_CHUNK)
            out[:, h0:h1] = cum
        return out[[todo.index(k) for k in keys]]

    # ------------------------------------------------------------------ step
    def check_actions(self, actions: Any) -> np.ndarray:
        """The actions as a new (N, n) float64 array clipped to [-1, 1]; ValueError if they are
        not real numbers (complex, bool, strings, objects), the shape is wrong or an entry is NaN
        or infinite."""
        try:
            a = np.asarray(actions)
        except (TypeError, ValueError) as exc:  # e.g. ragged nested lists
            raise ValueError(f"action must be an array of real numbers, got {actions!r}") from exc
        if a.dtype.kind not in "fiu":
            raise ValueError(f"action must be an array of real numbers (float or integer dtype), got "
                             f"dtype {a.dtype}: {actions!r}")
        a = np.array(a, dtype=np.float64)  # a copy: the caller's array is never modified
        want = (self.n,) if self.single else (self.num_envs, self.n)
        if a.shape != want:
            raise ValueError(f"action must have shape {want}, got {a.shape}")
        a = a.reshape(self.num_envs, self.n)
        if not _clip_finite(a):
            raise ValueError(f"action must be finite, got {np.asarray(actions).tolist()}")
        return a

    def step(self, actions: Any, skip: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One agent step of every arm; returns (obs, rewards, terminated, truncated, info) with
        ``info`` a dict of per-arm arrays (see :meth:`info_row` for one arm's plain dict).

        ``skip`` (a boolean mask) marks arms whose results the caller discards because it resets
        them next (the vector env's next-step autoreset): they draw no noise, so each arm's random
        stream stays that of a single env."""
        residual, gated, status, obs_noise = self._advance(self.check_actions(actions), skip)
        self.steps += 1
        _accumulate_episode(status, self.loop.sums, self.loop.ksteps, self._ep_int, self._ep_f)
        t_end = self.loop.time
        res, flags = self._step_rewards(status, t_end)
        rewards = res[R_REWARD]
        terminated = res[R_TERMINATED] > 0.0
        truncated = res[R_TRUNCATED] > 0.0
        info = self._step_info(status, res, flags, residual, gated, terminated, truncated, t_end)
        self.done[:] = (terminated | truncated) if flags else False
        which = None if skip is None or not skip.any() else [int(i) for i in np.flatnonzero(~skip)]
        obs = self.observe(info, which=which, t=t_end, noise=obs_noise)
        return obs, rewards, terminated, truncated, info

    def _advance(self, a: np.ndarray, skip: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
        """Run the kernel over one control period with the checked actions ``a``: (the residual
        torque applied, the look-ahead's hand-back mask or None, the kernel's status, the
        observation noise drawn for the step's end)."""
        residual = self._torque(a)
        gated = None
        if self.lookahead is not None:
            gated = self.handed_back()
            residual[gated] = 0.0
        noise, obs_noise = self._draw_noise(1, skip)
        rec = self._record
        _, nrec, status = self.loop.advance(
            self.steps_per_period, residual=residual, noise=noise,
            terminate=self.terminate_on_violation,
            record_samples=self.samples_per_period if rec is not None else 0,
            out=None if rec is None else rec.slab() if self._rec_all is None else self._rec_all)
        if rec is not None:
            if self._rec_all is not None:
                self._pick_channels(self._rec_all, rec.slab())
            rec.commit(nrec)
        return residual, gated, status, obs_noise

    def _step_rewards(self, status: np.ndarray, t_end: np.ndarray) -> tuple[np.ndarray, int]:
        """The step's reward rows (:data:`STEP_ROWS`, one column per arm) and the kernel's flags
        (bit 1: an arm's episode ended, bit 2: one diverged), the score term added in place."""
        res = np.empty((len(STEP_ROWS), self.num_envs))
        if self.weights.law_baseline:
            k = np.minimum(self.steps - 1, self.max_episode_steps - 1)
            base = self._law_steps[self._arms, k]
        else:
            base = self._no_base
        flags = step_outputs(status, self.loop.sums, self._law_e2, base, self._wvec, t_end, self._durations, res)
        if self._score_w > 0:
            if self._law_partial and (self._ep_f[:, EP_SAMPLES] > self._law_h).any():
                self._catch_up_law()
            score_step(self._ep_f[:, EP_SAMPLES], self._ep_f[:, EP_E2_JOINT:], self._law_cum, self._phi,
                       self._score_w, res[R_REWARD], self._score_term)
        return res, flags

    def _step_info(self, status: np.ndarray, res: np.ndarray, flags: int, residual: np.ndarray,
                   gated: np.ndarray | None, terminated: np.ndarray, truncated: np.ndarray,
                   t_end: np.ndarray) -> dict[str, Any]:
        """The step's ``info``: per-arm arrays (views of a fresh copy of the last signals), the
        reasons an episode ended and, on its last step, its metrics."""
        N = self.num_envs
        reason = np.empty(N, dtype=object)  # filled with None
        trunc_reason = np.empty(N, dtype=object)
        if flags:
            for i in range(N):
                if status[i, ST_DIVERGED]:
                    reason[i] = "diverged"
                elif terminated[i]:
                    reason[i] = "violation"
                elif truncated[i]:
                    trunc_reason[i] = "time_limit"
        last = self.loop.last.copy()  # the info entries below are views of this fresh copy
        sl = self._last_slices
        info: dict[str, Any] = {
            "cost": res[R_VIOLATED],
            "violating_samples": status[:, ST_VIOL_SAMPLES],
            "u": last[:, sl[0]],
            "u_law": last[:, sl[1]],
            "u_residual": residual,
            "saturated": status[:, ST_SAT_STEPS] > 0,
            "x3": last[:, sl[2]],
            "x3_hat": last[:, sl[3]],
            "controller_outputs": {name: last[:, s] for name, s in self._out_slices},
            "termination_reason": reason,
            "truncation_reason": trunc_reason,
            "reward_info": {"alive": res[R_ALIVE], **{t.name: res[R_TERM0 + k] for k, t in enumerate(TERMS)},
                            "score": self._score_term.copy(), "violation": res[R_PENALTY]},
        }
        if self._filter_slices:
            info["filter_outputs"] = {name: last[:, s] for name, s in self._filter_slices}
        if gated is not None:
            info["lookahead_handback"] = gated
        if flags & 2:
            info["diverged_message"] = np.array(
                [divergence_message(int(d), float(t), self.sim.dt, self.sim.unstable_steps, self.controller.name)
                 or None for d, t in zip(status[:, ST_DIVERGED], t_end)],
                dtype=object)
        if flags:
            # the episode's totals on its last step (Gymnasium's RecordEpisodeStatistics owns
            # info["episode"]; these are the benchmark's own metrics)
            em = np.empty(N, dtype=object)
            for i in np.flatnonzero(terminated | truncated):
                em[i] = self.episode_metrics(int(i), reason[i], trunc_reason[i])
            info["episode_metrics"] = em
        return info

    def _check_start_time(self, value: Any) -> "tuple[float, float] | None":
        """``start_time`` as a (low, high) range in s, or None (every episode starts at t = 0).
        ValueError names the field and the accepted range, or the reward that cannot go with it."""
        if value is None:
            return None
        o = self.owner
        last = self.sim.duration - self.control_period
        hint = f" (at most the duration less one control period, {last:g} s)"
        if isinstance(value, (list, tuple, np.ndarray)):
            lo, hi = check_reals(o, "start_time", value, 2, lo=0.0, hi=last, unit="s")
            if hi < lo:
                raise ValueError(f"{o} start_time must be a (low, high) range with low <= high, got {value!r}")
        else:
            lo = hi = check_real(o, "start_time", value, lo=0.0, hi=last, unit="s", hint=hint)
        w = self.weights
        if w.score > 0 or w.relative:
            raise ValueError(f"{o} start_time needs a reward without the reference law's run from t = 0 (the score "
                             f"term, relative tracking); give reward_weights with score=0 and relative=False "
                             f"(e.g. reward_weights={{}}), got start_time={value!r} with {w!r}")
        return (float(lo), float(hi))

    def _start_steps(self, idx: Sequence[int], scenarios: Sequence[Scenario]) -> "list[int] | None":
        """Each reset arm's first integration step under ``start_time``: a time drawn from the arm's
        generator (a range) or fixed, rounded to whole control periods and kept at least one period
        before the scenario's end; None without ``start_time`` (nothing drawn)."""
        if self.start_time is None:
            return None
        lo, hi = self.start_time
        p = self.steps_per_period
        out = []
        for i, sc in zip(idx, scenarios):
            t0 = lo if hi == lo else float(self.rngs[i].uniform(lo, hi))
            k = int(round(t0 / self.control_period)) * p
            out.append(min(k, (sc.sim.n_steps // p - 1) * p))
        return out

    def _check_action_scale(self, value: Any) -> "np.ndarray | None":
        """``action_scale`` as n N m per joint, or None (plain mode's scale is then max_torque); one
        number stands for every joint. ValueError names the field and the accepted range."""
        if value is None:
            return None
        o = self.owner
        if isinstance(value, str) and value == "law" and not self.residual:
            value = _law_scale(self.base, self.suite, self.level, None, LAW_SCALE_EPISODES, LAW_SCALE_MARGIN, 0)
        if self.residual:
            raise ValueError(f"{o} action_scale is plain mode's (controller None); in residual mode the residual's "
                             f"torque at action 1 is residual_scale, got action_scale={value!r}")
        n, umax = self.base.arm.n_links, self.sim.max_torque
        if isinstance(value, (list, tuple, np.ndarray)):
            vals = check_reals(o, "action_scale", value, n, lo=0.0, hi=umax, lo_open=True, unit="N m")
        else:
            vals = (check_real(o, "action_scale", value, lo=0.0, hi=umax, lo_open=True, unit="N m",
                               hint=" (at most max_torque)"),) * n
        return np.asarray(vals, dtype=np.float64)

    def _torque(self, a: np.ndarray) -> np.ndarray:
        """Actions in [-1, 1] as N m: the residual's scale, or in plain mode ``action_scale`` per joint
        (each arm's torque limit when it is None)."""
        if self.residual:
            return a * self.residual_scale
        return a * (self._umax[:, None] if self.action_scale is None else self.action_scale[None, :])

    def _draw_noise(self, periods: int, skip: np.ndarray | None = None
                    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The measurement noise of ``periods`` control periods: (angle noise (N, periods * steps, n),
        the next observation's (N, n)) in rad, or (None, None) when no arm is noisy. Each arm draws
        from its own generator, and only if it is noisy and not in ``skip``, so an arm's stream does
        not depend on its neighbours (vector env == single envs): per period, the angle noise of its
        integration steps, then the next observation's, in one call for all periods (the same
        numbers as one call per period, or two)."""
        if not self._noisy:
            return None, None
        N, n, spp = self.num_envs, self.n, self.steps_per_period
        k = spp * n
        z = np.zeros((N, periods, k + n))
        for i in self._noisy:
            if skip is None or not skip[i]:
                self.rngs[i].standard_normal(out=z[i])
        z *= self._stds[:, None, None]
        return z[:, :, :k].reshape(N, periods * spp, n), z[:, -1, k:]

    def hold(self, actions: Any, periods: int) -> None:
        """``periods`` control periods of every arm with the same ``actions``, in one kernel call,
        for runs read only through :meth:`trajectory` (blf-eval's runs of the law alone, a zero
        residual). The state, the record, the episode's counters and each arm's random stream are
        what ``periods`` calls of :meth:`step` would leave, bit for bit: the kernel's numbers do not
        depend on how a run is cut into calls, and a noisy arm draws the same numbers, the
        observation noise it does not use included. (The running sums behind
        :meth:`episode_metrics`' RMSE are added per call, so they may differ in the last bits.)
        No observation, reward or info is made, so it needs a reward that keeps no state across
        steps (no score term, not relative), termination off, a control period of whole 1 ms
        samples and ``periods`` that stay within every arm's episode; ValueError otherwise."""
        o = f"{self.owner} hold:"
        periods = check_int(o, "periods", periods, lo=1)
        if self._score_w > 0 or self.weights.relative or self.terminate_on_violation:
            raise ValueError(f"{o} needs reward_weights with no score term and relative=False, and "
                             "terminate_on_violation=False (their steps read the steps before)")
        if self.steps_per_period % self.sim.steps_per_sample:
            raise ValueError(f"{o} needs a control period of whole 1 ms samples, got {self.control_period} s")
        if int(self.steps.max()) + periods > self.max_episode_steps:
            raise ValueError(f"{o} periods={periods} would run past the episode's end "
                             f"({self.max_episode_steps} periods, {int(self.steps.max())} done)")
        a = self.check_actions(actions)
        N, n, spp, m = self.num_envs, self.n, self.steps_per_period, self.samples_per_period
        residual = self._torque(a)
        noise, _ = self._draw_noise(periods)
        rec = self._record
        out = None if rec is None else np.empty((N, periods * m, len(CHANNELS), n))
        _, nrec, status = self.loop.advance(periods * spp, residual=residual, noise=noise, terminate=False,
                                            record_samples=periods * m if rec is not None else 0, out=out)
        if rec is not None:
            for j in range(periods):
                part = out[:, j * m : (j + 1) * m]
                self._pick_channels(part, rec.slab())
                rec.commit(np.clip(nrec - j * m, 0, m))
        self.steps += periods
        _accumulate_episode(status, self.loop.sums, self.loop.ksteps, self._ep_int, self._ep_f)

    def episode_metrics(self, i: int, termination_reason: str | None = None,
                        truncation_reason: str | None = None) -> dict[str, Any]:
        """Arm i's episode so far, in the benchmark's terms: RMSE per joint (degrees, over its 1 ms
        samples, as blf-eval computes it), violating 1 ms samples (any joint), violating integration
        steps, the first violation (s, on the integration grid, or None), divergence, and how it
        ended."""
        ei, ef = self._ep_int[i], self._ep_f[i]
        samples = float(ef[EP_SAMPLES])
        rmse = (np.degrees(np.sqrt(ef[EP_E2_JOINT:] / samples)).tolist() if samples > 0 else [None] * self.n)
        dt = self.sim.dt
        return {
            "rmse_deg": rmse,
            "violating_samples": int(ei[EP_VIOL_SAMPLES]),
            "violating_steps": int(ei[EP_VIOL_STEPS]),
            "filter_breaches": int(ei[EP_BREACHES]) if self.residual_filter else None,
            "assumption_failures": int(ei[EP_ASSUME_FAIL]) if self.residual_filter else None,
            "first_violation_s": None if ei[EP_FIRST_VIOL] < 0 else float(ei[EP_FIRST_VIOL] * dt),
            "diverged": bool(ei[EP_DIV_CODE]),
            "samples": int(samples),
            "time_s": float(self.loop.ksteps[i] * dt),
            "termination_reason": termination_reason,
            "truncation_reason": truncation_reason,
        }

    def _pick_channels(self, samples: np.ndarray, slab: np.ndarray) -> None:
        """Copy the recorded channels of ``samples`` (N, m, all channels, n) into ``slab`` (one run,
        a whole copy, when every channel is recorded)."""
        for d, c, k in self._rec_runs:
            slab[:, :, d : d + k] = samples[:, :, c : c + k]

    def trajectory(self, i: int = 0, release: bool = False):
        """Arm i's current episode so far on the 1 ms grid, as a
        :class:`blf_gym.kernel.simulate.Trajectory` (requires ``record=True``; its signals are the
        ``record_channels``, all by default), with the same counters as the inner path's:
        violating integration steps, the first one, saturated steps and divergence.
        ``release=True`` frees the arm's record once it is copied out (an evaluation that reduces
        each episode as it comes keeps one copy, not two)."""
        from blf_gym.kernel.simulate import Trajectory, divergence_message

        if not self.record:
            raise ValueError("trajectories are kept only with record=True")
        r = self._record.samples(i, release)
        signals = {name: (r[:, k, 0].copy() if name == "t" else r[:, k, :].copy())
                   for k, name in enumerate(self.record_channels)}
        ei = self._ep_int[i]
        dt = self.sim.dt
        code = int(ei[EP_DIV_CODE])
        t_div = float(ei[EP_DIV_STEP] * dt) if code else None
        return Trajectory(scenario=self.scenarios[i].name, controller=self.controller.name,
                          dt=dt, signals=signals, diverged=bool(code), diverged_at=t_div,
                          step_violations=int(ei[EP_VIOL_STEPS]),
                          first_violation_step_time=None if ei[EP_FIRST_VIOL] < 0 else float(ei[EP_FIRST_VIOL] * dt),
                          saturated_steps=int(ei[EP_SAT_STEPS]), divergence_code=code,
                          filter_breaches=int(ei[EP_BREACHES]), assumption_failures=int(ei[EP_ASSUME_FAIL]),
                          residual_filter=self.residual_filter,
                          message=divergence_message(code, t_div or 0.0, dt, self.sim.unstable_steps,
                                                     self.controller.name) if code else "")

    @staticmethod
    def info_row(info: dict[str, Any], i: int) -> dict[str, Any]:
        """Arm i's info as a plain dict (what the single env returns)."""
        out: dict[str, Any] = {}
        for k, v in info.items():
            if type(v) is dict:
                out[k] = {kk: (vv.item(i) if vv.ndim == 1 else vv[i]) for kk, vv in v.items()}
            else:
                out[k] = v.item(i) if v.ndim == 1 else v[i]  # a Python scalar (or the object itself)
        return out

    # ------------------------------------------------------------------ observation
    def observe(self, info: dict[str, Any] | None = None,
                which: Sequence[int] | None = None, t: np.ndarray | None = None,
                noise: np.ndarray | None = None) -> np.ndarray:
        """Observations (N, obs_dim) float32 at the arms' current time; adds the state part of
        ``info`` (time, error, bounds, margins, as per-arm arrays) when given. Measurement noise is
        drawn only for the arms in ``which`` (default all); the other rows are for discarding. ``t``
        is the arms' current time when the caller already has it; ``noise`` (N, n) rad is the
        measurement noise when the caller drew it (then nothing is drawn here)."""
        N, n = self.num_envs, self.n
        X = self.loop.X
        if t is None:
            t = self.loop.time
        b = self.loop.batch
        if noise is None:
            noise = self._obs_noise
            noise[:] = 0.0
            for i in self._noisy:
                if which is None or i in which:
                    noise[i] = self.rngs[i].standard_normal(n) * self._stds[i]
        obs = np.empty((N, self.obs_dim), dtype=np.float32)
        state = np.empty((N, MARGINS.length(n)))
        observe_batch(X, t, b.ref, b.bnd, b.plant, self.loop.last, noise, self._durations, self._umax, self._plan,
                      self._plan_scale, self._box64[0], self._box64[1], obs, self._ref, self._bnd, state)
        if info is not None:
            bnd = self._bnd.copy()
            info["time"] = t
            info["e1"] = state[:, MARGINS.slice("e1", n)]
            info["k_a"] = bnd[:, KA]
            info["k_b"] = bnd[:, KB]
            # g(t, q) <= 0 convention: positive means the bound is broken
            info["g_upper"] = state[:, MARGINS.slice("g_upper", n)]
            info["g_lower"] = state[:, MARGINS.slice("g_lower", n)]
            if self.privileged:
                info["qd"] = X[:, STATE.slice("qd", n)].copy()
        return obs
