"""The batched environment logic shared by :class:`~blf_gym.env.PlanarBLFEnv` (one arm) and
:class:`~blf_gym.vector.PlanarBLFVectorEnv` (N arms): scenario handling, the agent step over the
compiled closed loop, observations, rewards and info. There is no other copy of this logic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Mapping, Sequence

import numpy as np
from numba import njit

from .bounds import bounds_into
from .controller import NO_CONTROLLER, InnerController, make_controller
from .metrics import violation_mask
from .params import Scenario
from .reference import reference_into
from .scenarios import apply_variations, resolve_scenario, sample_suite
from .simulate import CHANNELS, ClosedLoop, divergence_message

__all__ = ["RewardWeights", "EnvCore", "observation_layout"]

_CH = {name: i for i, name in enumerate(CHANNELS)}


@dataclass(frozen=True)
class RewardWeights:
    """Per-agent-step reward r = alive - tracking * E - torque * U - violation * [ended by it].

    E is the mean over the step's 1 ms samples and the joints of (e1 / bound)^2, the error
    normalized by the bound on its side (so E <= 1 while inside the bounds); U is the mean of
    (u / max_torque)^2 (<= 1). With ``alive >= tracking + torque`` (checked), every step inside
    the bounds earns r >= 0, so ending an episode early by a violation never pays.
    """

    tracking: float = 1.0
    """Weight of the normalized squared tracking error (>= 0)."""
    torque: float = 0.01
    """Weight of the normalized squared torque (>= 0)."""
    alive: float | None = None
    """Reward per step for staying inside the bounds; default tracking + torque."""
    violation: float = 100.0
    """Penalty on the step that ends the episode by a violation or divergence (>= 0)."""

    def __post_init__(self) -> None:
        for name in ("tracking", "torque", "violation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"RewardWeights.{name} must be finite and >= 0, got {v!r}")
        if self.alive is None:
            object.__setattr__(self, "alive", self.tracking + self.torque)
        if not (math.isfinite(self.alive) and self.alive >= self.tracking + self.torque):
            raise ValueError(
                f"RewardWeights.alive must be >= tracking + torque = {self.tracking + self.torque} "
                f"so that a violation never pays; got {self.alive!r}")


# Squashing scales (value -> c tanh(value / c)) of the unbounded observation entries.
_SQ_VEL = 100.0
_SQ_ACC_REF = 1000.0
_SQ_DIST = 1.0e4
_ANGLE_CLIP = 4.0 * math.pi
_ERR_CLIP = 10.0


def observation_layout(n: int = 3, privileged: bool = False) -> list[tuple[str, str, float, float]]:
    """(name, unit, low, high) of every observation entry, in order."""
    rows: list[tuple[str, str, float, float]] = []
    rows += [(f"y_{j+1} (measured angle)", "rad", -_ANGLE_CLIP, _ANGLE_CLIP) for j in range(n)]
    rows += [(f"q_d_{j+1}", "rad", -_ANGLE_CLIP, _ANGLE_CLIP) for j in range(n)]
    rows += [(f"qd_d_{j+1} (squashed {_SQ_VEL:g})", "rad/s", -_SQ_VEL, _SQ_VEL) for j in range(n)]
    rows += [(f"qdd_d_{j+1} (squashed {_SQ_ACC_REF:g})", "rad/s^2", -_SQ_ACC_REF, _SQ_ACC_REF) for j in range(n)]
    rows += [(f"e1_{j+1} / bound (clipped)", "-", -_ERR_CLIP, _ERR_CLIP) for j in range(n)]
    rows += [("k_a", "rad", 0.0, 10.0), ("k_b", "rad", 0.0, 10.0),
             ("k_a'", "rad/s", -10.0, 10.0), ("k_b'", "rad/s", -10.0, 10.0),
             ("sin(2 pi f t)", "-", -1.0, 1.0), ("cos(2 pi f t)", "-", -1.0, 1.0),
             ("t / duration", "-", 0.0, 1.0)]
    rows += [(f"u_{j+1} / max_torque (last applied)", "-", -1.0, 1.0) for j in range(n)]
    rows += [(f"x2_hat_{j+1} (squashed {_SQ_VEL:g})", "rad/s", -_SQ_VEL, _SQ_VEL) for j in range(n)]
    rows += [(f"x3_hat_{j+1} (squashed {_SQ_DIST:g})", "rad/s^2", -_SQ_DIST, _SQ_DIST) for j in range(n)]
    if privileged:
        rows += [(f"qd_{j+1} true (squashed {_SQ_VEL:g})", "rad/s", -_SQ_VEL, _SQ_VEL) for j in range(n)]
        rows += [(f"x3_{j+1} true (squashed {_SQ_DIST:g})", "rad/s^2", -_SQ_DIST, _SQ_DIST) for j in range(n)]
    return rows


@njit(cache=True, error_model="numpy")
def _refs_and_bounds(ts, rp, bp, plant, out_ref, out_bnd):
    for b in range(ts.shape[0]):
        reference_into(ts[b], rp[b], plant[b], out_ref[b])
        bounds_into(ts[b], bp[b], out_bnd[b])


def _squash(x: np.ndarray, c: float) -> np.ndarray:
    return c * np.tanh(x / c)


def _normalized_error(e: np.ndarray, ka: np.ndarray, kb: np.ndarray) -> np.ndarray:
    return np.where(e >= 0.0, e / ka, e / kb)


class EnvCore:
    """N arms of the PlanarBLF task stepped together by one compiled kernel call."""

    def __init__(
        self,
        num_envs: int,
        scenario: "str | Scenario" = "paper-0.1hz",
        controller: "str | InnerController | None" = None,
        residual_scale: float = 2.0,
        control_period: float = 0.01,
        privileged: bool = False,
        terminate_on_violation: bool = True,
        angle_noise_std: float | None = None,
        duration: float | None = None,
        max_torque: float | None = None,
        dt: float | None = None,
        variations: Mapping[str, Any] | None = None,
        reward_weights: RewardWeights | Mapping[str, float] | None = None,
        threads: int | None = None,
    ) -> None:
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        self.num_envs = int(num_envs)
        base, suite = resolve_scenario(scenario)
        sim_over = {k: v for k, v in (("duration", duration), ("max_torque", max_torque), ("dt", dt))
                    if v is not None}
        if sim_over:
            base = replace(base, sim=replace(base.sim, **sim_over))
        if angle_noise_std is not None:
            base = apply_variations(base, {"angle_noise_std": angle_noise_std})
        self.variations = dict(variations or {})
        self.base = apply_variations(base, self.variations) if self.variations else base
        self.suite = suite
        self.sim = self.base.sim
        # agent period: h | 1 ms | control_period (SPEC section 6)
        if not (math.isfinite(control_period) and control_period > 0):
            raise ValueError(f"control_period must be a positive number of seconds, got {control_period!r}")
        ratio = control_period / self.sim.sample_period
        if abs(ratio - round(ratio)) > 1e-9 * max(ratio, 1.0) or round(ratio) < 1:
            raise ValueError(
                f"control_period must be a whole multiple of the {self.sim.sample_period} s sample "
                f"period (e.g. 0.002, 0.005, 0.01), got {control_period!r}")
        self.control_period = float(control_period)
        self.samples_per_period = int(round(ratio))
        self.steps_per_period = self.samples_per_period * self.sim.steps_per_sample
        self.max_episode_steps = int(math.ceil(self.sim.n_samples / self.samples_per_period))
        if not (math.isfinite(residual_scale) and residual_scale > 0):
            raise ValueError(f"residual_scale must be a positive number of N m, got {residual_scale!r}")
        self.controller = NO_CONTROLLER if controller is None else make_controller(controller)
        self.residual = self.controller is not NO_CONTROLLER
        self.residual_scale = float(residual_scale)
        self.privileged = bool(privileged)
        self.terminate_on_violation = bool(terminate_on_violation)
        if reward_weights is None:
            reward_weights = RewardWeights()
        elif not isinstance(reward_weights, RewardWeights):
            reward_weights = RewardWeights(**dict(reward_weights))
        self.weights = reward_weights
        self.n = self.base.arm.n_links
        self.loop = ClosedLoop([self.base] * self.num_envs, self.controller, threads=threads)
        self.obs_dim = len(observation_layout(self.n, self.privileged))
        layout = observation_layout(self.n, self.privileged)
        self.obs_low = np.array([r[2] for r in layout], dtype=np.float32)
        self.obs_high = np.array([r[3] for r in layout], dtype=np.float32)
        N, n = self.num_envs, self.n
        self.scenarios: list[Scenario] = [self.base] * N
        self.rngs: list[np.random.Generator] = [np.random.default_rng() for _ in range(N)]
        self.steps = np.zeros(N, dtype=np.int64)
        self.last_x3 = np.zeros((N, n))
        self.done = np.zeros(N, dtype=bool)
        self._ref = np.zeros((N, 3 * n))
        self._bnd = np.zeros((N, 6))

    # ------------------------------------------------------------------ reset
    def scenario_for(self, rng: np.random.Generator, options: Mapping[str, Any] | None) -> Scenario:
        """The episode's scenario: the suite draw (if any), then option variations."""
        sc = sample_suite(rng, self.base, self.suite) if self.suite else self.base
        if options:
            opts = dict(options)
            var = {k: opts.pop(k) for k in list(opts) if k in ("frequency", "force", "force_onset",
                   "friction_scale", "dead_zone_scale", "payload", "initial_error", "angle_noise_std")}
            if opts:
                raise ValueError(f"unknown reset option(s) {sorted(opts)}; accepted: the variations "
                                 "of blf_gym.scenarios.VARIATIONS")
            sc = apply_variations(sc, var)
        return sc

    def reset_envs(self, idx: Sequence[int], options: Mapping[str, Any] | None = None) -> None:
        scs = [self.scenario_for(self.rngs[i], options) for i in idx]
        for i, sc in zip(idx, scs):
            self.scenarios[i] = sc
        self.loop.set_scenarios(scs, which=list(idx))
        for i in idx:
            self.steps[i] = 0
            self.last_x3[i] = 0.0
            self.done[i] = False

    # ------------------------------------------------------------------ step
    def check_actions(self, actions: Any) -> np.ndarray:
        a = np.asarray(actions, dtype=np.float64)
        want = (self.num_envs, self.n)
        if a.shape != want:
            if self.num_envs == 1 and a.shape == (self.n,):
                a = a.reshape(want)
            else:
                raise ValueError(f"action must have shape {want if self.num_envs > 1 else (self.n,)}, "
                                 f"got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a.tolist()}")
        return np.clip(a, -1.0, 1.0)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        a = self.check_actions(actions)
        N, n = self.num_envs, self.n
        scale = self.residual_scale if self.residual else np.array(
            [sc.sim.max_torque for sc in self.scenarios])[:, None]
        residual = a * scale
        noise = None
        stds = np.array([sc.angle_noise_std for sc in self.scenarios])
        if np.any(stds > 0):
            # each arm draws from its own generator, and only if it is noisy, so an arm's stream
            # does not depend on its neighbours (vector env == single envs)
            noise = np.zeros((N, self.steps_per_period, n))
            for i in np.flatnonzero(stds > 0):
                noise[i] = self.rngs[i].standard_normal((self.steps_per_period, n)) * stds[i]
        rec, nrec, status = self.loop.advance(self.steps_per_period, residual=residual, noise=noise,
                                              terminate=self.terminate_on_violation,
                                              record_samples=self.samples_per_period)
        self.steps += 1
        rewards = np.zeros(N)
        terminated = np.zeros(N, dtype=bool)
        truncated = np.zeros(N, dtype=bool)
        infos: list[dict[str, Any]] = []
        w = self.weights
        for i in range(N):
            r = rec[i, : nrec[i]]
            info: dict[str, Any] = {}
            if nrec[i] > 0:
                e = r[:, _CH["e1"]]
                ka = r[:, _CH["k_a"]]
                kb = r[:, _CH["k_b"]]
                u = r[:, _CH["u"]]
                tracking = float(np.mean(_normalized_error(e, ka, kb) ** 2))
                torque = float(np.mean((u / self.scenarios[i].sim.max_torque) ** 2))
                viol_samples = int(violation_mask(e, ka, kb).any(axis=1).sum())
                self.last_x3[i] = r[-1, _CH["x3"]]
                last = r[-1]
            else:
                tracking = torque = 0.0
                viol_samples = 0
                last = None
            diverged = int(status[i, 1])
            violated = int(status[i, 2]) > 0
            reason = None
            if diverged:
                reason = "diverged"
            elif violated and self.terminate_on_violation:
                reason = "violation"
            terminated[i] = reason is not None
            penalty = w.violation if terminated[i] else 0.0
            rewards[i] = w.alive - w.tracking * tracking - w.torque * torque - penalty
            t_end = float(self.loop.time[i])
            truncated[i] = (not terminated[i]) and t_end >= self.scenarios[i].sim.duration - 1e-12
            info["reward_info"] = {"alive": w.alive, "tracking": -w.tracking * tracking,
                                   "torque": -w.torque * torque, "violation": -penalty}
            info["cost"] = 1.0 if violated else 0.0
            info["violating_samples"] = viol_samples
            info["termination_reason"] = reason
            if diverged:
                info["diverged_message"] = divergence_message(diverged, t_end, self.sim.dt)
            if truncated[i]:
                info["truncation_reason"] = "time_limit"
            if last is not None:
                info["u"] = last[_CH["u"]].copy()
                info["u_law"] = last[_CH["u_law"]].copy()
                info["u_residual"] = residual[i].copy()
                info["saturated"] = bool(np.any(r[:, _CH["saturated"]] > 0))
                info["x3"] = last[_CH["x3"]].copy()
                info["x3_hat"] = last[_CH["x3_hat"]].copy()
            infos.append(info)
            self.done[i] = terminated[i] or truncated[i]
        obs = self.observe(infos)
        return obs, rewards, terminated, truncated, infos

    # ------------------------------------------------------------------ observation
    def observe(self, infos: list[dict[str, Any]] | None = None,
                which: Sequence[int] | None = None) -> np.ndarray:
        """Observations (N, obs_dim) float32 at the arms' current time; fills the state part of
        ``infos`` (time, error, bounds, margins) when given. Measurement noise is drawn only for
        the arms in ``which`` (default all); the other rows are for discarding."""
        N, n = self.num_envs, self.n
        X = self.loop.X
        t = self.loop.time.astype(np.float64)
        b = self.loop._batch
        _refs_and_bounds(t, b.ref, b.bnd, b.plant, self._ref, self._bnd)
        ref, bnd = self._ref, self._bnd
        q = X[:, :n]
        noise = np.zeros((N, n))
        for i in range(N) if which is None else which:
            std = self.scenarios[i].angle_noise_std
            if std > 0:
                noise[i] = self.rngs[i].standard_normal(n) * std
        y = q + noise
        e = q - ref[:, :n]
        ka = bnd[:, 0:1]
        kb = bnd[:, 3:4]
        freq = b.ref[:, 0]
        dur = np.array([sc.sim.duration for sc in self.scenarios])
        umax = np.array([sc.sim.max_torque for sc in self.scenarios])[:, None]
        parts = [
            np.clip(y, -_ANGLE_CLIP, _ANGLE_CLIP),
            np.clip(ref[:, :n], -_ANGLE_CLIP, _ANGLE_CLIP),
            _squash(ref[:, n : 2 * n], _SQ_VEL),
            _squash(ref[:, 2 * n :], _SQ_ACC_REF),
            np.clip(_normalized_error(e, ka, kb), -_ERR_CLIP, _ERR_CLIP),
            bnd[:, [0, 3, 1, 4]],
            np.sin(2 * np.pi * freq * t)[:, None],
            np.cos(2 * np.pi * freq * t)[:, None],
            np.clip(t / dur, 0.0, 1.0)[:, None],
            np.clip(self.loop.last[:, :n] / umax, -1.0, 1.0),
            _squash(X[:, 3 * n : 4 * n], _SQ_VEL),
            _squash(X[:, 4 * n : 5 * n], _SQ_DIST),
        ]
        if self.privileged:
            parts += [_squash(X[:, n : 2 * n], _SQ_VEL), _squash(self.last_x3, _SQ_DIST)]
        obs = np.concatenate(parts, axis=1).astype(np.float32)
        np.clip(obs, self.obs_low, self.obs_high, out=obs)
        if infos is not None:
            for i, info in enumerate(infos):
                info["time"] = float(t[i])
                info["e1"] = e[i].copy()
                info["k_a"] = float(bnd[i, 0])
                info["k_b"] = float(bnd[i, 3])
                # g(t, q) <= 0 convention: positive means the bound is broken
                info["g_upper"] = e[i] - bnd[i, 0]
                info["g_lower"] = -bnd[i, 3] - e[i]
                if self.privileged:
                    info["qd"] = X[i, n : 2 * n].copy()
        return obs
