"""The closed loop: plant + observer + inner controller, integrated by fixed-step ODE3.

One compiled kernel serves everything: the reproduction (one arm, a whole 30 s episode per call),
the Gymnasium env (one arm, one agent period per call) and the vector env (N arms per call, split
over threads: the compiled kernel releases the GIL). It is specialised per (controller law,
observer) pair by cloning the template functions below with the law and observer bound as
globals, then compiled by numba with ``cache=True`` so a warm start loads machine code from disk.

Integration (docs/model.md section 6): Bogacki-Shampine ODE3, fixed step h, with the law and the observer
evaluated at every stage on the measured angles y = q(stage) + noise (the noise sample is held
over a step). Constraints are checked after every step; trajectories and metrics use the 1 ms
grid. A step outside ODE3's stability region is detected from the method's embedded error
estimate, even when the actuator limit keeps the state finite.

State layout per arm, ``X[b]`` (5n): ``[q, qd, x1_hat, x2_hat, x3_hat]``.
"""

from __future__ import annotations

import hashlib
import os
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from numba import njit
from numba import types as nbtypes
from numba.core import cgutils
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic
from numba.np.arrayobj import populate_array

from .bounds import BOUND_LEN, KA, KB, bounds_into
from .blocks import Connection, Controller, Observer, ResidualFilter, connect, model_length, nominal_length, nominal_model_into, work_length
from .controller import make_controller, make_observer
from .dynamics import (
    WORK_PER_LINK,
    abs_trig_into,
    ldl_factor_into,
    ldl_solve_factored,
    ldl_solve_into,
    coriolis_times_into,
    gravity_into,
    mass_matrix_into,
    wrench_torque_into,
)
from .params import BOUNDS_PACK, PLANT_TAIL, REFERENCE_PACK, Scenario, plant_length
from .reward import SUM_COLUMNS, SUM_E2_JOINT, SUM_EN2, SUM_ERR_MAX, SUM_SAMPLES, SUM_UN2, accumulate_sample
from .status import LAST_COLUMNS, N_STATUS, STATUS_COLUMNS
from .reference import reference_into
from .uncertainty import dead_zone, force_active, friction

__all__ = [
    "CHANNELS",
    "ClosedLoop",
    "Trajectory",
    "SimulationDiverged",
    "simulate",
    "simulate_batch",
]

# Recorded channels, each an n-vector per 1 ms sample (the time channel repeats t).
CHANNELS = (
    "t", "q", "qd", "q_ref", "qd_ref", "e1", "k_a", "k_b", "u", "h_u", "u_law", "saturated",
    "x3", "x3_hat", "x2_hat", "x1_hat", "y",
)
_C = {name: i for i, name in enumerate(CHANNELS)}
N_CHANNELS = len(CHANNELS)

# Offsets after the arm block (2n+1) in the packed plant vector, read from its one declaration.
_T = {name: i for i, name in enumerate(PLANT_TAIL)}
_VISC, _COUL, _PSI = _T["viscous"], _T["coulomb"], _T["tanh_slope"]
_HR, _HL, _TR, _TL = _T["slope_right"], _T["slope_left"], _T["break_right"], _T["break_left"]
_FX, _MZ, _ONSET = _T["f_x"], _T["moment"], _T["onset"]
_UMAX, _DIVLIM, _ERR_RTOL, _ERR_ATOL = _T["max_torque"], _T["divergence_limit"], _T["error_rtol"], _T["error_atol"]
_UNSTABLE_STEPS = _T["unstable_steps"]

(ST_STEPS, ST_DIVERGED, ST_VIOL_STEPS, ST_FIRST_VIOL, ST_SAT_STEPS, ST_VIOL_SAMPLES, ST_FILTER_BREACHES,
 ST_ASSUMPTION_FAILURES) = (STATUS_COLUMNS.index(c) for c in STATUS_COLUMNS)
LAST_U, LAST_ULAW, LAST_SAT, LAST_X3, LAST_X3HAT = (LAST_COLUMNS.index(c) for c in LAST_COLUMNS)
N_LAST = len(LAST_COLUMNS)


@njit(cache=True, error_model="numpy")
def _lumped_true(q, qd, qdd, u, nominal, out, M, L, work):
    """x3 = qdd - F_nom(q, qd) - M_nom^-1 u = M_nom^-1 (M_nom qdd + C_nom qd + G_nom - u)."""
    n = q.shape[0]
    trig = work[4 * n : 6 * n]
    c = work[6 * n : 7 * n]
    g = work[7 * n : 8 * n]
    r = work[8 * n : 9 * n]
    abs_trig_into(q, trig)
    mass_matrix_into(trig, nominal, M, work)
    coriolis_times_into(trig, qd, qd, nominal, c, work)
    gravity_into(trig, nominal, g, work)
    for i in range(n):
        acc = 0.0
        for j in range(n):
            acc += M[i * n + j] * qdd[j]
        r[i] = acc + c[i] + g[i] - u[i]
    ldl_solve_into(M, r, out, L)


@intrinsic
def _window(typingctx, arr, start, length):
    """The view arr[start:start+length] of a 1-D contiguous array, built without a bounds clamp
    or a runtime reshape, so that a compile-time ``length`` stays a constant LLVM can see.

    The kernel carves all its scratch views with this: with constant shapes (n = _N is bound at
    specialisation) LLVM unrolls every per-joint loop of the plant, law and observer, and with
    constant offsets from one base pointer it can tell the views apart (no aliasing reloads).
    Callers guarantee ``start + length <= len(arr)`` (scratch_length checks the layout).
    """
    if not (isinstance(arr, nbtypes.Array) and arr.ndim == 1 and arr.layout == "C"):
        return None
    sig = arr(arr, nbtypes.intp, nbtypes.intp)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        src = context.make_array(aryty)(context, builder, args[0])
        out = context.make_array(aryty)(context, builder)
        itemsize = context.get_constant(nbtypes.intp, context.get_abi_sizeof(context.get_data_type(aryty.dtype)))
        populate_array(out, data=builder.gep(src.data, [args[1]]),
                       shape=cgutils.pack_array(builder, [args[2]]),
                       strides=cgutils.pack_array(builder, [itemsize]),
                       itemsize=src.itemsize, meminfo=src.meminfo, parent=src.parent)
        return impl_ret_borrowed(context, builder, aryty, out._getvalue())

    return sig, codegen


@njit(cache=True, error_model="numpy", inline="always")
def _fixed(w, start, length):
    """w[start:start+length] with a shape LLVM sees as a constant when ``length`` is one."""
    return _window(w, start, length)


@njit(cache=True, error_model="numpy", inline="always")
def _violates(e_or_q, ref, bnd, n):
    """True if any joint's error q - q_d is outside (-k_b, k_a) (first n entries of ``e_or_q``)."""
    for i in range(n):
        e = e_or_q[i] - ref[i]
        if e >= bnd[KA] or e <= -bnd[KB]:
            return True
    return False


@njit(cache=True, error_model="numpy")
def _record(r, t, x, y, ref, bnd, u, hu, ulaw, satf, x3, o1, o2, o3):
    """Write one 1 ms sample (the channels of CHANNELS) into ``r`` (channels, n). ``o1``, ``o2``,
    ``o3`` are the offsets of x1_hat, x2_hat, x3_hat in the state, -1 for one the observer lacks."""
    n = y.shape[0]
    for i in range(n):
        r[0, i] = t
        r[1, i] = x[i]
        r[2, i] = x[n + i]
        r[3, i] = ref[i]
        r[4, i] = ref[n + i]
        r[5, i] = x[i] - ref[i]
        r[6, i] = bnd[KA]
        r[7, i] = bnd[KB]
        r[8, i] = u[i]
        r[9, i] = hu[i]
        r[10, i] = ulaw[i]
        r[11, i] = satf[i]
        r[12, i] = x3[i]
        r[13, i] = x[o3 + i] if o3 >= 0 else np.nan
        r[14, i] = x[o2 + i] if o2 >= 0 else np.nan
        r[15, i] = x[o1 + i] if o1 >= 0 else np.nan
        r[16, i] = y[i]


@njit(cache=True, error_model="numpy", inline="always")
def _ode3_update(x, K0, K1, K2, dt, divlim, xn, ep):
    """The Bogacki-Shampine step: the new state into ``xn``, the embedded estimate's first part
    into ``ep``; False if an entry is non-finite or beyond ``divlim``."""
    ok = True
    for i in range(x.shape[0]):
        ep[i] = (-5.0 / 72.0) * K0[i] + (1.0 / 12.0) * K1[i] + (1.0 / 9.0) * K2[i]
        v = x[i] + dt * ((2.0 / 9.0) * K0[i] + (1.0 / 3.0) * K1[i] + (4.0 / 9.0) * K2[i])
        if not (abs(v) <= divlim):  # also catches NaN
            ok = False
        xn[i] = v
    return ok


@njit(cache=True, error_model="numpy", inline="always")
def _error_ratio(ep, K3, xn, dt, atol, rtol):
    """The step's embedded second-order error estimate over its tolerance, worst entry (K3 is the
    evaluation at the new state with the step's own inputs, docs/model.md section 9)."""
    en = 0.0
    for i in range(xn.shape[0]):
        e = abs(dt * (ep[i] - 0.125 * K3[i])) / (atol + rtol * abs(xn[i]))
        if e > en:
            en = e
    return en


@njit(cache=True, error_model="numpy", inline="always")
def _stage_input(st, x, K0, K1, dt, xs):
    """The state at which ODE3 stage ``st`` (0, 1, 2) is evaluated, into ``xs``."""
    if st == 0:
        for i in range(x.shape[0]):
            xs[i] = x[i]
    elif st == 1:
        for i in range(x.shape[0]):
            xs[i] = x[i] + 0.5 * dt * K0[i]
    else:
        for i in range(x.shape[0]):
            xs[i] = x[i] + 0.75 * dt * K1[i]


@njit(cache=True, error_model="numpy", inline="always")
def _instability(en, noisy, sps, err_run, unstable_steps):
    """The count of consecutive unstable steps after one check with error ratio ``en``, and whether
    the run is now diverged (a noisy arm's check counts for its sample period's steps)."""
    if en > 1.0:
        err_run += 1 if not noisy else sps
        return err_run, err_run >= unstable_steps
    return 0, False


@njit(cache=True, error_model="numpy", inline="always")
def _step_bookkeeping(j, k, x, ref, bnd, satf, terminate, st, n):
    """At the start of step ``j`` (global ``k``), state ``x``: the constraint check of the state the
    previous step produced and the saturation count, into the status row ``st``; returns True if
    the arm must stop (a violation with ``terminate``)."""
    if j > 0 and _violates(x, ref, bnd, n):
        st[ST_VIOL_STEPS] += 1
        if st[ST_FIRST_VIOL] < 0:
            st[ST_FIRST_VIOL] = k
        if terminate:
            return True
    for i in range(n):
        if satf[i] > 0.0:
            st[ST_SAT_STEPS] += 1
            break
    return False


def _stage_template(t, x, noise_j, y, res, plant, nom, same_arm, rp, bp, lg, og, fg, ref, bnd, cout,
                    fout, rr, u, hu, satf, dx, pw, Mp, Lp, wl, wo):
    """One evaluation of the closed-loop right-hand side at (t, x), written into ``dx``.

    The measurement is y = q(stage) + noise, the noise sample held over the step, so without noise
    the law and the observer see the angles at every stage like Simulink's continuous blocks.
    ``x`` = [q, qd, observer states, controller states]. ``_ctrl_output``, ``_obs_rhs`` and
    ``_ctrl_update`` are the generated glue of :func:`blf_gym.blocks.connect`, bound with the sizes
    ``_N``, ``_NO``, ``_NC`` by :func:`_specialise`; with a residual filter (``_FILTER``), ``_res_filter``
    turns the residual (with ``_PLAIN``, the agent's torque minus u_law) into ``fout[:n]``.
    """
    n = _N  # noqa: F821 (the number of joints, a compile-time constant bound at specialisation)
    nn = n * n
    arm = plant[: 2 * n + 1]
    o = 2 * n + 1
    reference_into(t, rp, arm, ref)
    bounds_into(t, bp, bnd)
    q = _fixed(x, 0, n)
    qd = _fixed(x, n, n)
    xo = _fixed(x, 2 * n, _NO)  # noqa: F821
    xc = _fixed(x, 2 * n + _NO, _NC)  # noqa: F821
    dxo = _fixed(dx, 2 * n, _NO)  # noqa: F821
    dxc = _fixed(dx, 2 * n + _NO, _NC)  # noqa: F821
    same_angles = True
    for i in range(n):
        y[i] = q[i] + noise_j[i]
        if y[i] != q[i]:
            same_angles = False
    # the plant's configuration terms
    trig = pw[4 * n : 6 * n]
    c = pw[6 * n : 7 * n]
    g = pw[7 * n : 8 * n]
    jf = pw[8 * n : 9 * n]
    rhs = pw[9 * n : 10 * n]
    abs_trig_into(q, trig)
    mass_matrix_into(trig, arm, Mp, pw)
    gravity_into(trig, arm, g, pw)
    ldl_factor_into(Mp, Lp)
    # The nominal model at the measured angles, shared by the law and the observer. Without noise
    # y == q, and when the nominal arm is the true one (the paper's cases) it equals the plant's.
    if same_angles and same_arm:
        for i in range(nn):
            nom[i] = Mp[i]
        for i in range(n):
            nom[nn + i] = g[i]
        for i in range(2 * n):
            nom[nn + n + i] = trig[i]
        for i in range(nn):
            nom[nn + 3 * n + i] = Lp[i]
    else:
        nominal_model_into(y, _fixed(nom, 2 * nn + 3 * n, 2 * n + 1), nom, pw[10 * n :])
    umax = plant[o + _UMAX]
    _ctrl_output(t, y, q, qd, xo, xc, ref, bnd, nom, og, lg, fg, u, cout, rr, fout, umax, dxo, dxc, wl)  # noqa: F821
    if _FILTER:  # noqa: F821 (compile-time constant)
        for i in range(n):
            rr[i] = res[i] - cout[i] if _PLAIN else res[i]  # noqa: F821
        _res_filter(t, y, q, qd, xo, xc, ref, bnd, nom, og, lg, fg, u, cout, rr, fout, umax, dxo, dxc, wl)  # noqa: F821
    for i in range(n):
        ui = cout[i] + (fout[i] if _FILTER else res[i])  # noqa: F821
        s = 0.0
        if ui > umax:
            ui = umax
            s = 1.0
        elif ui < -umax:
            ui = -umax
            s = 1.0
        u[i] = ui
        satf[i] = s
        hu[i] = dead_zone(ui, plant[o + _HR], plant[o + _HL], plant[o + _TR], plant[o + _TL])
    # plant: M qdd = H(u) - C qd - G - J^T f_ext - tau_fric   (paper eq. 1)
    coriolis_times_into(trig, qd, qd, arm, c, pw)
    if force_active(t, plant[o + _ONSET]) > 0.0:
        wrench_torque_into(trig, arm, plant[o + _FX : o + _MZ + 1], jf)
    else:
        for i in range(n):
            jf[i] = 0.0
    for i in range(n):
        rhs[i] = hu[i] - c[i] - g[i] - jf[i] - friction(qd[i], plant[o + _VISC], plant[o + _COUL],
                                                       plant[o + _PSI])
        dx[i] = qd[i]
    ldl_solve_factored(Lp, rhs, dx[n : 2 * n])
    _obs_rhs(t, y, q, qd, xo, xc, ref, bnd, nom, og, lg, fg, u, cout, rr, fout, umax, dxo, dxc, wo)  # noqa: F821
    _ctrl_update(t, y, q, qd, xo, xc, ref, bnd, nom, og, lg, fg, u, cout, rr, fout, umax, dxo, dxc, wl)  # noqa: F821


def _advance_template(X, ksteps, n_steps, dt, sps, plant, nominal, rp, bp, lg, og, fgains, residual,
                      noise, terminate, rec, nrec, status, last, scratch, sums, unstable_run):
    """Advance every arm b by up to ``n_steps`` ODE3 steps from global step ``ksteps[b]``.

    One step is: the stage evaluations (:func:`_stage_input`, ``_stage``), the step's bookkeeping
    at its start (:func:`_step_bookkeeping`; at 1 ms samples also :func:`_sample`, which feeds the
    reward's :func:`blf_gym.reward.accumulate_sample` and the record), the update
    (:func:`_ode3_update`) and the instability check (:func:`_error_ratio`, :func:`_instability`).

    Instability check (docs/model.md section 9): a step's embedded Bogacki-Shampine error estimate
    needs the fourth evaluation f(t + h, x_new) *with the step's own inputs* (measurement noise
    sample, residual). Without noise it is checked at every step, and that evaluation is reused as
    the next step's first one when the inputs stay the same (first-same-as-last); at the last step
    of a call it is evaluated anyway, since the next call may bring new inputs. With noise, whose
    sample changes every step, it is evaluated at every step ending a 1 ms sample period (global
    step index, so every path checks the same steps) and counts for that many steps.
    ``unstable_run[b]`` carries the count of consecutive unstable steps across calls, so the verdict
    does not depend on how a run is cut into calls.

    Stops an arm early on divergence (state restored to the last finite one) or, when
    ``terminate``, right after the first step whose end state violates a bound. Records the
    channels of :data:`CHANNELS` into ``rec[b]`` at every step index divisible by ``sps``.
    ``scratch`` (N, scratch_length(...)) is per-arm work space.
    """
    N = X.shape[0]
    n = _N  # noqa: F821 (the number of joints, a compile-time constant bound at specialisation)
    nx = _NX  # noqa: F821 (2n + observer states + controller states, bound at specialisation)
    has_noise = noise.shape[1] > 0
    for b in range(N):
        # Scratch views. The kernel is compiled without NRT: it allocates nothing and views carry
        # no reference counting (which would otherwise dominate a step's cost). Every view is
        # given a compile-time-constant shape, so after inlining LLVM unrolls the per-joint loops
        # of the law, observer and model.
        w = scratch[b]
        K0 = _fixed(w, 0, nx)
        K1 = _fixed(w, nx, nx)
        K2 = _fixed(w, 2 * nx, nx)
        K3 = _fixed(w, 3 * nx, nx)
        o = 4 * nx
        xs = _fixed(w, o, nx)
        xn = _fixed(w, o + nx, nx)
        ep = _fixed(w, o + 2 * nx, nx)
        o += 3 * nx
        y = _fixed(w, o, n)
        nz = _fixed(w, o + n, n)
        ref = _fixed(w, o + 2 * n, 3 * n)
        bnd = _fixed(w, o + 5 * n, BOUND_LEN)
        o += 5 * n + BOUND_LEN
        u = _fixed(w, o, n)
        hu = _fixed(w, o + n, n)
        satf = _fixed(w, o + 2 * n, n)
        x3 = _fixed(w, o + 3 * n, n)
        o += 4 * n
        cout = _fixed(w, o, _NOUT)  # noqa: F821 (the controller's outputs, u_law first)
        o += _NOUT  # noqa: F821
        fout = _fixed(w, o, _NFOUT)  # noqa: F821 (the residual filter's outputs, r_f first)
        o += _NFOUT  # noqa: F821
        rr = _fixed(w, o, n)  # the residual the filter sees
        o += n
        Mp = _fixed(w, o, n * n)
        Lp = _fixed(w, o + n * n, n * n)
        o += 2 * n * n
        nom = _fixed(w, o, nominal_length(n))
        o += nominal_length(n)
        pw = _fixed(w, o, (10 + WORK_PER_LINK) * n + n * n)
        o += (10 + WORK_PER_LINK) * n + n * n
        wl = _fixed(w, o, work_length(n))
        o += work_length(n)
        wo = _fixed(w, o, work_length(n))
        o += work_length(n)
        # the inputs of the true lumped disturbance at the latest 1 ms sample [q, qd, qdd, u],
        # evaluated once at the end of the call unless every sample is recorded
        smp = _fixed(w, o, 4 * n)
        x = _fixed(X[b], 0, nx)
        ulaw = _fixed(cout, 0, n)
        recording = nrec[b] < rec.shape[1]
        x3_pending = False
        res_b = residual[b]
        rp_b = rp[b]
        bp_b = bp[b]
        lg_b = lg[b]
        og_b = og[b]
        fg_b = fgains[b]
        plant_b = plant[b]
        nom_b = nominal[b]
        arm_b = plant_b[: 2 * n + 1]
        same_arm = True
        for i in range(2 * n + 1):
            nom[model_length(n) + i] = nom_b[i]
            if nom_b[i] != arm_b[i]:
                same_arm = False
        divlim = plant_b[2 * n + 1 + _DIVLIM]
        err_rtol = plant_b[2 * n + 1 + _ERR_RTOL]
        err_atol = plant_b[2 * n + 1 + _ERR_ATOL]
        unstable_steps = plant_b[2 * n + 1 + _UNSTABLE_STEPS]
        err_max = 0.0
        err_run = unstable_run[b]
        # a noisy arm's measurement changes every step: its check runs once per sample period
        noisy = False
        if has_noise:
            for j in range(n_steps):
                for i in range(n):
                    if noise[b, j, i] != 0.0:
                        noisy = True
        umax = plant_b[2 * n + 1 + _UMAX]
        st_b = status[b]
        sm_b = sums[b]
        for i in range(st_b.shape[0]):
            st_b[i] = 0
        st_b[ST_FIRST_VIOL] = -1
        for i in range(sm_b.shape[0]):
            sm_b[i] = 0.0
        last_b = last[b]
        k0 = ksteps[b]
        steps = 0
        diverged = 0
        stopped = False
        have_k0 = False
        for j in range(n_steps):
            k = k0 + j
            t = k * dt
            for i in range(n):
                nz[i] = noise[b, j, i] if has_noise else 0.0
            check = (not noisy) or ((k + 1) % sps == 0)
            halt = False
            committed = False
            # the stages share one call site, so the inlined stage (law and observer included) is
            # compiled once: 0, 1, 2 are the step's Bogacki-Shampine stages, 3 the check's
            # evaluation at the new state
            for st in range(4):
                if st == 0:
                    ts = t
                    kst = K0
                    if not have_k0:
                        _stage_input(st, x, K0, K1, dt, xs)
                elif st == 1:
                    ts = t + 0.5 * dt
                    kst = K1
                    _stage_input(st, x, K0, K1, dt, xs)
                elif st == 2:
                    ts = t + 0.75 * dt
                    kst = K2
                    _stage_input(st, x, K0, K1, dt, xs)
                else:
                    if not _ode3_update(x, K0, K1, K2, dt, divlim, xn, ep):
                        diverged = 1
                        halt = True
                        break
                    committed = True
                    if not check:
                        break
                    ts = (k + 1) * dt  # the next step's time exactly as its stage 0 computes it
                    kst = K3
                    for i in range(nx):
                        xs[i] = xn[i]
                if not (st == 0 and have_k0):
                    _stage(ts, xs, nz, y, res_b, plant_b, nom, same_arm, rp_b, bp_b, lg_b, og_b, fg_b,  # noqa: F821
                           ref, bnd, cout, fout, rr, u, hu, satf, kst, pw, Mp, Lp, wl, wo)
                if st == 3:
                    # the embedded error estimate grows without bound when h is outside ODE3's
                    # stability region, even when the actuator limit keeps the state finite
                    en = _error_ratio(ep, K3, xn, dt, err_atol, err_rtol)
                    if en > err_max:
                        err_max = en
                    err_run, unstable = _instability(en, noisy, sps, err_run, unstable_steps)
                    if unstable:
                        diverged = 2
                    continue
                if st > 0:
                    continue
                # bookkeeping at the step's start time t (state x)
                if _step_bookkeeping(j, k, x, ref, bnd, satf, terminate, st_b, n):
                    halt = True
                    if err_run > 0:
                        # the bound broke while ODE3's error estimate was above tolerance: the
                        # integration's violation, not the arm's (code 3, a divergence)
                        diverged = 3
                    break
                if _BREACH >= 0 and fout[_BREACH] > 0.0:  # noqa: F821 (the filter's own monitors)
                    st_b[ST_FILTER_BREACHES] += 1
                if _ASSUME >= 0 and fout[_ASSUME] < 0.5:  # noqa: F821
                    st_b[ST_ASSUMPTION_FAILURES] += 1
                if k % sps == 0:
                    # a 1 ms sample: the true lumped disturbance, the reward/metric sums, the record
                    if recording:
                        _lumped_true(x[:n], x[n : 2 * n], K0[n : 2 * n], u, nom_b, x3, Mp, Lp, pw)
                        for i in range(n):
                            last_b[LAST_X3 * n + i] = x3[i]
                    else:
                        for i in range(n):
                            smp[i] = x[i]
                            smp[n + i] = x[n + i]
                            smp[2 * n + i] = K0[n + i]
                            smp[3 * n + i] = u[i]
                        x3_pending = True
                    if accumulate_sample(x, y, ref, bnd, u, cout, umax, sm_b, n):
                        st_b[ST_VIOL_SAMPLES] += 1
                    for i in range(n):
                        last_b[LAST_X3HAT * n + i] = x[_X3H + i] if _X3H >= 0 else np.nan  # noqa: F821
                    if recording:
                        _record(rec[b, nrec[b]], t, x, y, ref, bnd, u, hu, ulaw, satf, x3,
                                _X1H, _X2H, _X3H)  # noqa: F821
                        nrec[b] += 1
                        recording = nrec[b] < rec.shape[1]
                for i in range(n):
                    last_b[LAST_U * n + i] = u[i]
                    last_b[LAST_ULAW * n + i] = ulaw[i]
                    last_b[LAST_SAT * n + i] = satf[i]
                for i in range(_NOUT):  # noqa: F821
                    last_b[N_LAST * n + i] = cout[i]
                for i in range(_NFOUT):  # noqa: F821
                    last_b[N_LAST * n + _NOUT + i] = fout[i]  # noqa: F821
            if committed:
                for i in range(nx):
                    x[i] = xn[i]
                steps += 1
            if halt or diverged:
                stopped = True
                break
            # first-same-as-last: the check's evaluation is the next step's first one when the
            # inputs are the same (no noise, and the residual is held for the whole call)
            have_k0 = check and not noisy and j + 1 < n_steps
            if have_k0:
                K0, K3 = K3, K0  # swap the views: no copy
        if x3_pending:
            _lumped_true(smp[:n], smp[n : 2 * n], smp[2 * n : 3 * n], smp[3 * n :], nom_b, x3, Mp, Lp, pw)
            for i in range(n):
                last_b[LAST_X3 * n + i] = x3[i]
        if not stopped:
            t_end = (k0 + steps) * dt
            reference_into(t_end, rp_b, arm_b, ref)
            bounds_into(t_end, bp_b, bnd)
            if _violates(x, ref, bnd, n):
                st_b[ST_VIOL_STEPS] += 1
                if st_b[ST_FIRST_VIOL] < 0:
                    st_b[ST_FIRST_VIOL] = k0 + steps
                if terminate and err_run > 0:
                    diverged = 3  # as above: this violation ends the episode, on an unstable integration
        ksteps[b] = k0 + steps
        unstable_run[b] = err_run
        st_b[ST_STEPS] = steps
        st_b[ST_DIVERGED] = diverged
        sm_b[SUM_ERR_MAX] = err_max


def scratch_length(n: int, n_obs: int | None = None, n_ctrl: int = 0, n_out: int | None = None,
                   n_fout: int = 0) -> int:
    """Per-arm scratch the kernel needs (must match the views carved in _advance_template); the
    default sizes are the LESO's 3n states, no controller states, the torque as only output and no
    filter."""
    n_obs = 3 * n if n_obs is None else n_obs
    n_out = n if n_out is None else n_out
    nx = 2 * n + n_obs + n_ctrl
    return (7 * nx + 5 * n + BOUND_LEN + 4 * n + n_out + n_fout + n + 2 * n * n + nominal_length(n)
            + (10 + WORK_PER_LINK) * n + n * n + 2 * work_length(n) + 4 * n)


# ---------------------------------------------------------------------------------------------
# specialisation: clone the templates with the law and observer bound, compile with a disk cache


_KERNEL_MODULES = ("blocks", "bounds", "dynamics", "reference", "reward", "simulate", "status", "uncertainty")


def _source_digest(*modules: types.ModuleType) -> str:
    """Hash of the source files the compiled kernel depends on.

    numba's cache only watches the file that defines a function, not the files of the functions
    it calls; folding every dependency's source into the kernel's name makes an edit to any of
    them invalidate the cached kernel (and only those: editing the env does not recompile).
    """
    h = hashlib.sha1()
    pkg = Path(__file__).parent
    for name in _KERNEL_MODULES:
        h.update((pkg / f"{name}.py").read_bytes())
    for m in modules:
        f = getattr(m, "__file__", None)
        if f:
            h.update(Path(f).read_bytes())
    return h.hexdigest()[:10]


def _cache_dir(dispatcher) -> Path:
    """Where numba keeps this dispatcher's cache: next to the sources if that folder is writable,
    otherwise its fallback (``NUMBA_CACHE_DIR`` or the user's cache folder)."""
    return Path(dispatcher._cache._cache_path)


def _is_cached(dispatcher) -> bool:
    """True if machine code for this dispatcher is in memory or in numba's disk cache."""
    return bool(dispatcher.signatures) or Path(dispatcher._cache._cache_file._index_path).is_file()


def remove_stale_cache(cache: Path, prefix: str, digest: str) -> list[Path]:
    """Delete numba's cache files of older builds of one kernel, ``simulate.{prefix}{digest}-...``
    with another 10-hex-digit digest (they are never used again); return what was deleted.

    Only that exact name with another digest is stale. Other kernels whose names merely start with
    the prefix stay: the unfiltered ``advance__n3__proposed__leso__`` is a prefix of the filtered
    ``advance__n3__proposed__leso__barrier__...``, and a glob on the prefix deleted those, so every
    run that built one kernel recompiled the other."""
    import re

    if not cache.is_dir():
        return []
    pattern = re.compile(rf"simulate\.{re.escape(prefix)}([0-9a-f]{{10}})-")
    gone = []
    for f in cache.glob(f"simulate.{prefix}*"):
        m = pattern.match(f.name)
        if m and m.group(1) != digest:
            try:
                f.unlink()
                gone.append(f)
            except OSError:
                pass
    return gone


def kernel_label(controller: str, observer: str, residual_filter: str | None = None, plain: bool = False) -> str:
    """A compiled closed loop in a user's words: the law (or none, for plain torques), the filter and
    what it acts on, the observer."""
    law = "plain torques (no inner law)" if controller == "none" else f"the {controller} law"
    filt = ("" if residual_filter is None else
            f", its {residual_filter} filter on the agent's {'whole torque' if plain else 'residual'}")
    return f"{law}{filt}, with the {observer} observer"


def compile_notice(label: str, cache: Path) -> None:
    """Tell the user why the first run waits (printed once per kernel, on standard error); ``label``
    is :func:`kernel_label`'s."""
    import sys

    print(f"blf-gym: compiling the closed loop for {label} (first run only, about 15-50 s; "
          f"cached in {cache})", file=sys.stderr, flush=True)


def _clone(template, name: str, bindings: dict, **jit_options):
    g = dict(template.__globals__)
    g.update(bindings)
    fn = types.FunctionType(template.__code__, g, name, template.__defaults__, template.__closure__)
    fn.__qualname__ = name
    fn.__module__ = template.__module__
    fn.__doc__ = template.__doc__
    return njit(cache=True, error_model="numpy", **jit_options)(fn)


_KERNELS: dict[tuple, object] = {}
_NOTICED: set = set()


def _specialise(conn: Connection):
    """The compiled kernel for one connection (controller, observer, n): the templates cloned with
    the generated glue and the sizes bound as globals, compiled with a disk cache."""
    key = conn
    if key not in _KERNELS:
        n = conn.n
        digest = hashlib.sha1((_source_digest() + conn.digest).encode()).hexdigest()[:10]
        pair = f"{conn.controller.name}__{conn.observer.name}"
        if conn.filter is not None:
            pair += f"__{conn.filter.name}{'_plain' if conn.plain else ''}"
        tag = f"{pair}__{digest}"
        off = {k: 2 * n + conn.obs_offsets[k][0] if k in conn.obs_offsets and conn.obs_offsets[k][1] == n else -1
               for k in ("x1_hat", "x2_hat", "x3_hat")}
        fo = conn.fout_offsets
        sizes = {"_N": n, "_NO": conn.n_obs, "_NC": conn.n_ctrl, "_NX": 2 * n + conn.n_obs + conn.n_ctrl,
                 "_NOUT": conn.n_out, "_X1H": off["x1_hat"], "_X2H": off["x2_hat"], "_X3H": off["x3_hat"],
                 "_FILTER": conn.filter is not None, "_PLAIN": conn.plain, "_NFOUT": conn.n_fout,
                 "_BREACH": fo["breach"][0] if "breach" in fo else -1,
                 "_ASSUME": fo["assumptions"][0] if "assumptions" in fo else -1}
        stage = _clone(_stage_template, f"stage__n{n}__{tag}",
                       {"_ctrl_output": conn.ctrl_output, "_obs_rhs": conn.obs_rhs, "_ctrl_update": conn.ctrl_update,
                        "_res_filter": conn.res_filter, **sizes}, inline="always")
        kernel = _clone(_advance_template, f"advance__n{n}__{tag}", {"_stage": stage, **sizes}, nogil=True, _nrt=False)
        cache = _cache_dir(kernel)
        remove_stale_cache(cache, f"stage__n{n}__{pair}__", digest)
        remove_stale_cache(cache, f"advance__n{n}__{pair}__", digest)
        _KERNELS[key] = kernel
    return _KERNELS[key]


# ---------------------------------------------------------------------------------------------
# Python-side shells


def _compile_error(conn: Connection, exc: Exception) -> str:
    """A one-paragraph message for a kernel numba could not compile, naming the plug-in at fault
    (each of its functions is compiled alone on the kernel's argument types to find it)."""
    from numba import njit as _njit
    from numba import types as _t

    c, o = conn.controller, conn.observer
    arr = _t.float64[::1]
    for fn, params, owner in ((c.output, c._out_params, f"{c.owner}.output"),
                              (c.update, c._upd_params, f"{c.owner}.update"),
                              (o.rhs, o._rhs_params, f"{o.owner}.rhs")):
        if fn is None:
            continue
        layouts = o.param_layout if fn is o.rhs else c.param_layout
        sig = tuple(_t.float64 if (p == "t" or p.startswith(("k_a", "k_b")) or (p in layouts and layouts[p][1] is None))
                    else arr for p in params)
        try:
            _njit(error_model="numpy")(getattr(fn, "py_func", fn)).compile(sig)
        except Exception as e:  # noqa: BLE001
            first = str(e).strip().splitlines()
            return (f"{owner} could not be compiled by numba (write it as loops over numpy arrays, without "
                    f"allocating, Python objects or unsupported calls): {' '.join(first[:3])}")
    first = str(exc).strip().splitlines()
    return f"the closed loop for {c.owner} + {o.owner} could not be compiled by numba: {' '.join(first[:3])}"


class SimulationDiverged(RuntimeError):
    """Raised on request when the state became non-finite or exceeded the divergence limit."""


@dataclass
class Trajectory:
    """Signals of one run on the 1 ms grid (docs/model.md section 8), plus how the run ended.

    Every array has the sample axis first; joint signals are (samples, n). ``u`` is the torque
    commanded to the actuators (law + residual, after the limit), ``h_u`` what the dead-zone passes,
    ``x3`` the true lumped disturbance against the controller's nominal model and ``x3_hat`` the
    observer's estimate.
    """

    scenario: str
    controller: str
    dt: float
    signals: dict[str, np.ndarray]
    diverged: bool = False
    diverged_at: float | None = None
    step_violations: int = 0
    """Integration steps whose end state broke a bound (finer than the 1 ms samples)."""
    first_violation_step_time: float | None = None
    saturated_steps: int = 0
    divergence_code: int = 0
    """0 healthy, 1 non-finite or beyond SimParams.divergence_limit, 2 numerically unstable, 3 a
    bound broken (ending the episode) while the integration was unstable."""
    wall_s: float = 0.0
    message: str = ""
    filter_breaches: int = 0
    """With a residual filter: integration steps where its condition did not hold (should be 0)."""
    assumption_failures: int = 0
    """With a residual filter: integration steps where an assumption of its guarantee failed."""
    residual_filter: str | None = None
    """The residual filter the run went through (None: none)."""

    def __getattr__(self, name: str) -> np.ndarray:
        signals = self.__dict__.get("signals", {})
        if name in signals:
            return signals[name]
        raise AttributeError(name)

    @property
    def n_samples(self) -> int:
        return int(self.signals["t"].shape[0])

    def save_npz(self, path: str | os.PathLike) -> None:
        """Write the signals and metadata atomically to ``path`` (.npz)."""
        from .io import atomic_write_npz

        meta = dict(scenario=self.scenario, controller=self.controller, dt=self.dt,
                    diverged=self.diverged, diverged_at=self.diverged_at)
        atomic_write_npz(path, {**self.signals, **{f"meta_{k}": np.asarray(v if v is not None else np.nan)
                                                  for k, v in meta.items()}})


@dataclass
class _Batch:
    plant: np.ndarray
    nominal: np.ndarray
    ref: np.ndarray
    bnd: np.ndarray
    law_gains: np.ndarray
    obs_gains: np.ndarray
    filter_gains: np.ndarray


class ClosedLoop:
    """N arms with one controller and one observer, stepped by the compiled kernel.

    Each arm has its own scenario (plant, reference, bounds); all share ``dt``. The state, the
    global step counter and the last applied torques live here; :meth:`advance` runs the kernel,
    splitting the arms over ``threads`` (default: one per CPU, at most one per arm).
    """

    def __init__(
        self,
        scenarios: Sequence[Scenario],
        controller: str | Controller = "proposed",
        observer: str | Observer = "leso",
        threads: int | None = None,
        residual_filter: "str | ResidualFilter | None" = None,
        plain: bool = False,
    ) -> None:
        if len(scenarios) == 0:
            raise ValueError("ClosedLoop needs at least one scenario")
        self.controller = make_controller(controller)
        self.observer = make_observer(observer)
        self.n = scenarios[0].arm.n_links
        dts = {s.sim.dt for s in scenarios}
        if len(dts) != 1:
            raise ValueError(f"all scenarios of a ClosedLoop must share SimParams.dt, got {sorted(dts)}")
        self.dt = dts.pop()
        sps = {s.sim.steps_per_sample for s in scenarios}
        if len(sps) != 1:
            raise ValueError("all scenarios of a ClosedLoop must share SimParams.sample_period")
        self.steps_per_sample = sps.pop()
        if threads is None:
            threads = min(len(scenarios), os.cpu_count() or 1)
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.threads = int(threads)
        self._pool = None
        n = self.n
        if self.controller.nominal.n_links != n or self.observer.nominal.n_links != n:
            raise ValueError("controller/observer nominal model must have as many links as the plant")
        self.residual_filter = self.controller.make_filter(residual_filter)
        """The residual filter between the residual and the actuator (None: none)."""
        self.plain = bool(plain)
        """With a filter: the residual passed to advance() is the agent's whole torque."""
        self.connection = connect(self.controller, self.observer, n, self.residual_filter, self.plain)
        self._kernel = _specialise(self.connection)
        fresh = not _is_cached(self._kernel)
        if fresh and self._kernel not in _NOTICED:
            _NOTICED.add(self._kernel)
            label = kernel_label(self.controller.name, self.observer.name,
                                 self.residual_filter.name if self.residual_filter else None, self.plain)
            compile_notice(label, _cache_dir(self._kernel))
        c = self.connection
        self.N = len(scenarios)
        self.nx = 2 * n + c.n_obs + c.n_ctrl
        """State entries per arm: [q, qd, observer states, controller states]."""
        self.X = np.zeros((self.N, self.nx))
        self.ksteps = np.zeros(self.N, dtype=np.int64)
        self.unstable_run = np.zeros(self.N, dtype=np.int64)
        """Per arm, the consecutive integration steps the instability check has failed so far
        (carried across calls, reset with the arm)."""
        self.last = np.zeros((self.N, N_LAST * n + c.n_out + c.n_fout))
        """Per arm, the columns of blf_gym.status.LAST_COLUMNS (n each), then the controller's
        outputs in its declared order (see :meth:`outputs`)."""
        self._scratch = np.zeros((self.N, scratch_length(n, c.n_obs, c.n_ctrl, c.n_out, c.n_fout)))
        self._zeros_residual = np.zeros((self.N, n))
        self._no_noise = np.zeros((self.N, 0, n))
        self._no_record = np.zeros((self.N, 0, N_CHANNELS, n))
        self.set_scenarios(scenarios)
        if fresh:
            self._compile()

    def _compile(self) -> None:
        """Compile the kernel now (a call of zero steps), reporting a plug-in numba cannot compile as
        a ValueError that names it."""
        from numba.core.errors import NumbaError

        X, k, last = self.X.copy(), self.ksteps.copy(), self.last.copy()
        try:
            self.advance(0, record_samples=0)
        except NumbaError as exc:
            raise ValueError(_compile_error(self.connection, exc)) from None
        finally:
            self.X[:], self.ksteps[:], self.last[:] = X, k, last

    def outputs(self) -> dict[str, np.ndarray]:
        """The controller's outputs at the start of the last integration step, by name ((N, size)
        views of a copy)."""
        base = N_LAST * self.n
        last = self.last.copy()
        return {name: last[:, base + off : base + off + m] for name, (off, m) in self.connection.out_offsets.items()}

    def set_scenarios(self, scenarios: Sequence[Scenario], which: Sequence[int] | None = None) -> None:
        """Install scenarios (all, or the arms listed in ``which``) and reset those arms."""
        idx = list(range(self.N)) if which is None else list(which)
        if len(scenarios) != len(idx):
            raise ValueError("one scenario per reset arm is required")
        if not hasattr(self, "_batch"):
            n = self.n
            self._batch = _Batch(
                plant=np.zeros((self.N, plant_length(n))),
                nominal=np.tile(self.controller.nominal.pack(), (self.N, 1)),
                ref=np.zeros((self.N, len(REFERENCE_PACK))),
                bnd=np.zeros((self.N, len(BOUNDS_PACK))),
                law_gains=np.tile(self.controller.gains, (self.N, 1)),
                obs_gains=np.tile(self.observer.gains, (self.N, 1)),
                filter_gains=np.tile(self.residual_filter.gains if self.residual_filter else np.zeros(0),
                                     (self.N, 1)),
            )
        b = self._batch
        for i, sc in zip(idx, scenarios):
            if sc.arm.n_links != self.n or sc.sim.dt != self.dt or sc.sim.steps_per_sample != self.steps_per_sample:
                raise ValueError("a replacement scenario must keep n links, dt and sample_period")
            b.plant[i] = sc.pack_plant()
            b.ref[i] = sc.pack_reference()
            b.bnd[i] = sc.bounds.pack()
            self._reset_arm(i, sc)

    def _reset_arm(self, i: int, sc: Scenario) -> None:
        from .reference import joint_reference

        n = self.n
        q_d0 = joint_reference(0.0, sc)[0]
        q0 = q_d0 + np.asarray(sc.initial_error)
        no = self.connection.n_obs
        self.X[i] = 0.0
        self.X[i, :n] = q0
        self.X[i, 2 * n : 2 * n + no] = self.observer.initial(q0.copy())
        self.X[i, 2 * n + no :] = self.controller.initial(q0.copy())
        self.ksteps[i] = 0
        self.unstable_run[i] = 0
        self.last[i] = 0.0

    @property
    def time(self) -> np.ndarray:
        """Simulated time of each arm, s (global step counter times dt, never accumulated)."""
        return self.ksteps * self.dt

    def advance(
        self,
        n_steps: int,
        residual: np.ndarray | None = None,
        noise: np.ndarray | None = None,
        terminate: bool = False,
        record_samples: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Run ``n_steps`` ODE3 steps on every arm.

        ``residual`` (N, n) N m is added to the law's torque over the whole call; ``noise``
        (N, n_steps, n) rad is added to the measured angles step by step. Returns
        ``(rec, nrec, status)``: recorded samples (N, S, channels, n), how many per arm, and the
        status columns [steps, diverged (0, 1 non-finite, 2 unstable, 3 a terminating violation on an unstable integration), violating steps, first
        violating step or -1, saturated steps, violating 1 ms samples]. ``self.sums`` then holds
        per arm [max ODE3 error estimate, sum of (e1/bound)^2, sum of (u/max_torque)^2, samples,
        then the sum of e1^2 (rad^2) of each joint] over the call's 1 ms samples, and
        ``self.last`` [u, u_law, saturated] at the start of the
        last integration step and [x3, x3_hat] at the last 1 ms sample.
        """
        N, n = self.N, self.n
        if residual is None:
            res = self._zeros_residual
        else:
            res = residual if (type(residual) is np.ndarray and residual.dtype == np.float64
                               and residual.flags.c_contiguous) else np.ascontiguousarray(residual, dtype=np.float64)
            if res.shape != (N, n):
                raise ValueError(f"residual must have shape {(N, n)}, got {res.shape}")
        if noise is None:
            nz = self._no_noise
        else:
            nz = np.ascontiguousarray(noise, dtype=np.float64)
            if nz.shape[1] not in (0, n_steps) or nz.shape[0] != N:
                raise ValueError(f"noise must have shape {(N, n_steps, n)}, got {nz.shape}")
        if record_samples is None:
            record_samples = n_steps // self.steps_per_sample + 1
        rec = np.zeros((N, record_samples, N_CHANNELS, n)) if record_samples else self._no_record
        nrec = np.zeros(N, dtype=np.int64)
        status = np.empty((N, N_STATUS), dtype=np.int64)  # every column is set by the kernel
        sums = np.empty((N, SUM_E2_JOINT + n))
        b = self._batch
        if self.threads <= 1 or N == 1:
            self._kernel(self.X, self.ksteps, int(n_steps), float(self.dt), self.steps_per_sample, b.plant,
                         b.nominal, b.ref, b.bnd, b.law_gains, b.obs_gains, b.filter_gains, res, nz, bool(terminate),
                         rec, nrec, status, self.last, self._scratch, sums, self.unstable_run)
            self.sums = sums
            return rec, nrec, status
        arrays = (self.X, self.ksteps, b.plant, b.nominal, b.ref, b.bnd, b.law_gains, b.obs_gains, b.filter_gains,
                  res, nz, rec, nrec, status, self.last, self._scratch, sums, self.unstable_run)

        def run(lo: int, hi: int) -> None:
            a = arrays if (lo == 0 and hi == N) else [arr[lo:hi] for arr in arrays]
            self._kernel(a[0], a[1], int(n_steps), float(self.dt), int(self.steps_per_sample),
                         a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], a[10], bool(terminate),
                         a[11], a[12], a[13], a[14], a[15], a[16], a[17])

        # The kernel releases the GIL: contiguous blocks of arms run on parallel threads and write
        # into views of the shared arrays. Each arm's arithmetic is the same as alone.
        threads = min(self.threads, N)
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="blf")
        edges = np.linspace(0, N, threads + 1).round().astype(int)
        futures = [self._pool.submit(run, int(lo), int(hi)) for lo, hi in zip(edges[:-1], edges[1:])]
        for f in futures:
            f.result()
        self.sums = sums
        return rec, nrec, status


def divergence_message(code: int, t: float, dt: float, unstable_steps: int = 100,
                       controller: str | None = None) -> str:
    """Human-readable reason for a kernel divergence code (status column ``diverged``).

    ``controller`` is the inner law's name, ``"none"`` in plain mode (the agent's action is the
    whole torque), or None when unknown; it selects the likely cause named in the message. For
    code 2 the run is stopped ``unstable_steps`` steps after the instability began; the message
    gives both times. Code 3 is a violation that ended the episode (``terminate``) while ODE3's
    error estimate was above its tolerance: the integration broke the bound, so it is reported as
    a divergence, not as the arm's violation."""
    if code not in (1, 2, 3):
        return ""
    if controller == "none":
        cause = ("With no inner law, the actions are the likely cause: they spin the arm up to extreme "
                 "speeds (plain mode, termination off).")
    else:
        law = f"the {controller} law's" if controller else "the controller's"
        cause = (f"The likely cause is the step: dt = {dt:g} s is too large for {law} gains (the paper's "
                 f"gains need dt <= 1.5e-4 s; the default is 1e-4 s).")
    if code == 1:
        what = (f"simulation diverged at t = {t:.6f} s: the state became non-finite or exceeded "
                f"SimParams.divergence_limit.")
    elif code == 3:
        what = (f"simulation diverged numerically at t = {t:.6f} s: a bound was broken while ODE3's error "
                f"estimate was above its tolerance, so the integration, not the arm, broke it (the episode "
                f"ended on that violation before {unstable_steps} consecutive unstable steps, the count "
                f"that stops a run as unstable, were reached).")
    else:
        onset = max(0.0, t - unstable_steps * dt)
        what = (f"simulation diverged numerically (unstable from t = {onset:.6f} s, stopped at t = {t:.6f} s): "
                f"ODE3's error estimate stayed above tolerance for {unstable_steps} consecutive steps, so "
                f"the step is outside the integrator's stability region; the torque limit kept the state "
                f"finite, but the numbers are meaningless.")
    return f"{what} {cause} The signals up to that time are kept."


def _trajectory(sc: Scenario, controller: str, dt: float, rec: np.ndarray, nrec: int,
                status: np.ndarray, wall: float) -> Trajectory:
    r = rec[:nrec]
    signals = {name: (r[:, i, 0].copy() if name == "t" else r[:, i, :].copy())
               for i, name in enumerate(CHANNELS)}
    code = int(status[ST_DIVERGED])
    diverged = code != 0
    steps = int(status[ST_STEPS])
    fv = int(status[ST_FIRST_VIOL])
    msg = divergence_message(code, steps * dt, dt, sc.sim.unstable_steps, controller)
    return Trajectory(
        scenario=sc.name, controller=controller, dt=dt, signals=signals, diverged=diverged,
        diverged_at=steps * dt if diverged else None,
        step_violations=int(status[ST_VIOL_STEPS]),
        first_violation_step_time=None if fv < 0 else fv * dt,
        saturated_steps=int(status[ST_SAT_STEPS]), divergence_code=code, wall_s=wall, message=msg,
        filter_breaches=int(status[ST_FILTER_BREACHES]), assumption_failures=int(status[ST_ASSUMPTION_FAILURES]),
    )


def simulate_batch(
    scenarios: Sequence[Scenario],
    controller: str | Controller = "proposed",
    observer: str | Observer = "leso",
    noise_seeds: Sequence[int] | None = None,
    threads: int | None = None,
    residual: np.ndarray | None = None,
    residual_filter: "str | ResidualFilter | None" = None,
) -> list[Trajectory]:
    """Run whole episodes (each scenario's ``sim.duration``) for N scenarios in one kernel call.

    The law is evaluated at every ODE3 stage; episodes are not terminated on violation (they are
    counted). A diverging arm stops early and its trajectory says so (``diverged``, ``message``).
    ``residual`` (N, n) N m, held over the whole episode, is added to the law's torque, through
    ``residual_filter`` if given (one of the controller's filters).
    """
    loop = ClosedLoop(scenarios, controller, observer, threads=threads, residual_filter=residual_filter)
    steps = {s.sim.n_steps for s in scenarios}
    if len(steps) != 1:
        raise ValueError("simulate_batch needs scenarios of one duration")
    n_steps = steps.pop()
    noise = None
    if any(s.angle_noise_std > 0 for s in scenarios):
        seeds = noise_seeds if noise_seeds is not None else range(len(scenarios))
        noise = np.stack([np.random.default_rng(sd).standard_normal((n_steps, loop.n)) * s.angle_noise_std
                          for sd, s in zip(seeds, scenarios)])
    t0 = time.perf_counter()
    rec, nrec, status = loop.advance(n_steps, residual=residual, noise=noise, record_samples=scenarios[0].sim.n_samples)
    wall = time.perf_counter() - t0
    name = loop.controller.name
    trajs = [_trajectory(sc, name, loop.dt, rec[i], int(nrec[i]), status[i], wall / len(scenarios))
             for i, sc in enumerate(scenarios)]
    if loop.residual_filter is not None:
        for tr in trajs:
            tr.residual_filter = loop.residual_filter.name
    return trajs


def simulate(
    scenario: Scenario | str = "paper-0.1hz",
    controller: str | Controller = "proposed",
    observer: str | Observer = "leso",
    noise_seed: int = 0,
    raise_on_divergence: bool = False,
) -> Trajectory:
    """Run one whole episode and return its :class:`Trajectory` on the 1 ms grid.

    >>> traj = simulate("paper-0.1hz", "proposed")
    >>> traj.e1.shape
    (30000, 3)
    """
    if isinstance(scenario, str):
        from .params import preset

        scenario = preset(scenario)
    traj = simulate_batch([scenario], controller, observer, noise_seeds=[noise_seed], threads=1)[0]
    if traj.diverged and raise_on_divergence:
        raise SimulationDiverged(traj.message)
    return traj

