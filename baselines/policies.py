"""The paper's laws as SB3-style policies: ``predict(obs, state, episode_start, deterministic)``.

A :class:`BaselinePolicy` drives the **plain** env (the action is the torque over max_torque)
from observations alone, so SB3's ``evaluate_policy`` and our evaluation can score a controller
exactly like a trained agent. It is a *sampled* implementation: it runs its own LESO on the
measured angles, holds its torque over the env's ``control_period`` and must be used with
``control_period`` equal to the integration step (0.1 ms), e.g.::

    env = gym.make("PlanarBLF-v0", control_period=1e-4)
    policy = BaselinePolicy("proposed", env=env)

Given ``env=``, the policy refuses an env whose ``control_period`` is not its ``dt``, or that is in
residual mode, or whose torque limit differs (on the default 10 ms env the held torque breaks the
bounds within a few steps). Without ``env=`` it cannot check, and warns once at the first
``predict``.

The inner path (``controller=`` in the env, or ``blf_gym.kernel.simulate``) evaluates the same compiled
law at every ODE3 stage instead; the two agree closely but not exactly (docs/model.md section 6), and the
evaluation command uses the inner path. BC reads the true velocity, so it needs
``privileged=True``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from blf_gym.plugins.blocks import connect, model_length, nominal_length, nominal_model_into, work_length
from blf_gym.model.bounds import BOUND_LEN, KA, KA_DDOT, KA_DOT, KB, KB_DDOT, KB_DOT
from blf_gym.envs.observation import (SQUASH_REF_ACCELERATION, SQUASH_VELOCITY, observation_index, observation_layout,
                                  unsquash)
from blf_gym.model.reference import REFERENCE_SIGNALS
from blf_gym.model.params import BoundParams

from .controllers import ControllerGains, ObserverGains
from .leso import leso_ode3

__all__ = ["BaselinePolicy"]

_SQ_VEL, _SQ_ACC = SQUASH_VELOCITY, SQUASH_REF_ACCELERATION


class BaselinePolicy:
    """BC, LESOBC or the proposed law as a policy for the plain ``PlanarBLF-v0`` env.

    The number of joints n is the law's nominal arm's (``gains.nominal``; without ``gains``, the
    plug-in's default, the paper's 3-link arm), and so are the observation's layout and the action's
    n entries. For an arm of other than 3 links pass ``gains=ControllerGains(nominal=arm, K1=...,
    K2=...)``; ``check_env`` refuses an env whose arm has another number of links."""

    def __init__(
        self,
        controller: str = "proposed",
        dt: float = 1e-4,
        max_torque: float = 150.0,
        gains: ControllerGains | None = None,
        observer: ObserverGains | None = None,
        bounds: BoundParams | None = None,
        env: Any = None,
    ) -> None:
        from dataclasses import fields as _fields

        from blf_gym.plugins.registry import available_controllers, make_controller, make_observer

        names = [c for c in available_controllers() if c != "none"]
        if controller not in names:
            raise ValueError(f"unknown controller {controller!r}; accepted values: {names}")
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        if not (np.isfinite(max_torque) and max_torque > 0):
            raise ValueError(f"max_torque must be a positive number of N m, got {max_torque!r}")
        self.name = controller
        self.gains = gains or ControllerGains()
        self.obs_gains = observer or ObserverGains()
        # the registered plug-in, built with these gains (a plug-in of another package takes its
        # own defaults), connected to the LESO this policy integrates itself
        # the given gains go to the plug-in's factory; without them it takes its own defaults
        kw = {} if gains is None else {f.name: getattr(gains, f.name) for f in _fields(gains)}
        self.inner = make_controller(controller, **kw)
        if self.inner.states:
            raise ValueError(f"BaselinePolicy samples stateless laws; {controller!r} has states "
                             f"{list(self.inner.states)}: score it on the inner path (controller={controller!r})")
        n = self.n = self.inner.nominal.n_links
        self._layout(n)
        # the LESO models the law's arm (connect asks both blocks for one nominal model)
        self._conn = connect(self.inner, make_observer("leso", k0=self.obs_gains.k0, nominal=self.inner.nominal), n)
        self.bounds = bounds or BoundParams()
        self.dt = float(dt)
        self.max_torque = float(max_torque)
        self._nominal = self.inner.nominal.pack()
        self._k0 = np.array([self.obs_gains.k0])
        self._nom = np.zeros(nominal_length(n))
        self._nom[model_length(n) : model_length(n) + self._nominal.size] = self._nominal
        self._work = np.zeros(work_length(n))
        self._cout = np.zeros(self._conn.n_out)
        self._none = np.zeros(0)
        self._xhat: np.ndarray | None = None
        self._y_prev: np.ndarray | None = None
        self._u_prev: np.ndarray | None = None
        self._checked = False
        if env is not None:
            self.check_env(env)

    def _layout(self, n: int) -> None:
        """Where the law's inputs sit in the observation of an arm of ``n`` links."""
        idx = observation_index(n)
        self._obs_dim = len(observation_layout(n))
        self._y, self._qd_ref, self._qd_d, self._qdd_d = idx["y"], idx["q_d"], idx["qd_d"], idx["qdd_d"]
        self._ka, self._kb = idx["k_a"].start, idx["k_b"].start
        self._kad, self._kbd = idx["k_a_rate"].start, idx["k_b_rate"].start
        self._time = idx["time"].start
        self._qd_true = idx["qd"]

    def check_env(self, env: Any) -> None:
        """Refuse an env this policy cannot drive: residual mode, a ``control_period`` other than
        ``dt``, another torque limit, or an arm of another number of links than the law's. Accepts a
        Gymnasium env (wrapped or not) or vector env."""
        core = getattr(getattr(env, "unwrapped", env), "core", None)
        if core is None:
            raise ValueError(f"BaselinePolicy.check_env: {type(env).__name__} is not a PlanarBLF env")
        if core.n != self.n:
            raise ValueError(f"BaselinePolicy's law models an arm of {self.n} links, the env's has {core.n}: pass "
                             "gains=ControllerGains(nominal=<the env's arm>, K1=..., K2=...)")
        if core.residual:
            raise ValueError("BaselinePolicy drives the plain env (its action is the whole torque); this env is "
                             f"in residual mode over {core.controller.name!r}. Use gym.make('PlanarBLF-v0', ...)")
        if not np.isclose(core.control_period, self.dt, rtol=1e-9, atol=0.0):
            raise ValueError(f"BaselinePolicy integrates its LESO and holds its torque with dt = {self.dt:g} s, but "
                             f"the env's control_period is {core.control_period:g} s; make the env with "
                             f"control_period={self.dt:g} (at 10 ms the held torque breaks the bounds within "
                             "a few steps)")
        if not np.isclose(core.sim.max_torque, self.max_torque):
            raise ValueError(f"BaselinePolicy scales its torque by max_torque = {self.max_torque:g} N m, but the env's "
                             f"is {core.sim.max_torque:g} N m; pass max_torque={core.sim.max_torque:g}")
        self._checked = True

    def reset(self, num_envs: int = 1) -> None:
        self._xhat = None
        self._y_prev = None
        self._u_prev = np.zeros((num_envs, self.n))

    def _laws(self, obs: np.ndarray, starts: np.ndarray) -> np.ndarray:
        N, n = obs.shape[0], self.n
        if self._xhat is None or self._xhat.shape[0] != N:
            self._xhat = np.zeros((N, self._conn.n_obs))
            self._y_prev = obs[:, self._y].copy()
            self._u_prev = np.zeros((N, n))
            starts = np.ones(N, dtype=bool)
        u = np.zeros((N, n))
        ref = np.empty(len(REFERENCE_SIGNALS) * n)
        bnd = np.empty(BOUND_LEN)
        for i in range(N):
            y = obs[i, self._y].astype(np.float64)
            if starts[i]:
                self._xhat[i] = 0.0
                self._xhat[i, :n] = y
                self._u_prev[i] = 0.0
            else:
                # the observer integrates the last period with the measurement and torque held
                self._xhat[i] = leso_ode3(self._xhat[i], self._y_prev[i], self._u_prev[i],
                                          self._nominal, self._k0, self.dt, self._work)
            ref[:n] = obs[i, self._qd_ref]
            ref[n : 2 * n] = unsquash(obs[i, self._qd_d].astype(np.float64), _SQ_VEL)
            ref[2 * n :] = unsquash(obs[i, self._qdd_d].astype(np.float64), _SQ_ACC)
            ka, kb = float(obs[i, self._ka]), float(obs[i, self._kb])
            kad, kbd = float(obs[i, self._kad]), float(obs[i, self._kbd])
            r = self.bounds.decay_rate  # exponential bounds: k'' = -r k'
            bnd[[KA, KA_DOT, KA_DDOT, KB, KB_DOT, KB_DDOT]] = (ka, kad, -r * kad, kb, kbd, -r * kbd)
            if self.inner.full_state:
                if obs.shape[1] < self._qd_true.stop:
                    raise ValueError(f"{self.name} reads the true velocity (a full-state law): make the env with "
                                     "privileged=True")
                qd = unsquash(obs[i, self._qd_true].astype(np.float64), _SQ_VEL)
            else:
                qd = np.zeros(n)
            nominal_model_into(y, self._nominal, self._nom, self._work)
            c = self._conn
            # the law's output alone, through the generated glue's named signals (blf_gym.plugins.blocks;
            # unused ones get an empty array): no observer or controller state, no filter, no derivatives
            c.ctrl_output(t=0.0, y=y, q=y, qd=qd, xo=self._xhat[i], xc=self._none, ref=ref, bnd=bnd, nom=self._nom,
                          og=self._k0, cg=self.inner.gains, fg=self._none, u=self._none, cout=self._cout,
                          r=self._none, fout=self._none, umax=self.max_torque, dxo=self._none, dxc=self._none,
                          work=self._work)
            u[i] = np.clip(self._cout[:n], -self.max_torque, self.max_torque)
            self._y_prev[i] = y
            self._u_prev[i] = u[i]
        return u

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        """SB3's PolicyPredictor interface: actions in [-1, 1] (torque / max_torque)."""
        if not self._checked:
            import warnings

            warnings.warn(f"BaselinePolicy({self.name!r}) was not given env=, so it cannot check that the env's "
                          f"control_period equals its dt = {self.dt:g} s; at the default 10 ms it breaks the "
                          "bounds within a few steps. Pass env= (or call check_env(env)).", UserWarning, stacklevel=2)
            self._checked = True
        obs = np.asarray(observation)
        single = obs.ndim == 1
        batch = obs[None] if single else obs
        if batch.ndim != 2 or batch.shape[1] < self._obs_dim:
            raise ValueError(f"expected PlanarBLF observations of an arm of {self.n} links, of shape ({self._obs_dim},) "
                             f"or (N, {self._obs_dim}+), got {obs.shape}")
        starts = (np.zeros(batch.shape[0], dtype=bool) if episode_start is None
                  else np.asarray(episode_start, dtype=bool).reshape(-1))
        # an observation at t = 0 starts an episode even if the caller does not say so
        starts = starts | (batch[:, self._time] == 0.0)
        u = self._laws(batch, starts)
        actions = (u / self.max_torque).astype(np.float32)
        return (actions[0] if single else actions), state
