"""Nonlinear model-predictive control with CasADi, as a policy of the plain env (docs/model.md
section 15).

The controller's model is the nominal arm (paper Table 1) derived here symbolically from its
Lagrangian, independently of :mod:`blf_gym.model.dynamics` (``tests/test_mpc.py`` checks the two against
each other): point masses m_j at the links' far ends, so the kinetic energy is
1/2 sum_j m_j |d p_j/dt|^2 and the potential sum_j m_j g p_j,y, and

    M(q) = sum_j m_j J_j^T J_j,    c(q, qd) = d/dt(M qd)|_qdd=0 - 1/2 d(qd^T M qd)/dq,    G = dV/dq.

The model adds the joint friction F(qd) = b qd + c tanh(psi qd) (the paper's nominal values) and a
disturbance d held over the horizon: qdd = M^-1 (u - c - G - F(qd)) + d. Each interval is
``substeps`` RK4 steps (ten of 1 ms: the friction is a mode of up to 2,500 1/s on the light third
link). The state and d come from the policy's own extended Kalman filter on z = [q, qd, d]: the
model's step under the torque applied over the last sample predicts, the measured angle corrects, d
is a random walk. The env's LESO lags the friction's mode, so its estimates are not used.

Its rows on the protocol are in docs/nmpc (``docs/nmpc/run.sh``, docs/model.md section 15).

The problem (multiple shooting, N intervals of ``sample_period``, x_0 the measured angle and the
observer's velocity):

    min  sum_{k=1..N} |q_k - q_d,k|^2_Q + |qd_k - qd_d,k|^2_Qd
         + sum_{k<N} (r |u_k|^2 + r_d |u_k - u_k-1|^2 + rho 1^T s_k)      (u_-1: the torque applied last)
    s.t. x_{k+1} = RK4(x_k, u_k),   |u_k| <= u_max,   s_k >= 0,
         -(1 - beta) k_b,k+1 - s_k <= q_k+1 - q_d,k+1 <= (1 - beta) k_a,k+1 + s_k

with beta the ``backoff``, r the ``u_weight``, r_d the ``du_weight`` and rho the ``penalty``.

The output constraints are soft with an exact (L1) penalty, so the problem is always feasible;
every violation is still counted by the benchmark. The objective is quadratic in the unknowns, so
its Hessian is constant and serves as the Gauss-Newton Hessian (the dynamics' curvature is left
out). By default each sample takes one **real-time iteration** (``scheme="rti"``): from the previous
solution shifted by one interval (primal and dual), the dynamics and constraints are linearised
once and one QP in the step is solved (HPIPM, through CasADi), whose full step is the new plan. The
``"ipopt"`` scheme instead solves each sample's problem to convergence with IPOPT from the same
warm start. The problem's functions are compiled to C once and kept in blf-gym's cache folder
(:func:`blf_gym.results.io.cache_dir`, ``nmpc/``), so later processes load them in a fraction of a second.

A solve whose solver (the QP's, or IPOPT) does not report success is a **failure**: the policy
then applies the next torque of its last successful plan while that plan lasts, and otherwise a
computed-torque law on the same model (``fallback_kp``, ``fallback_kd``); both are counted
(:meth:`NMPCPolicy.report`). With ``retry_every`` > 1, while the computed-torque law acts a solve
is tried only every ``retry_every`` samples, so an arm the model has lost costs less. An estimator
whose state is no longer finite, or whose covariance has become singular (an arm that spun far
from its model), starts again at the measured angle, and that restart is counted too.
"""

from __future__ import annotations

import hashlib
import math
import multiprocessing
import os
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from blf_gym.envs.observation import (
    PREVIEW_EXTRAS,
    PREVIEW_POINTS,
    PREVIEW_STEP,
    SQUASH_REF_ACCELERATION,
    SQUASH_VELOCITY,
    observation_index,
    unsquash,
)
from blf_gym.jit import sources
from blf_gym.results.io import cache_dir
from blf_gym.model.params import ArmParams, FrictionParams

__all__ = ["NMPCParams", "casadi_dynamics", "NMPC", "NMPCPolicy", "nmpc"]


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
    """Intervals in the horizon (>= 1); it covers horizon x sample_period s, at most the 0.3 s
    of the observation's preview."""
    sample_period: float = field(default=0.01, metadata={"unit": "s"})
    """Period at which the problem is solved and its first torque held; the env's control_period."""
    q_weight: float = field(default=1e4, metadata={"unit": "1/rad^2"})
    """Weight of the squared angle error."""
    qd_weight: float = field(default=10.0, metadata={"unit": "s^2/rad^2"})
    """Weight of the squared velocity error."""
    u_weight: float = field(default=1e-4, metadata={"unit": "1/(N m)^2"})
    """Weight of the squared torque."""
    du_weight: float = field(default=1e-2, metadata={"unit": "1/(N m)^2"})
    """Weight of the squared torque change between intervals (the first from the torque applied
    last): it keeps the loop through the observer's lag from ringing."""
    penalty: float = field(default=1e5, metadata={"unit": "1/rad"})
    """Exact-penalty weight of the output constraints' slack."""
    backoff: float = field(default=0.02, metadata={"unit": "-"})
    """Share of the bounds the constraints keep free (in [0, 1)): the constraints hold at the
    nodes, the benchmark counts every 1 ms sample in between, and the angle is measured."""
    scheme: str = field(default="rti", metadata={"unit": "-"})
    """How each sample's problem is solved. ``"rti"`` (the default), the real-time iteration: one
    full Gauss-Newton SQP step per sample from the previous sample's solution shifted by one
    interval, the dynamics and constraints linearised there and the QP solved by ``qp_solver``, so
    the work per sample is one Jacobian and one warm-started QP. ``"ipopt"``: IPOPT to convergence,
    at most ``max_iter`` iterations (the scheme of the first protocol run, docs/nmpc/ipopt)."""
    qp_solver: str = field(default="hpipm", metadata={"unit": "-"})
    """The ``"rti"`` scheme's QP solver, a CasADi conic plug-in. ``"hpipm"`` (the default), HPIPM's
    interior point (Frison and Diehl, 2020), which exploits the problem's stage structure by a
    Riccati recursion (``_QP_OPTIONS`` in this module holds its tolerances). The others take the
    same QP without that structure and were slower or failed here (docs/model.md section 15)."""
    regularization: float = field(default=1e-6, metadata={"unit": "-"})
    """Added to the diagonal of the ``"rti"`` scheme's QP Hessian (in the objective's units per
    unknown squared): a Levenberg-Marquardt term that makes the QP strictly convex without moving
    the point the iterations converge to."""
    max_iter: int = field(default=50, metadata={"unit": "-"})
    """IPOPT's iteration limit per sample (the ``"ipopt"`` scheme); a solve that reaches it is a
    failure. A limit of 15 (on six training-suite episodes every converged solve but one took at
    most 8 iterations) cut the protocol run's CPU time by a quarter but lost the arm at the force's
    onset on the 0.1 Hz preset and in the training suite, where converging solves need more
    iterations (docs/model.md section 15), so the limit stays at 50."""
    retry_every: int = field(default=1, metadata={"unit": "-"})
    """While the computed-torque fallback acts (a solve failed and no successful plan is left), the
    problem is solved again only every ``retry_every`` samples (1, the default: at every sample, as
    in the documented protocol rows); the samples in between keep the fallback without a solve. A
    larger value bounds the cost of an arm the model has lost (10 in the run of docs/nmpc/max_iter15)."""
    fallback_kp: float = field(default=400.0, metadata={"unit": "1/s^2"})
    """Proportional gain of the computed-torque fallback."""
    fallback_kd: float = field(default=40.0, metadata={"unit": "1/s"})
    """Derivative gain of the computed-torque fallback."""
    substeps: int = field(default=10, metadata={"unit": "-"})
    """RK4 steps per interval. The friction makes the light third link stiff: near zero velocity
    M^-1 (b + c psi) is a mode of about 2,500 1/s, so RK4 needs steps of at most about 1.1 ms."""
    measurement_std: float = field(default=1e-4, metadata={"unit": "rad"})
    """Standard deviation of the angle measurement the estimator assumes (> 0)."""
    velocity_noise: float = field(default=0.05, metadata={"unit": "rad/s"})
    """Estimator's process noise on each velocity per sample: the model's error over one sample."""
    disturbance_noise: float = field(default=20.0, metadata={"unit": "rad/s^2"})
    """Estimator's random walk of each held disturbance per sample: how fast it may change."""
    nominal: ArmParams = field(default_factory=ArmParams)
    friction: FrictionParams = field(default_factory=FrictionParams)
    """The model's joint friction, b qd + c tanh(psi qd): the paper's nominal values by default
    (the suites perturb the plant's). None of it (zero coefficients) leaves the prediction wrong
    by about 0.5 rad on the third link within 100 ms of small torques (``tests/test_mpc.py``)."""

    def __post_init__(self) -> None:
        o = "NMPCParams"
        for name in ("horizon", "max_iter", "retry_every", "substeps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{o}.{name} must be an integer >= 1, got {v!r}")
        for name in ("sample_period", "q_weight", "qd_weight", "u_weight", "du_weight", "penalty", "fallback_kp",
                     "fallback_kd", "regularization", "measurement_std", "velocity_noise", "disturbance_noise"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{o}.{name} must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("sample_period", "measurement_std"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{o}.{name} must be > 0, got {getattr(self, name)!r}")
        if self.scheme not in ("ipopt", "rti"):
            raise ValueError(f"{o}.scheme must be 'ipopt' or 'rti', got {self.scheme!r}")
        if not isinstance(self.qp_solver, str) or not self.qp_solver:
            raise ValueError(f"{o}.qp_solver must be the name of a CasADi conic plug-in, got {self.qp_solver!r}")
        b = self.backoff
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not 0 <= b < 1:
            raise ValueError(f"{o}.backoff must be a number in [0, 1), got {b!r}")
        object.__setattr__(self, "backoff", float(b))
        span = PREVIEW_POINTS * PREVIEW_STEP
        if self.horizon * self.sample_period > span + 1e-12:
            raise ValueError(f"{o}: horizon x sample_period = {self.horizon * self.sample_period:g} s must be at "
                             f"most the observation's preview, {span:g} s")


def casadi_dynamics(arm: ArmParams = ArmParams(), friction: FrictionParams | None = None) -> Any:
    """A CasADi Function ``f(x, u, d) -> xdot`` of the nominal arm, x = [q, qd] (2n), u and d (n):
    qdd = M^-1 (u - c(q, qd) - G(q) - F(qd)) + d, F the joint friction (none if None; see the
    module docstring)."""
    ca = _casadi()
    n = arm.n_links
    q = ca.SX.sym("q", n)
    qd = ca.SX.sym("qd", n)
    u = ca.SX.sym("u", n)
    d = ca.SX.sym("d", n)
    M, c, G = _lagrangian_terms(ca, arm, q, qd)
    qdd = ca.solve(M, u - c - G - _friction(ca, friction, qd)) + d
    return ca.Function("f", [ca.vertcat(q, qd), u, d], [ca.vertcat(qd, qdd)], ["x", "u", "d"], ["xdot"])


def _lagrangian_terms(ca: Any, arm: ArmParams, q: Any, qd: Any) -> tuple[Any, Any, Any]:
    """M(q), c(q, qd) and G(q) of the point-mass arm, from its kinetic and potential energy."""
    n = arm.n_links
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
    return M, c, ca.gradient(V, q)


def _friction(ca: Any, friction: FrictionParams | None, qd: Any) -> Any:
    """b qd + c tanh(psi qd) per joint (paper eq. 2), or zero."""
    if friction is None:
        return ca.SX.zeros(qd.shape[0])
    return friction.viscous * qd + friction.coulomb * ca.tanh(friction.tanh_slope * qd)


_QP_OPTIONS: dict[str, dict[str, Any]] = {
    # HPIPM's interior point: its residual tolerances are absolute, and this problem's gradient is of
    # order 1e5 (the penalty), so stationarity is asked to 1e-3 (1e-8 relative) and the rest to 1e-6;
    # CasADi gives every unbounded unknown the box +-inf, here +-1e3 (of a step in rad, rad/s or N m)
    "hpipm": {"inf": 1e3, "hpipm": {"mode": "robust", "iter_max": 100, "res_g_max": 1e-3, "res_b_max": 1e-6,
                                    "res_d_max": 1e-6, "res_m_max": 1e-6}},
    "qrqp": {"print_iter": False, "print_header": False, "print_info": False},
    "osqp": {"osqp": {"verbose": False}},
    "qpoases": {"printLevel": "none"},
}
"""The ``"rti"`` scheme's options for a QP plug-in: HPIPM's tolerances, the others' silence."""


class NMPC:
    """The optimal control problem of the module docstring, one compiled CasADi Function shared by
    every arm; each arm's warm start is a value the caller keeps (:meth:`solve`)."""

    def __init__(self, params: NMPCParams = NMPCParams(), u_max: float = 150.0, compiled: bool = True) -> None:
        ca = _casadi()
        self.params = p = params
        n = p.nominal.n_links
        self.n, self.N, self.u_max = n, p.horizon, float(u_max)
        if p.scheme == "rti" and not ca.has_conic(p.qp_solver):
            raise ValueError(f"NMPCParams.qp_solver: {p.qp_solver!r} is not a QP plug-in of this CasADi build "
                             "(e.g. 'hpipm', 'qrqp', 'osqp', 'qpoases')")
        if not (math.isfinite(self.u_max) and self.u_max > 0):
            raise ValueError(f"NMPC.u_max must be a positive number of N m, got {u_max!r}")
        f = casadi_dynamics(p.nominal, p.friction)
        h = p.sample_period / p.substeps
        x, u, d = ca.SX.sym("x", 2 * n), ca.SX.sym("u", n), ca.SX.sym("d", n)
        k1 = f(x, u, d)
        k2 = f(x + h / 2 * k1, u, d)
        k3 = f(x + h / 2 * k2, u, d)
        k4 = f(x + h * k3, u, d)
        rk4 = ca.Function("rk4", [x, u, d], [x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
        if p.substeps == 1:
            self.step = rk4
        else:
            # one RK4 step repeated: the generated code holds it (and its derivatives) once
            xm, um, dm = ca.MX.sym("x", 2 * n), ca.MX.sym("u", n), ca.MX.sym("d", n)
            xe = xm
            for _ in range(p.substeps):
                xe = rk4(xe, um, dm)
            self.step = ca.Function("step", [xm, um, dm], [xe])
        xm, um, dm = ca.MX.sym("x", 2 * n), ca.MX.sym("u", n), ca.MX.sym("d", n)
        xe = self.step(xm, um, dm)
        # the estimator's prediction and its Jacobian in (x, d)
        self.predict_jac = ca.Function("predict_jac", [xm, um, dm], [xe, ca.jacobian(xe, ca.vertcat(xm, dm))])
        q, qd, acc = ca.SX.sym("q", n), ca.SX.sym("qd", n), ca.SX.sym("a", n)
        M, c, G = _lagrangian_terms(ca, p.nominal, q, qd)
        F = _friction(ca, p.friction, qd)
        # the computed torque that gives acceleration acc on the model
        self.inverse = ca.Function("inverse", [q, qd, acc], [M @ acc + c + G + F])
        self._nlam = 0
        self._compiled = compiled
        self._fn: Any = None

    @property
    def _solver(self) -> Any:
        """The solver Function, built or loaded at the first solve (:meth:`_load_or_build`)."""
        if self._fn is None:
            self._fn = self._load_or_build(_casadi(), self._compiled)
        return self._fn

    def _key(self, compiled: bool) -> str:
        ca = _casadi()
        src = sources.digest(__name__).encode()  # this module's import closure, not only its file
        text = repr((asdict(self.params), self.u_max, compiled, ca.__version__)).encode()
        return hashlib.sha256(src + text).hexdigest()[:20]

    def _load_or_build(self, ca: Any, compiled: bool) -> Any:
        """The solver Function: loaded from the cache when this code, these parameters and this
        CasADi built it before; otherwise built (with C code generation when ``compiled`` and a C
        compiler is on the PATH: about 10-20 s once, then several times faster per solve) and saved."""
        import shutil

        compiled = compiled and (shutil.which("gcc") or shutil.which("cc")) is not None
        path = cache_dir() / "nmpc" / f"{self._key(compiled)}.casadi"
        fn = None
        if path.is_file():
            try:
                fn = ca.Function.load(str(path))
            except Exception:  # noqa: BLE001 (a damaged cache file is rebuilt)
                fn = None
        if fn is None and not compiled:
            fn = self._build(ca, None, part=True)
        elif fn is None:
            # CasADi's compiler works in the folder it is told (a scratch folder, gone once the
            # function is saved with its binary embedded), but writes the generated C under the working
            # folder by its jit name: a name of our own, removed after the build (they once piled up in
            # a repository)
            name = f"blf_nmpc_jit_{os.getpid()}_{path.stem}"
            with tempfile.TemporaryDirectory(prefix="blf-nmpc-jit-") as scratch:
                try:
                    built = self._build(ca, (scratch, name), part=True)
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
                    built.save(str(tmp))
                    os.replace(tmp, path)
                finally:
                    Path(f"{name}.c").unlink(missing_ok=True)
            fn = ca.Function.load(str(path))  # the saved binary, not the scratch folder's
        if self.params.scheme == "rti":
            return self._build(ca, None, lin=fn)  # the QP solver around the cached linearisation
        self._nlam = int(fn.size1_in(10))  # the multipliers' input
        return fn

    def _layout(self) -> tuple[int, int, int]:
        """(stage state size, stage control size, unknowns) of the stage-wise problem (:meth:`_build`)."""
        n, N = self.n, self.N
        nz, nv = 4 * n, 2 * n
        return nz, nv, (N + 1) * nz + N * nv

    def _build(self, ca: Any, jit: tuple[str, str] | None, part: bool = False, lin: Any = None) -> Any:
        """The solver Function; ``jit`` (scratch folder, name) compiles its C there (None: not compiled).
        ``part``: only the part that is compiled and cached, for ``"rti"`` the linearisation (the QP
        solvers cannot all be saved), for ``"ipopt"`` the whole solver; ``lin``: that linearisation,
        loaded, for ``"rti"``.

        The problem is written stage by stage, as structure-exploiting QP solvers (HPIPM) need it:
        the unknowns are w = [z_0, v_0, z_1, v_1, ..., z_N], with the stage state
        z_k = [x_k, sigma_k, u_prev,k] (the arm's state, the slack of node k, the torque of the stage
        before) and the stage control v_k = [u_k, s_k] (the torque and the slack of node k+1), so that
        z_k+1 = [RK4(x_k, u_k), s_k, u_k] and every cost term and constraint involves one stage only.
        The constraints are ordered [gap_0, init_0, gap_1, out_1, ..., gap_N-1, out_N-1, out_N]: the
        gaps z_k+1 - f(z_k, v_k) = 0, the initial stage z_0 = [x0, 0, u_last], and each node's two
        soft output constraints."""
        p, n, N = self.params, self.n, self.N
        pr = self._problem(ca)
        w, P, f, g, ng, nw, nx = pr.w, pr.P, pr.f, pr.g, pr.ng, pr.nw, 2 * n
        lbw, ubw, lbg, ubg = pr.bounds
        opts = {} if jit is None else {
            "jit": True, "compiler": "shell", "jit_serialize": "embed", "jit_name": jit[1], "jit_temp_suffix": False,
            "jit_cleanup": False,
            "jit_options": {"flags": ["-O3"], "verbose": False, "directory": os.path.join(jit[0], "")}}
        self._nlam = ng + nw
        X0, U0, S0 = ca.MX.sym("X0", nx, N + 1), ca.MX.sym("U0", n, N), ca.MX.sym("S0", n, N)
        L0 = ca.MX.sym("L0", self._nlam)
        # the warm start's stages from its trajectory: sigma_k = s_k-1 (0 at the first node), u_prev,k = u_k-1
        Z0 = ca.vertcat(X0, ca.horzcat(ca.DM.zeros(n), S0), ca.horzcat(pr.ulast, U0))
        w0 = ca.vertcat(ca.vec(ca.vertcat(Z0[:, :N], U0, S0)), Z0[:, N])
        if p.scheme == "rti":
            # the real-time iteration: one full Gauss-Newton step from the shifted solution w0, the QP
            # in the step dw with the constraints linearised at w0 (one Jacobian, one QP per sample)
            if lin is None:
                lin = ca.Function("nmpc_lin", [w, P], [g, ca.jacobian(g, w), ca.gradient(f, w)], opts)
            if part:
                return lin
            ws, sol = self._rti_step(ca, pr, lin, w0, L0)
        else:
            # IPOPT from the shifted solution, multipliers included, with a small barrier parameter
            solver = ca.nlpsol("nmpc_nlp", "ipopt", {"x": w, "p": P, "f": f, "g": g},
                               {"print_time": False, **opts, "hess_lag": pr.hess_lag, "ipopt.print_level": 0,
                                "ipopt.sb": "yes", "ipopt.max_iter": p.max_iter,
                                "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-4,
                                "ipopt.warm_start_bound_push": 1e-6, "ipopt.warm_start_mult_bound_push": 1e-6})
            sol = solver(x0=w0, p=P, lbx=lbw, ubx=ubw, lbg=lbg, ubg=ubg, lam_g0=L0[:ng], lam_x0=L0[ng:])
            ws = sol["x"]
        stride = pr.stride
        st = ca.reshape(ws[: N * stride], stride, N)
        nz = pr.nz
        res = [ca.horzcat(st[:nx, :], ws[N * stride:N * stride + nx]), st[nz:nz + n, :], st[nz + n:, :],
               ca.vertcat(sol["lam_g"], sol["lam_x"])]
        return ca.Function("nmpc", [*pr.pars, X0, U0, S0, L0], res,
                           ["x0", "d", "qref", "qdref", "ka", "kb", "u_last", "X0", "U0", "S0", "L0"],
                           ["X", "U", "S", "L"])

    def _rti_step(self, ca: Any, pr: SimpleNamespace, lin: Any, w0: Any, L0: Any) -> tuple[Any, dict[str, Any]]:
        """The real-time iteration's QP from the shifted solution ``w0``: (the new unknowns, their
        multipliers ``lam_g`` and ``lam_x``)."""
        p, n, N = self.params, self.n, self.N
        nz, nv, nw, ng = pr.nz, pr.nv, pr.nw, pr.ng
        lbw, ubw, lbg, ubg = pr.bounds
        g0, J0, grad0 = lin(w0, pr.P)
        # the step's metric is regularised (Levenberg-Marquardt): the slacks and the first node have
        # no quadratic cost; a fixed point (zero step) is still a KKT point of the problem itself
        h_qp = pr.hess + p.regularization * ca.DM.eye(nw)
        qp_opts: dict[str, Any] = {"error_on_fail": False, **_QP_OPTIONS.get(p.qp_solver, {})}
        if p.qp_solver == "hpipm":  # the stage structure, as laid out in _build
            qp_opts.update(N=N, nx=[nz] * (N + 1), nu=[nv] * N + [0], ng=[nz] + [2 * n] * N)
        qp = ca.conic("nmpc_qp", p.qp_solver, {"h": h_qp.sparsity(), "a": J0.sparsity()}, qp_opts)
        sol = qp(h=h_qp, g=grad0, a=J0, lba=lbg - g0, uba=ubg - g0, lbx=lbw - w0, ubx=ubw - w0,
                 lam_a0=L0[:ng], lam_x0=L0[ng:])
        return w0 + sol["x"], {"lam_g": sol["lam_a"], "lam_x": sol["lam_x"]}

    def _problem(self, ca: Any) -> SimpleNamespace:
        """The stage-wise problem of :meth:`_build` in CasADi symbols: the unknowns ``w``, the
        parameters (``pars``, stacked in ``P``), the cost ``f``, the constraints ``g`` and their
        bounds, the Gauss-Newton Hessian and its Lagrangian function for IPOPT."""
        p, n, N = self.params, self.n, self.N
        nx = 2 * n
        nz, nv, nw = self._layout()
        stride = nz + nv
        w = ca.MX.sym("w", nw)
        stages = ca.reshape(w[: N * stride], stride, N)
        Z = ca.horzcat(stages[:nz, :], w[N * stride:])  # z_0 .. z_N
        V = stages[nz:, :]
        X, Sig, Uprev = Z[:nx, :], Z[nx:nx + n, :], Z[nx + n:, :]
        U, S = V[:n, :], V[n:, :]
        x0, dh, ulast = ca.MX.sym("x0", nx), ca.MX.sym("d", n), ca.MX.sym("u_last", n)
        qref, qdref = ca.MX.sym("qref", n, N + 1), ca.MX.sym("qdref", n, N + 1)
        ka, kb = ca.MX.sym("ka", 1, N + 1), ca.MX.sym("kb", 1, N + 1)
        pars = [x0, dh, qref, qdref, ka, kb, ulast]
        P = ca.vertcat(*[ca.vec(a) for a in pars])
        E = X[:n, 1:] - qref[:, 1:]
        Ed = X[n:, 1:] - qdref[:, 1:]
        f = (p.q_weight * ca.sumsqr(E) + p.qd_weight * ca.sumsqr(Ed) + p.u_weight * ca.sumsqr(U)
             + p.du_weight * ca.sumsqr(U - Uprev[:, :N]) + p.penalty * ca.sum1(ca.sum2(Sig[:, 1:])))
        keep = 1.0 - p.backoff
        # the horizon's steps as one mapped call: the generated code holds one step and its derivatives
        gaps = Z[:, 1:] - ca.vertcat(self.step.map(N)(X[:, :N], U, ca.repmat(dh, 1, N)), S, U)
        out = ca.vertcat(E - Sig[:, 1:] - ca.repmat(keep * ka[:, 1:], n, 1),
                         -E - Sig[:, 1:] - ca.repmat(keep * kb[:, 1:], n, 1))  # node k's in column k-1
        init = Z[:, 0] - ca.vertcat(x0, ca.DM.zeros(n), ulast)
        g = ca.vertcat(gaps[:, 0], init, ca.vec(ca.vertcat(gaps[:, 1:], out[:, : N - 1])), out[:, N - 1])
        eq = np.concatenate([np.ones(2 * nz), np.tile(np.r_[np.ones(nz), np.zeros(2 * n)], N - 1), np.zeros(2 * n)])
        ng = int(g.shape[0])
        # Gauss-Newton: the objective is quadratic in w, so its Hessian is constant; the dynamics'
        # curvature is left out (the exact Hessian through the substeps was 70 % of a solve)
        hess = ca.DM(ca.Function("h", [w], [ca.hessian(f, w)[0]])(ca.DM.zeros(nw)))
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", ng)
        hess_lag = ca.Function("hess_lag", [w, P, lam_f, lam_g], [lam_f * ca.triu(hess)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        inf = np.inf
        lo_v, hi_v = np.r_[np.full(n, -self.u_max), np.zeros(n)], np.r_[np.full(n, self.u_max), np.full(n, inf)]
        lbw = np.r_[np.tile(np.r_[np.full(nz, -inf), lo_v], N), np.full(nz, -inf)]
        ubw = np.r_[np.tile(np.r_[np.full(nz, inf), hi_v], N), np.full(nz, inf)]
        bounds = (lbw, ubw, np.where(eq == 1, 0.0, -inf), np.zeros(ng))
        return SimpleNamespace(w=w, P=P, pars=pars, ulast=ulast, f=f, g=g, ng=ng, nw=nw, nz=nz, nv=nv,
                               stride=stride, hess=hess, hess_lag=hess_lag, bounds=bounds)

    def _shift_multipliers(self, lam: np.ndarray) -> np.ndarray:
        """The multipliers ``[lam_g, lam_x]`` of a solution moved one interval on, as its primal
        values are: each stage's block takes the next stage's and the last is repeated (the initial
        stage's constraint keeps its own), so a warm-started QP or IPOPT starts from the right guess."""
        n, N = self.n, self.N
        nz, nv, nw = self._layout()
        lam = np.asarray(lam, dtype=float).ravel()
        ng = lam.size - nw
        # lam_g = [gap_0, init_0, (gap_k, out_k) for k = 1..N-1, out_N]; lam_x = [(z_k, v_k) for k < N, z_N]
        gap0, init = lam[:nz], lam[nz:2 * nz]
        mid = lam[2 * nz: ng - 2 * n].reshape(N - 1, nz + 2 * n)
        outN = lam[ng - 2 * n: ng]
        gaps = np.vstack([gap0[None], mid[:, :nz]])  # gap_0 .. gap_N-1
        outs = np.vstack([mid[:, nz:], outN[None]])  # out_1 .. out_N
        gaps = np.vstack([gaps[1:], gaps[-1:]])
        outs = np.vstack([outs[1:], outs[-1:]])
        lam_g = np.concatenate([gaps[0], init, np.hstack([gaps[1:], outs[:-1]]).ravel(), outs[-1]])
        lx = lam[ng:]
        stages = lx[: N * (nz + nv)].reshape(N, nz + nv)
        zN = lx[N * (nz + nv):]
        stages = np.vstack([stages[1:], np.r_[zN, stages[-1, nz:]][None]])
        return np.concatenate([lam_g, stages.ravel(), stages[-1, :nz]])

    def predict_states(self, x0: np.ndarray, torques: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
        """The model's states after each of ``torques`` (k, n), each held one sample period, from x0."""
        d = np.zeros(self.n) if d is None else d
        out, x = [], np.asarray(x0, dtype=float)
        for u in np.atleast_2d(torques):
            x = np.asarray(self.step(x, u, d)).ravel()
            out.append(x)
        return np.array(out)

    def solve(self, x0, d_hat, q_ref, qd_ref, k_a, k_b, u_last=None,
              warm: Any = None) -> tuple[np.ndarray, dict[str, Any], Any]:
        """``(plan, facts, warm)``: the optimal torques (n, N), the solver's facts (``success``,
        ``iterations``, ``slack``: the largest slack in rad, ``status``) and the warm start of the
        next sample (give it back as ``warm``; None starts cold). ``q_ref``, ``qd_ref`` (n, N+1)
        and ``k_a``, ``k_b`` (N+1) cover the horizon's nodes, the current one first; ``u_last`` is
        the torque applied over the last sample (None: zero)."""
        u_last = np.zeros(self.n) if u_last is None else u_last
        if warm is not None:
            Xg, Ug, Sg, Lg = warm
            X0 = np.hstack([Xg[:, 1:], Xg[:, -1:]])
            U0 = np.hstack([Ug[:, 1:], Ug[:, -1:]])
            S0 = np.hstack([Sg[:, 1:], Sg[:, -1:]])
            L0 = self._shift_multipliers(Lg)
        else:
            X0 = np.repeat(np.reshape(x0, (-1, 1)), self.N + 1, axis=1)
            U0 = np.zeros((self.n, self.N))
            S0 = np.zeros((self.n, self.N))
            L0 = np.zeros(self._nlam)
        try:
            X, U, S, L = self._solver(x0, d_hat, q_ref, qd_ref, np.reshape(k_a, (1, -1)), np.reshape(k_b, (1, -1)),
                                      u_last, X0, U0, S0, L0)
        except RuntimeError:  # the solver refused its data (e.g. a non-finite state): a failure like any other
            return np.full((self.n, self.N), np.nan), {"success": False, "iterations": 0, "slack": float("nan"),
                                                      "status": SOLVER_ERROR}, None
        stats = self._solver.stats()
        X, U, S, L = np.asarray(X), np.asarray(U), np.asarray(S), np.asarray(L)
        ok = bool(stats.get("success", False)) and bool(np.all(np.isfinite(U)))
        status = stats.get("return_status", "")
        if not isinstance(status, str):  # a QP plug-in's numeric code: CasADi's name for it first
            status = f"{stats.get('unified_return_status', 'SOLVER_RET_UNKNOWN')} ({self.params.qp_solver} {status})"
        facts = {"success": ok, "iterations": int(stats.get("iter_count", -1)),
                 "slack": float(np.max(S)) if S.size else 0.0, "status": status}
        return U, facts, ((X, U, S, L) if ok else None)


class _Arm:
    """One arm's memory between samples: the estimator's state z = [q, qd, d] and covariance, the
    warm start, the last converged plan and its age."""

    __slots__ = ("z", "cov", "warm", "plan", "age", "wait")

    def __init__(self) -> None:
        self.z: np.ndarray | None = None
        self.cov: np.ndarray | None = None
        self.warm: Any = None
        self.plan: np.ndarray | None = None
        self.age = 0
        self.wait = 0
        """Samples left before the next solve while the computed-torque fallback acts."""


SOLVER_ERROR = "Solver_Error"
"""The status of a solve whose solver raised an error instead of returning (:meth:`NMPC.solve`)."""

SKIPPED = "Skipped_In_Fallback"
"""The status of a sample on which no solve ran (:attr:`NMPCParams.retry_every`)."""


def _estimate(nmpc: NMPC, arm: _Arm, y: np.ndarray, u_last: np.ndarray) -> np.ndarray:
    """The extended Kalman filter of the module docstring: the arm's z = [q, qd, d] after the
    measured angle ``y``, ``u_last`` having been held over the last sample."""
    n, p = nmpc.n, nmpc.params
    r = p.measurement_std ** 2
    if arm.z is None:  # the first sample: at the measured angle, velocity and disturbance unknown
        arm.z = np.concatenate([y, np.zeros(2 * n)])
        arm.cov = np.diag(np.concatenate([np.full(n, r), np.full(n, 1.0), np.full(n, 100.0 ** 2)]))
        return arm.z
    xe, J = nmpc.predict_jac(arm.z[: 2 * n], u_last, arm.z[2 * n:])
    F = np.eye(3 * n)
    F[: 2 * n] = np.asarray(J)
    q = np.concatenate([np.zeros(n), np.full(n, p.velocity_noise ** 2), np.full(n, p.disturbance_noise ** 2)])
    z = np.concatenate([np.asarray(xe).ravel(), arm.z[2 * n:]])
    cov = F @ arm.cov @ F.T + np.diag(q)
    gain = np.linalg.solve(cov[:n, :n] + r * np.eye(n), cov[:n, :]).T
    arm.z = z + gain @ (y - z[:n])
    arm.cov = cov - gain @ cov[:n, :]
    arm.cov = 0.5 * (arm.cov + arm.cov.T)
    return arm.z


def _act(nmpc: NMPC, arm: _Arm, y, qref, qdref, ka, kb, u_last,
         qdd_now) -> tuple[np.ndarray, float, bool, str, bool]:
    """One sample of one arm: (torque, solve time in s, whether the fallback acted, the solver's status,
    whether the estimator was restarted because its state or covariance was no longer usable)."""
    t0 = time.perf_counter()
    try:
        z = _estimate(nmpc, arm, y, u_last)
    except np.linalg.LinAlgError:  # a covariance gone singular: the same as a state no longer finite
        z = np.full(3 * nmpc.n, np.nan)
    restarted = not np.all(np.isfinite(z))
    if restarted:  # the filter diverged (an arm spun far from its model): start it afresh at y
        arm.z, arm.cov, arm.warm, arm.plan, arm.wait = None, None, None, None, 0
        z = _estimate(nmpc, arm, y, u_last)
    x0, d = z[: 2 * nmpc.n], z[2 * nmpc.n:]
    if arm.wait > 0:  # the fallback acts and the next solve is not due yet
        arm.wait -= 1
        return _computed_torque(nmpc, x0, d, qref, qdref, qdd_now), time.perf_counter() - t0, True, SKIPPED, restarted
    plan, facts, warm = nmpc.solve(x0, d, qref, qdref, ka, kb, u_last, arm.warm)
    if facts["success"]:
        arm.warm, arm.plan, arm.age = warm, plan, 0
        return plan[:, 0].copy(), time.perf_counter() - t0, False, facts["status"], restarted
    arm.age += 1
    if arm.plan is not None and arm.age < arm.plan.shape[1]:
        u = arm.plan[:, arm.age].copy()  # the last converged plan, one more interval on
    else:
        u = _computed_torque(nmpc, x0, d, qref, qdref, qdd_now)
        arm.warm = None
        arm.wait = nmpc.params.retry_every - 1
    return u, time.perf_counter() - t0, True, facts["status"], restarted


def _computed_torque(nmpc: NMPC, x0: np.ndarray, d: np.ndarray, qref: np.ndarray, qdref: np.ndarray,
                     qdd_now: np.ndarray) -> np.ndarray:
    """The fallback's computed-torque law on the model, at the estimated state x0 and disturbance d."""
    n, p = nmpc.n, nmpc.params
    q, qd = x0[:n], x0[n:]
    a = qdd_now - d + p.fallback_kp * (qref[:, 0] - q) + p.fallback_kd * (qdref[:, 0] - qd)
    return np.clip(np.asarray(nmpc.inverse(q, qd, a)).ravel(), -nmpc.u_max, nmpc.u_max)


def _worker(conn: Any, params: NMPCParams, u_max: float, compiled: bool) -> None:
    """A solving process: owns some arms, answers each batch of their samples."""
    nmpc = NMPC(params, u_max, compiled)
    arms: dict[int, _Arm] = {}
    conn.send("ready")
    while True:
        msg = conn.recv()
        if msg is None:
            return
        out = []
        for i, start, args in msg:
            if start or i not in arms:
                arms[i] = _Arm()
            out.append(_act(nmpc, arms[i], *args))
        conn.send(out)


class NMPCPolicy:
    """The NMPC as an SB3-style policy for the plain env: ``predict(obs, state, episode_start,
    deterministic)`` gives actions in [-1, 1] (torque over max_torque), as a trained agent's.

    It reads the measured angle y, the torque applied over the last sample, and the preview of the
    reference and the bounds (the observation extras :data:`blf_gym.envs.observation.PREVIEW_EXTRAS`), so
    it acts in ``gym.make("PlanarBLF-v0", **policy.env_kwargs)``. Each row of a batch is an arm with
    its own warm start; an observation at t = 0 (or ``episode_start``) starts that arm afresh.

    ``workers``: processes that solve the arms of a batch in parallel (each loads the compiled
    solver from the cache); None uses two when a batch has several arms and two cores are free to
    this process, else 0 (solve in this process). ``compiled`` False skips the C code generation
    (no compiler run, about three times slower per solve)."""

    whole_batch = True
    """blf-eval calls it once per step with every arm (it keeps per-arm state)."""

    def __init__(self, params: NMPCParams | None = None, max_torque: float = 150.0, workers: int | None = None,
                 env: Any = None, compiled: bool = True) -> None:
        self.params = params or NMPCParams()
        self.max_torque = float(max_torque)
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
            raise ValueError(f"NMPCPolicy.workers must be None or an integer >= 0, got {workers!r}")
        self.workers = workers
        self.nmpc = NMPC(self.params, self.max_torque, compiled)
        self.compiled = compiled
        self.name = "nmpc"
        self.env_kwargs: dict[str, Any] = {"controller": "none", "control_period": self.params.sample_period,
                                           "observation_extras": list(PREVIEW_EXTRAS)}
        self._index = observation_index(self.nmpc.n, False, PREVIEW_EXTRAS)
        self._arms: dict[int, _Arm] = {}
        self._pool: list[Any] = []
        self._times: list[float] = []
        self._fallbacks = 0
        self._samples = 0
        self._restarts = 0
        self._statuses: dict[str, int] = {}
        if env is not None:
            self.check_env(env)

    def check_env(self, env: Any) -> None:
        """Refuse an env this policy cannot drive: residual mode, another control period or torque
        limit, or an observation without the preview; its layout is read from the env."""
        core = getattr(getattr(env, "unwrapped", env), "core", None)
        if core is None:
            raise ValueError(f"NMPCPolicy.check_env: {type(env).__name__} is not a PlanarBLF env")
        if core.residual:
            raise ValueError("NMPCPolicy drives the plain env (its action is the whole torque); make the env with "
                             "gym.make('PlanarBLF-v0', **policy.env_kwargs)")
        if not np.isclose(core.control_period, self.params.sample_period, rtol=1e-9, atol=0.0):
            raise ValueError(f"NMPCPolicy holds each torque for sample_period = {self.params.sample_period:g} s, but "
                             f"the env's control_period is {core.control_period:g} s")
        if not np.isclose(core.sim.max_torque, self.max_torque):
            raise ValueError(f"NMPCPolicy scales its torque by max_torque = {self.max_torque:g} N m, but the env's "
                             f"is {core.sim.max_torque:g} N m")
        missing = [g for g in PREVIEW_EXTRAS if g not in core.observation_extras]
        if missing:
            raise ValueError(f"NMPCPolicy reads the preview {missing} of the observation; make the env with "
                             "observation_extras including blf_gym.envs.observation.PREVIEW_EXTRAS (policy.env_kwargs)")
        self._index = observation_index(core.n, core.privileged, core.observation_extras)

    def _inputs(self, o: np.ndarray) -> tuple:
        """The problem's data from one observation row (float64)."""
        ix, n, p = self._index, self.nmpc.n, self.params
        o = o.astype(np.float64)
        y = o[ix["y"]]
        # the preview's times 0, PREVIEW_STEP, ... and the horizon's nodes 0, h, ..., N h
        tp = np.arange(PREVIEW_POINTS + 1) * PREVIEW_STEP
        tk = np.arange(p.horizon + 1) * p.sample_period
        q_all = np.vstack([o[ix["q_d"]], o[ix["q_d_preview"]].reshape(PREVIEW_POINTS, n)])
        qd_all = unsquash(np.vstack([o[ix["qd_d"]], o[ix["qd_d_preview"]].reshape(PREVIEW_POINTS, n)]),
                          SQUASH_VELOCITY)
        ka_all = np.concatenate([o[ix["k_a"]], o[ix["k_a_preview"]]])
        kb_all = np.concatenate([o[ix["k_b"]], o[ix["k_b_preview"]]])

        def at(v: np.ndarray) -> np.ndarray:
            return np.interp(tk, tp, v)  # exact at the preview's own times

        qref = np.array([at(q_all[:, j]) for j in range(n)])
        qdref = np.array([at(qd_all[:, j]) for j in range(n)])
        qdd_now = unsquash(o[ix["qdd_d"]], SQUASH_REF_ACCELERATION)
        u_last = o[ix["u"]] * self.max_torque
        return y, qref, qdref, at(ka_all), at(kb_all), u_last, qdd_now

    def _start_pool(self, count: int) -> None:
        ctx = multiprocessing.get_context("spawn")
        for _ in range(count):
            a, b = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(b, self.params, self.max_torque, self.compiled), daemon=True)
            proc.start()
            self._pool.append((proc, a))
        for _, conn in self._pool:
            if conn.recv() != "ready":  # pragma: no cover
                raise RuntimeError("an NMPC worker did not start")

    def _pool_size(self, rows: int) -> int:
        if self.workers is not None:
            return self.workers
        if rows < 2 or multiprocessing.current_process().daemon:
            return 0
        try:
            free = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover
            free = os.cpu_count() or 1
        return 2 if free >= 2 else 0

    def predict(self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        """SB3's PolicyPredictor interface: actions in [-1, 1] (torque / max_torque)."""
        obs = np.asarray(observation)
        single = obs.ndim == 1
        batch = obs[None] if single else obs
        width = max(s.stop for s in self._index.values())
        if batch.ndim != 2 or batch.shape[1] != width:
            raise ValueError(f"NMPCPolicy expects observations of {width} entries (the plain env with "
                             f"observation_extras={list(PREVIEW_EXTRAS)}), got shape {obs.shape}")
        if not np.all(np.isfinite(batch)):
            raise ValueError("NMPCPolicy: the observation holds NaN or inf")
        rows = batch.shape[0]
        starts = (np.zeros(rows, dtype=bool) if episode_start is None
                  else np.asarray(episode_start, dtype=bool).reshape(-1))
        starts = starts | (batch[:, self._index["time"].start] == 0.0)
        args = [self._inputs(batch[i]) for i in range(rows)]
        want = self._pool_size(rows)
        if want and not self._pool:
            self._start_pool(want)
        if self._pool:
            parts: list[list[tuple[int, bool, tuple]]] = [[] for _ in self._pool]
            for i in range(rows):
                parts[i % len(self._pool)].append((i, bool(starts[i]), args[i]))
            for (_, conn), part in zip(self._pool, parts):
                conn.send(part)
            results: list[Any] = [None] * rows
            for (_, conn), part in zip(self._pool, parts):
                for (i, _, _), r in zip(part, conn.recv()):
                    results[i] = r
        else:
            results = []
            for i in range(rows):
                if starts[i] or i not in self._arms:
                    self._arms[i] = _Arm()
                results.append(_act(self.nmpc, self._arms[i], *args[i]))
        u = np.empty((rows, self.nmpc.n))
        for i, (ui, wall, fell_back, status, restarted) in enumerate(results):
            u[i] = ui
            self._samples += 1
            if status != SKIPPED:
                self._times.append(wall)
            self._fallbacks += int(fell_back)
            self._restarts += int(restarted)
            self._statuses[status] = self._statuses.get(status, 0) + 1
        actions = np.clip(u / self.max_torque, -1.0, 1.0).astype(np.float32)
        return (actions[0] if single else actions), state

    def report(self) -> dict[str, Any]:
        """The samples so far and the solves among them (the others were skipped while the fallback
        acted, :attr:`NMPCParams.retry_every`); fallbacks (samples whose torque did not come from a
        converged solve), estimator restarts (its state was no longer finite, so it started again at
        the measured angle), the solver's statuses (``Skipped_In_Fallback`` for a sample without a solve),
        and the time of a sample with a solve in ms, the estimator included (median, 99th percentile,
        largest)."""
        t = np.array(self._times) * 1e3
        return {"samples": self._samples, "solves": int(t.size), "fallbacks": self._fallbacks,
                "estimator_restarts": self._restarts, "statuses": dict(self._statuses),
                "solve_ms_median": float(np.median(t)) if t.size else None,
                "solve_ms_p99": float(np.percentile(t, 99)) if t.size else None,
                "solve_ms_max": float(t.max()) if t.size else None,
                "horizon_s": self.params.horizon * self.params.sample_period,
                "sample_period_s": self.params.sample_period}

    def close(self) -> None:
        """End the solving processes."""
        for proc, conn in self._pool:
            try:
                conn.send(None)
            except (BrokenPipeError, OSError):
                pass
            proc.join(timeout=5)
        self._pool = []

    def __del__(self) -> None:  # pragma: no cover - best effort at interpreter exit
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass


def nmpc(**kwargs: Any) -> NMPCPolicy:
    """The ``nmpc`` entry point of ``blf_gym.policies``: :class:`NMPCPolicy` with NMPCParams fields,
    ``max_torque``, ``workers`` and ``compiled`` as keywords (unknown ones refused by name)."""
    from .params import params_from

    top = {k: kwargs.pop(k) for k in ("max_torque", "workers", "compiled") if k in kwargs}
    return NMPCPolicy(params_from(NMPCParams, kwargs, "NMPC parameter"), **top)
