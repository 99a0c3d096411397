"""Nonlinear model-predictive control with CasADi (work in progress: the optimal control problem and
its prediction model; the policy wrapper, the reference preview and the protocol rows follow).

The controller's model is the nominal arm (paper Table 1) derived here symbolically from its
Lagrangian, independently of :mod:`blf_gym.dynamics` (``tests/test_mpc.py`` checks the two against
each other): point masses m_j at the links' far ends, so the kinetic energy is
1/2 sum_j m_j |d p_j/dt|^2 and the potential sum_j m_j g p_j,y, and

    M(q) = sum_j m_j J_j^T J_j,    c(q, qd) = d/dt(M qd)|_qdd=0 - 1/2 d(qd^T M qd)/dq,    G = dV/dq.

The prediction adds the observer's disturbance estimate x3_hat, held over the horizon:
qdd = M^-1 (u - c - G) + x3_hat. It is discretised with one RK4 step per sample period.

The problem (multiple shooting, N intervals of ``sample_period``):

    min  sum_k |q_k - q_d,k|^2_Q + |qd_k - qd_d,k|^2_Qd + r |u_k|^2 + rho sum_k 1^T s_k
    s.t. x_{k+1} = RK4(x_k, u_k),   |u_k| <= u_max,
         -k_b,k + s_k >= -(q_k - q_d,k),  q_k - q_d,k <= k_a,k + s_k,  s_k >= 0

The output constraints are soft with an exact (L1) penalty, so the problem is always feasible;
every violation is still counted by the benchmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blf_gym.params import ArmParams

__all__ = ["NMPCParams", "casadi_dynamics", "NMPC"]


def _casadi():
    try:
        import casadi
    except ImportError as exc:  # pragma: no cover - depends on the extra
        raise ImportError("the NMPC needs CasADi: pip install 'blf-gym[mpc]'") from exc
    return casadi


@dataclass(frozen=True)
class NMPCParams:
    """The NMPC's horizon, weights and solver settings."""

    horizon: int = field(default=30, metadata={"unit": "-"})
    """Intervals in the horizon (>= 1); the horizon covers horizon x sample_period seconds."""
    sample_period: float = field(default=0.01, metadata={"unit": "s"})
    """The period at which the problem is solved and its first torque held (> 0)."""
    q_weight: float = field(default=1e4, metadata={"unit": "1/rad^2"})
    """Weight of the squared angle error."""
    qd_weight: float = field(default=10.0, metadata={"unit": "s^2/rad^2"})
    """Weight of the squared velocity error."""
    u_weight: float = field(default=1e-4, metadata={"unit": "1/(N m)^2"})
    """Weight of the squared torque."""
    penalty: float = field(default=1e5, metadata={"unit": "1/rad"})
    """Exact-penalty weight of the output constraints' slack."""
    max_iter: int = field(default=50, metadata={"unit": "-"})
    """Iteration limit of the solver per sample."""
    nominal: ArmParams = field(default_factory=ArmParams)

    def __post_init__(self) -> None:
        o = "NMPCParams"
        for name in ("horizon", "max_iter"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{o}.{name} must be an integer >= 1, got {v!r}")
        for name in ("sample_period", "q_weight", "qd_weight", "u_weight", "penalty"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{o}.{name} must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.sample_period <= 0:
            raise ValueError(f"{o}.sample_period must be > 0 s, got {self.sample_period!r}")


def casadi_dynamics(arm: ArmParams = ArmParams()) -> Any:
    """A CasADi Function ``f(x, u, d) -> xdot`` of the nominal arm, x = [q, qd] (2n), u and d (n):
    qdd = M^-1 (u - c(q, qd) - G(q)) + d (see the module docstring)."""
    ca = _casadi()
    n = arm.n_links
    q = ca.SX.sym("q", n)
    qd = ca.SX.sym("qd", n)
    u = ca.SX.sym("u", n)
    d = ca.SX.sym("d", n)
    theta = ca.cumsum(q)
    px, py = ca.SX(0), ca.SX(0)
    M = ca.SX.zeros(n, n)
    V = ca.SX(0)
    for j in range(n):
        px = px + arm.lengths[j] * ca.cos(theta[j])
        py = py + arm.lengths[j] * ca.sin(theta[j])
        J = ca.jacobian(ca.vertcat(px, py), q)
        M = M + arm.masses[j] * (J.T @ J)
        V = V + arm.masses[j] * arm.gravity * py
    Mqd = M @ qd
    c = ca.jtimes(Mqd, q, qd) - 0.5 * ca.gradient(ca.dot(qd, Mqd), q)
    G = ca.gradient(V, q)
    qdd = ca.solve(M, u - c - G) + d
    return ca.Function("f", [ca.vertcat(q, qd), u, d], [ca.vertcat(qd, qdd)], ["x", "u", "d"], ["xdot"])


class NMPC:
    """The optimal control problem of the module docstring, solved with IPOPT and warm-started
    from the previous solution shifted by one interval."""

    def __init__(self, params: NMPCParams = NMPCParams(), u_max: float = 150.0) -> None:
        ca = _casadi()
        self.params = p = params
        n = p.nominal.n_links
        self.n, self.N, self.u_max = n, p.horizon, float(u_max)
        f = casadi_dynamics(p.nominal)
        h = p.sample_period
        x, u, d = ca.SX.sym("x", 2 * n), ca.SX.sym("u", n), ca.SX.sym("d", n)
        k1 = f(x, u, d)
        k2 = f(x + h / 2 * k1, u, d)
        k3 = f(x + h / 2 * k2, u, d)
        k4 = f(x + h * k3, u, d)
        self.step = ca.Function("rk4", [x, u, d], [x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
        opti = ca.Opti()
        N = self.N
        X = opti.variable(2 * n, N + 1)
        U = opti.variable(n, N)
        S = opti.variable(n, N)
        x0, dh = opti.parameter(2 * n), opti.parameter(n)
        qref, qdref = opti.parameter(n, N + 1), opti.parameter(n, N + 1)
        ka, kb = opti.parameter(1, N + 1), opti.parameter(1, N + 1)
        cost = 0
        opti.subject_to(X[:, 0] == x0)
        for k in range(N):
            opti.subject_to(X[:, k + 1] == self.step(X[:, k], U[:, k], dh))
            e = X[:n, k + 1] - qref[:, k + 1]
            ed = X[n:, k + 1] - qdref[:, k + 1]
            cost += p.q_weight * ca.sumsqr(e) + p.qd_weight * ca.sumsqr(ed) + p.u_weight * ca.sumsqr(U[:, k])
            cost += p.penalty * ca.sum1(S[:, k])
            opti.subject_to(e <= ka[0, k + 1] + S[:, k])
            opti.subject_to(-e <= kb[0, k + 1] + S[:, k])
        opti.subject_to(ca.vec(S) >= 0)
        opti.subject_to(opti.bounded(-self.u_max, ca.vec(U), self.u_max))
        opti.minimize(cost)
        opti.solver("ipopt", {"expand": True, "print_time": False, **self._jit(), "ipopt.print_level": 0, "ipopt.sb": "yes",
                              "ipopt.max_iter": p.max_iter, "ipopt.warm_start_init_point": "yes"})
        self._opti, self._X, self._U, self._S = opti, X, U, S
        self._par = (x0, dh, qref, qdref, ka, kb)
        # one CasADi Function around the solver: Opti's own solve() re-checks the problem each call
        self._solver = opti.to_function("nmpc", [x0, dh, qref, qdref, ka, kb, X, U, S], [X, U, S],
                                        ["x0", "d", "qref", "qdref", "ka", "kb", "X0", "U0", "S0"], ["X", "U", "S"])
        self._guess: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @staticmethod
    def _jit() -> dict[str, Any]:
        """Compile the problem's functions to C when a C compiler is on the PATH (about ten times
        faster per iteration); otherwise CasADi's virtual machine evaluates them."""
        import shutil

        if shutil.which("gcc") is None and shutil.which("cc") is None:
            return {}
        return {"jit": True, "compiler": "shell", "jit_options": {"flags": ["-O1"], "verbose": False}}

    def predict_states(self, x0: np.ndarray, torques: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
        """The model's states after each of ``torques`` (k, n), each held one sample period, from x0."""
        d = np.zeros(self.n) if d is None else d
        out, x = [], np.asarray(x0, dtype=float)
        for u in np.atleast_2d(torques):
            x = np.asarray(self.step(x, u, d)).ravel()
            out.append(x)
        return np.array(out)

    def solve(self, x0, d_hat, q_ref, qd_ref, k_a, k_b) -> tuple[np.ndarray, dict[str, Any]]:
        """The first torque of the optimal plan and the solver's facts (``success``, ``iterations``,
        ``slack``: the largest constraint slack in rad, ``status``). ``q_ref``, ``qd_ref`` (n, N+1)
        and ``k_a``, ``k_b`` (N+1) cover the horizon's nodes, the current one first."""
        if self._guess is not None:
            Xg, Ug, Sg = self._guess
            X0 = np.hstack([Xg[:, 1:], Xg[:, -1:]])
            U0 = np.hstack([Ug[:, 1:], Ug[:, -1:]])
            S0 = np.hstack([Sg[:, 1:], Sg[:, -1:]])
        else:
            X0 = np.repeat(np.reshape(x0, (-1, 1)), self.N + 1, axis=1)
            U0 = np.zeros((self.n, self.N))
            S0 = np.zeros((self.n, self.N))
        X, U, S = self._solver(x0, d_hat, q_ref, qd_ref, np.reshape(k_a, (1, -1)), np.reshape(k_b, (1, -1)), X0, U0, S0)
        stats = self._solver.stats()
        X, U, S = np.asarray(X), np.asarray(U), np.asarray(S)
        ok = bool(stats.get("success", False)) and np.all(np.isfinite(U))
        self._guess = (X, U, S)
        return U[:, 0].copy(), {"success": ok, "iterations": int(stats.get("iter_count", -1)),
                                "slack": float(np.max(S)), "status": str(stats.get("return_status", ""))}

    def reset(self) -> None:
        """Forget the warm start (a new episode)."""
        self._guess = None
