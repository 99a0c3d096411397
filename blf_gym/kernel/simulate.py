"""The closed loop: plant + observer + inner controller, integrated by fixed-step ODE3.

One compiled kernel serves everything: the reproduction (one arm, a whole 30 s episode per call),
the Gymnasium env (one arm, one agent period per call) and the vector env (N arms per call, split
over threads: the compiled kernel releases the GIL). Arms are stepped in blocks of lanes in
lockstep, laid out lanes innermost (:func:`lane_layout`): one lane by default, :data:`LANES` with
``ClosedLoop(lanes=LANES)``, where the per-arm code vectorises across arms (docs/model.md
section 6). It is specialised per (controller law,
observer) pair by cloning the template functions below with the law and observer bound as
globals, then compiled by numba with ``cache=True`` so a warm start loads machine code from disk.

Integration (docs/model.md section 6): Bogacki-Shampine ODE3, fixed step h, with the law and the observer
evaluated at every stage on the measured angles y = q(stage) + noise (the noise sample is held
over a step). Constraints are checked after every step; trajectories and metrics use the 1 ms
grid. A step outside ODE3's stability region is detected from the method's embedded error
estimate, even when the actuator limit keeps the state finite.

State layout per arm, ``X[b]``: ``[q, qd, observer states, controller states]`` (5n with the LESO).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)
from numba import types as nbtypes
from numba.core import cgutils
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic
from numba.np.arrayobj import populate_array

from blf_gym.jit import vmath
from blf_gym.model.bounds import BOUND_LEN, KA, KB, bounds_exponent, bounds_from, bounds_into
from blf_gym.plugins.blocks import (Connection, Controller, Observer, ResidualFilter, connect, nominal_length,
                     nominal_terms_into, work_length)
from blf_gym.plugins.registry import make_controller, make_observer
from blf_gym.jit.layout import (ARM, BOUNDS, CHANNELS, EXP_ARGS, FLAGS, KERNEL_WORK, NOMINAL, PENDING, PLANT, PLANT_TAIL,
                                RECORD, REF, REFERENCE, STATE, TAIL, TRIG, TRIG_ARGS, at, block_layout, part)
from blf_gym.model.dynamics import (
    abs_trig_into,
    ldl_factor_into,
    ldl_solve_factored,
    ldl_solve_into,
    coriolis_times_into,
    gravity_into,
    mass_matrix_into,
    wrench_torque_into,
)
from blf_gym.model.params import Scenario, check_int, usable_cores
from blf_gym.kernel.reward import SUM_E2_JOINT, SUM_ERR_MAX, accumulate_sample
from blf_gym.jit.views import fixed
from blf_gym.kernel.status import (LAST_SAT, LAST_U, LAST_ULAW, LAST_X3, LAST_X3HAT, N_LAST, N_STATUS, ST_ASSUMPTION_FAILURES,
                     ST_DIVERGED, ST_FILTER_BREACHES, ST_FIRST_VIOL, ST_SAT_STEPS, ST_STEPS, ST_VIOL_SAMPLES,
                     ST_VIOL_STEPS)
from blf_gym.model.reference import reference_angle, reference_from, reference_into
from blf_gym.model.uncertainty import dead_zone, force_active, friction, friction_exponent, friction_from

__all__ = [
    "Batch",
    "CHANNELS",
    "ClosedLoop",
    "Trajectory",
    "SimulationDiverged",
    "simulate",
    "simulate_batch",
]

N_CHANNELS = len(CHANNELS)
# Each channel's row in a record (blf_gym.jit.layout.RECORD; the kernel freezes these into its code).
(_CH_T, _CH_Q, _CH_QD, _CH_QREF, _CH_QDREF, _CH_E1, _CH_KA, _CH_KB, _CH_U, _CH_HU, _CH_ULAW, _CH_SAT, _CH_X3,
 _CH_X3HAT, _CH_X2HAT, _CH_X1HAT, _CH_Y) = (RECORD.index(c) for c in (
    "t", "q", "qd", "q_ref", "qd_ref", "e1", "k_a", "k_b", "u", "h_u", "u_law", "saturated", "x3", "x3_hat",
    "x2_hat", "x1_hat", "y"))

# Offsets within the plant's scalars (the tail after the arm) and, as triples for at(), in the
# packed plant vector: blf_gym.jit.layout.PLANT.
_VISC, _COUL, _PSI = (TAIL.index(k) for k in ("viscous", "coulomb", "tanh_slope"))
_HR, _HL, _TR, _TL = (TAIL.index(k) for k in ("slope_right", "slope_left", "break_right", "break_left"))
_P_ARM, _P_TAIL, _SIZE_ARM, _SIZE_TAIL = PLANT.start("lengths"), PLANT.start(PLANT_TAIL[0]), ARM.total, TAIL.total
_P_FX, _P_MZ, _P_ONSET = PLANT.start("f_x"), PLANT.start("moment"), PLANT.start("onset")
_P_UMAX, _P_DIVLIM, _P_RTOL, _P_ATOL = (PLANT.start(k) for k in ("max_torque", "divergence_limit", "error_rtol",
                                                                  "error_atol"))
_P_UNSTABLE = PLANT.start("unstable_steps")
# the state's head, the reference signal, the pending sample, the nominal signal, the kernel's work
_S_Q, _S_QD, _S_OBS, _SIZE_N = STATE.start("q"), STATE.start("qd"), STATE.total, STATE.size("q")
_R_Q, _R_QD = REF.start("q_d"), REF.start("qd_d")
_PD_Q, _PD_QD, _PD_QDD, _PD_U = (PENDING.start(k) for k in ("q", "qd", "qdd", "u"))
_NOM_M, _NOM_G, _NOM_TRIG, _NOM_L, _NOM_ARM = (NOMINAL.start(k) for k in ("M", "G", "trig", "L", "arm"))
_KW_TRIG, _KW_C, _KW_G, _KW_JF, _KW_RHS, _KW_NOM = (KERNEL_WORK.start(k) for k in (
    "trig", "coriolis", "gravity", "wrench", "rhs", "nominal"))
_SIZE_TRIG, _SIZE_KW_NOM = TRIG.total, KERNEL_WORK.size("nominal")
_T_COS, _T_SIN = TRIG.start("cos"), TRIG.start("sin")
_A_PLANT, _A_MEAS, _A_REF, _A_END = (*(TRIG_ARGS.start(k) for k in ("plant", "measured", "reference")), TRIG_ARGS.total)
_E_FRIC, _E_BOUNDS, _E_END = EXP_ARGS.start("friction"), EXP_ARGS.start("bounds"), EXP_ARGS.total


@njit(cache=True, error_model="numpy")
def _lumped_true(q, qd, qdd, u, nominal, out, M, L, work):
    """x3 = qdd - F_nom(q, qd) - M_nom^-1 u = M_nom^-1 (M_nom qdd + C_nom qd + G_nom - u)."""
    n = q.shape[0]
    trig = part(work, _KW_TRIG, _SIZE_TRIG, n)
    c = part(work, _KW_C, _SIZE_N, n)
    g = part(work, _KW_G, _SIZE_N, n)
    r = part(work, _KW_RHS, _SIZE_N, n)
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


def _lane_intrinsic(lanes: int):
    """The intrinsic ``_lane(block, start, length, b)``: lane ``b``'s entries ``start`` to
    ``start + length`` of a block laid out lanes-innermost (entry s of lane b at ``s * lanes + b``),
    as a 1-D view with the constant stride ``lanes`` elements.

    This is the batched kernel's layout: one block holds ``lanes`` arms side by side, so the same
    entry of consecutive arms is contiguous and a loop over the lanes of per-arm code (plug-ins
    included, unchanged) vectorises. A constant stride lets LLVM prove the lanes independent."""

    @intrinsic
    def _lane(typingctx, block, start, length, b):
        if not (isinstance(block, nbtypes.Array) and block.ndim == 1 and block.layout == "C"):
            return None
        out_t = nbtypes.Array(block.dtype, 1, "A")
        sig = out_t(block, nbtypes.intp, nbtypes.intp, nbtypes.intp)

        def codegen(context, builder, signature, args):
            src = context.make_array(signature.args[0])(context, builder, args[0])
            out = context.make_array(out_t)(context, builder)
            itemsize = context.get_abi_sizeof(context.get_data_type(block.dtype))
            first = builder.add(builder.mul(args[1], context.get_constant(nbtypes.intp, lanes)), args[3])
            populate_array(out, data=builder.gep(src.data, [first]), shape=cgutils.pack_array(builder, [args[2]]),
                           strides=cgutils.pack_array(builder, [context.get_constant(nbtypes.intp, lanes * itemsize)]),
                           itemsize=src.itemsize, meminfo=src.meminfo, parent=src.parent)
            return impl_ret_borrowed(context, builder, out_t, out._getvalue())

        return sig, codegen

    return _lane


@intrinsic
def _claim(typingctx, counter):
    """``_claim(counter)``: atomically add one to ``counter[0]`` and return its value before, so
    that threads running the kernel on the same batch each take the next block no other has
    taken (the blocks go to whichever thread is free, so none waits for a slower one)."""
    if not (isinstance(counter, nbtypes.Array) and counter.ndim == 1 and counter.dtype == nbtypes.int64):
        return None
    sig = nbtypes.int64(counter)

    def codegen(context, builder, signature, args):
        arr = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", arr.data, context.get_constant(nbtypes.int64, 1), "monotonic")

    return sig, codegen


LANES = 4
"""Arms per block of the batched kernel (``ClosedLoop(lanes=LANES)``): one AVX2 vector of doubles.
A batch of N arms is stepped as ceil(N / LANES) blocks; the default build is the same code compiled
for one lane."""
_lane1 = _lane_intrinsic(1)
_laneN = _lane_intrinsic(LANES)


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
        r[_CH_T, i] = t
        r[_CH_Q, i] = x[at(_S_Q, n) + i]
        r[_CH_QD, i] = x[at(_S_QD, n) + i]
        r[_CH_QREF, i] = ref[at(_R_Q, n) + i]
        r[_CH_QDREF, i] = ref[at(_R_QD, n) + i]
        r[_CH_E1, i] = x[at(_S_Q, n) + i] - ref[at(_R_Q, n) + i]
        r[_CH_KA, i] = bnd[KA]
        r[_CH_KB, i] = bnd[KB]
        r[_CH_U, i] = u[i]
        r[_CH_HU, i] = hu[i]
        r[_CH_ULAW, i] = ulaw[i]
        r[_CH_SAT, i] = satf[i]
        r[_CH_X3, i] = x3[i]
        r[_CH_X3HAT, i] = x[o3 + i] if o3 >= 0 else np.nan
        r[_CH_X2HAT, i] = x[o2 + i] if o2 >= 0 else np.nan
        r[_CH_X1HAT, i] = x[o1 + i] if o1 >= 0 else np.nan
        r[_CH_Y, i] = y[i]


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


@njit(cache=True, error_model="numpy", inline="always")
def _stage_trig(ts, q, qd, nz, y, rp, arm, tail, bp, ref, bnd, trig, ntrig, fr, ang, sn, cs, ex, ev, n,
                one_lane):
    """The part of a stage evaluation that calls the elementary functions (:mod:`blf_gym.jit.vmath`:
    sin and cos, acos, atan2, exp), for one lane: the reference and the bounds at ``ts``, the
    measurement y, the cos and sin of the plant's and the nominal model's link angles, and the
    friction torques. It runs in a loop of its own, so that the rest of the stage, in
    :func:`_lanes_template`, vectorises across lanes.

    Compiled for one lane, the 2n + 1 angles (the plant's links, the measured links, the
    reference's) go through one loop of ``sincos`` and the n + 1 exponents (the friction's, the
    bounds') through one loop of ``exp``, padded to whole vectors (``ang``/``sn``/``cs`` and
    ``ex``/``ev``), so that the single arm's calls vectorise too. In a block the lanes vectorise
    instead. Either way every number is the same function of the same argument, so a block's arms
    and single arms agree bit for bit."""
    same = True
    for i in range(n):
        y[i] = q[i] + nz[i]
        if y[i] != q[i]:
            same = False
    if one_lane:
        a_pl, a_me, a_rf, e_fr, e_bd = at(_A_PLANT, n), at(_A_MEAS, n), at(_A_REF, n), at(_E_FRIC, n), at(_E_BOUNDS, n)
        c0, s0 = at(_T_COS, n), at(_T_SIN, n)
        th = 0.0
        thy = 0.0
        for j in range(n):
            th += q[j]
            thy += y[j]
            ang[a_pl + j] = th
            ang[a_me + j] = thy
        ang[a_rf] = reference_angle(ts, rp)
        for i in range(at(_A_END, n), ang.shape[0]):
            ang[i] = 0.0
        for i in range(ang.shape[0]):
            sn[i], cs[i] = vmath.sincos(ang[i])
        for j in range(n):
            trig[c0 + j] = cs[a_pl + j]
            trig[s0 + j] = sn[a_pl + j]
            ntrig[c0 + j] = cs[a_me + j]
            ntrig[s0 + j] = sn[a_me + j]
        reference_from(sn[a_rf], cs[a_rf], rp, arm, ref)
        for i in range(n):
            ex[e_fr + i] = friction_exponent(qd[i], tail[_PSI])
        ex[e_bd] = bounds_exponent(ts, bp)
        for i in range(at(_E_END, n), ex.shape[0]):
            ex[i] = 0.0
        for i in range(ex.shape[0]):
            ev[i] = vmath.exp(ex[i])
        bounds_from(ev[e_bd], bp, bnd)
        for i in range(n):
            fr[i] = friction_from(qd[i], tail[_VISC], tail[_COUL], tail[_PSI] * qd[i], ev[e_fr + i])
    else:
        reference_into(ts, rp, arm, ref)
        bounds_into(ts, bp, bnd)
        abs_trig_into(q, trig)
        abs_trig_into(y, ntrig)  # without noise y == q, and these are the same numbers
        for i in range(n):
            fr[i] = friction(qd[i], tail[_VISC], tail[_COUL], tail[_PSI])
    return same


@njit(cache=True, error_model="numpy", inline="always")
def _copy(src, dst):
    """dst[:] = src[:len(dst)] (the kernel allocates nothing, so no slice assignment)."""
    for i in range(dst.shape[0]):
        dst[i] = src[i]


def lane_layout(n: int, n_obs: int, n_ctrl: int, n_out: int, n_fout: int, n_law_gains: int, n_obs_gains: int,
                n_filter_gains: int) -> dict[str, tuple[int, int]]:
    """The per-lane entries of a block of the batched kernel, name -> (offset, length) in lane
    entries (:func:`blf_gym.jit.layout.block_layout`; a block of L entries per lane holds
    ``L * LANES`` numbers), and ``"_total"``: (L, 0)."""
    pack = block_layout(n, n_obs, n_ctrl, n_out, n_fout, n_law_gains, n_obs_gains, n_filter_gains)
    return {**pack.offsets(n), "_total": (pack.length(n), 0)}


# per-lane flags of a block (floats, 1.0 true): blf_gym.jit.layout.FLAGS
(_F_NOISY, _F_PENDING, _F_HALT, _F_CHECK, _F_OK, _F_STOPPED, _F_K0, _F_SAME_ARM, _F_SAME_Y) = (FLAGS.index(f) for f in (
    "noisy", "pending", "halt", "check", "ok", "stopped", "k0", "same_arm", "same_y"))
_N_FLAGS = FLAGS.length()


# long: the kernel's time loop is one compiled function (numba inlines nothing across a call to a
# generated closure's globals, and a split would put the lanes' state through argument tuples)
def _lanes_template(X, ksteps, n_steps, dt, sps, plant, nominal, rp, bp, lg, og, fgains, residual,
                    noise, terminate, plain, rec, nrec, status, last, scratch, sums, unstable_run, taken):
    """Advance every arm b by up to ``n_steps`` ODE3 steps from global step ``ksteps[b]``, the arms
    in blocks of ``_LN`` lanes stepped in lockstep (``scratch[k]`` is block k, laid out by
    :func:`lane_layout`, lanes innermost).

    A block is loaded (:func:`_load_block_template`), stepped, and stored back
    (:func:`_store_block_template`). One step is: its lanes' inputs (:func:`_begin_step_template`),
    the stage evaluations (:func:`_stage_input`, :func:`_stage_trig` and the rest of the right-hand
    side, in two loops over the lanes), the step's bookkeeping at its start
    (:func:`_sample_template`: violations, the reward's sums, the record), the update
    (:func:`_ode3_update`), the instability check (:func:`_check_stability_template`) and the commit
    (:func:`_commit_template`). The parts are cloned with the kernel's bindings and inlined. Every lane computes every stage the block needs; a lane's own control
    flow (stopped, noisy, first-same-as-last, instability checks) only decides what it keeps, so
    each arm's numbers are those it would get alone.

    The rest of a stage evaluation at (ts, x), for one lane, into ``dx``: branch-free where the lanes
    may differ, so that its loop over the lanes vectorises. The measurement is y = q(stage) + noise,
    the noise sample held over the step, so without noise the law and the observer see the angles at
    every stage like Simulink's continuous blocks. ``x`` = [q, qd, observer states, controller
    states]. ``_ctrl_output``, ``_obs_rhs`` and ``_ctrl_update`` are the generated glue of
    :func:`blf_gym.plugins.blocks.connect`, bound with the sizes ``_N``, ``_NO``, ``_NC`` by
    :func:`_specialise`; with a residual filter (``_FILTER``), ``_res_filter`` turns the residual
    (with ``plain``, a runtime flag, the agent's torque minus u_law) into ``fout[:n]``. The nominal
    model is evaluated at y, from the cos and sin :func:`_stage_trig` left in it; when the nominal
    arm is the plant's and y == q that gives the plant's own numbers, which a one-lane kernel copies
    instead (``copy_model``; in a block the lanes would take different branches).

    Instability check (docs/model.md section 9): a step's embedded Bogacki-Shampine error estimate
    needs the fourth evaluation f(t + h, x_new) *with the step's own inputs* (measurement noise
    sample, residual). Without noise it is checked at every step, and that evaluation is the next
    step's first one when the inputs stay the same (first-same-as-last); at the last step of a call
    it is evaluated anyway, since the next call may bring new inputs. With noise, whose sample
    changes every step, it is evaluated at every step ending a 1 ms sample period (global step
    index, so every path checks the same steps) and counts for that many steps.
    ``unstable_run[b]`` carries the count of consecutive unstable steps across calls, so the verdict
    does not depend on how a run is cut into calls.

    Stops an arm early on divergence (state restored to the last finite one) or, when
    ``terminate``, right after the first step whose end state violates a bound. Records the
    channels of :data:`CHANNELS` into ``rec[b]`` at every step index divisible by ``sps``.

    The blocks are taken in turn through ``taken[0]`` (:func:`_claim`): several threads may run the
    kernel on the same arrays at once, each block stepped by exactly one of them.
    """
    N = X.shape[0]
    n = _N  # noqa: F821 (the number of joints, a compile-time constant bound at specialisation)
    nx = _NX  # noqa: F821
    LN = _LN  # noqa: F821 (lanes per block)
    n_blocks = (N + LN - 1) // LN
    while True:
        block = _claim(taken)
        if block >= n_blocks:
            break
        work = scratch[block]
        arm0 = block * LN
        _load_block(work, arm0, N, n_steps, X, ksteps, plant, nominal, rp, bp, lg, og, fgains, residual, noise,  # noqa: F821
                    status, sums)
        any_fsal = False  # every active lane's stage 0 is its last step's check evaluation
        for j in range(n_steps):
            n_active, any_check = _begin_step(work, arm0, N, j, sps, noise)  # noqa: F821
            if n_active == 0:
                break
            for stage in range(4):
                if stage == 0 and any_fsal:
                    # the check's evaluation at this state, with these inputs, was last step's: K3
                    for b in range(LN):
                        _copy(_lane(work, _L_K3, nx, b), _lane(work, _L_K0, nx, b))  # noqa: F821
                elif stage == 3:
                    # the update; a lane whose state turns non-finite or leaves the limit halts
                    for b in range(LN):
                        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
                        plant_l = _lane(work, _L_plant, _NPL, b)  # noqa: F821
                        ok = _ode3_update(_lane(work, _L_x, nx, b), _lane(work, _L_K0, nx, b), _lane(work, _L_K1, nx, b),  # noqa: F821
                                          _lane(work, _L_K2, nx, b), dt, plant_l[at(_P_DIVLIM, n)],  # noqa: F821
                                          _lane(work, _L_xn, nx, b), _lane(work, _L_ep, nx, b))  # noqa: F821
                        flags[_F_OK] = 1.0 if ok else 0.0
                    if not any_check:
                        break
                if stage > 0 or not any_fsal:
                    # the stage's time and state, then the two parts of the evaluation, each a
                    # loop over the lanes with the same code for every lane (they vectorise)
                    for b in range(LN):
                        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
                        xs = _lane(work, _L_xs, nx, b)  # noqa: F821
                        if stage < 3:
                            _stage_input(stage, _lane(work, _L_x, nx, b), _lane(work, _L_K0, nx, b), _lane(work, _L_K1, nx, b), dt,  # noqa: F821
                                         xs)
                        else:
                            _copy(_lane(work, _L_xn, nx, b), xs)  # noqa: F821
                        k = np.int64(flags[_F_K0]) + j
                        t = k * dt
                        _lane(work, _L_ts, 1, b)[0] = (t if stage == 0 else (t + 0.5 * dt if stage == 1 else  # noqa: F821
                                                    (t + 0.75 * dt if stage == 2 else (k + 1) * dt)))
                    for b in range(LN):
                        same_y = _stage_trig(_lane(work, _L_ts, 1, b)[0], _lane(work, _L_xs + at(_S_Q, n), n, b),  # noqa: F821
                                    _lane(work, _L_xs + at(_S_QD, n), n, b),  # noqa: F821
                                    _lane(work, _L_nz, n, b), _lane(work, _L_y, n, b),  # noqa: F821
                                    _lane(work, _L_rp, _NRP, b), _lane(work, _L_plant + at(_P_ARM, n), at(_SIZE_ARM, n), b),  # noqa: F821
                                    _lane(work, _L_plant + at(_P_TAIL, n), at(_SIZE_TAIL, n), b), _lane(work, _L_bp, _NBP, b),  # noqa: F821
                                    _lane(work, _L_ref, _NREF, b), _lane(work, _L_bnd, BOUND_LEN, b),  # noqa: F821
                                    _lane(work, _L_pw + at(_KW_TRIG, n), at(_SIZE_TRIG, n), b),  # noqa: F821
                                    _lane(work, _L_nom + at(_NOM_TRIG, n), at(_SIZE_TRIG, n), b),  # noqa: F821
                                    _lane(work, _L_fr, n, b), _lane(work, _L_ang, _NANG, b), _lane(work, _L_sn, _NANG, b),  # noqa: F821
                                    _lane(work, _L_cs, _NANG, b), _lane(work, _L_ex, _NEX, b), _lane(work, _L_ev, _NEX, b),  # noqa: F821
                                    n, LN == 1)  # noqa: F821
                        _lane(work, _L_flags, _N_FLAGS, b)[_F_SAME_Y] = 1.0 if same_y else 0.0  # noqa: F821
                    for b in range(LN):
                        # the rest of the evaluation at (tb, xs) into dx, written here rather than
                        # inlined from a function of its own: numba copies an inlined function's
                        # whole IR, and this part, with the plug-ins in it, is most of the kernel
                        tb = _lane(work, _L_ts, 1, b)[0]  # noqa: F821
                        flags_b = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
                        copy_model = LN == 1 and flags_b[_F_SAME_ARM] != 0.0 and flags_b[_F_SAME_Y] != 0.0
                        x = _lane(work, _L_xs, nx, b)  # noqa: F821
                        y = _lane(work, _L_y, n, b)  # noqa: F821
                        res = _lane(work, _L_res, n, b)  # noqa: F821
                        plant_b = _lane(work, _L_plant, _NPL, b)  # noqa: F821
                        nom = _lane(work, _L_nom, nominal_length(n), b)  # noqa: F821
                        lgb = _lane(work, _L_lg, _NLG, b)  # noqa: F821
                        ogb = _lane(work, _L_og, _NOG, b)  # noqa: F821
                        fg = _lane(work, _L_fg, _NFG, b)  # noqa: F821
                        ref = _lane(work, _L_ref, _NREF, b)  # noqa: F821
                        bnd = _lane(work, _L_bnd, BOUND_LEN, b)  # noqa: F821
                        cout = _lane(work, _L_cout, _NOUT, b)  # noqa: F821
                        fout = _lane(work, _L_fout, _NFOUT, b)  # noqa: F821
                        rr = _lane(work, _L_rr, n, b)  # noqa: F821
                        u = _lane(work, _L_u, n, b)  # noqa: F821
                        hu = _lane(work, _L_hu, n, b)  # noqa: F821
                        satf = _lane(work, _L_satf, n, b)  # noqa: F821
                        dx = _lane(work, _L_dx, nx, b)  # noqa: F821 (a constant offset: see below)
                        pw = _lane(work, _L_pw, _NPW, b)  # noqa: F821
                        Mp = _lane(work, _L_Mp, n * n, b)  # noqa: F821
                        Lp = _lane(work, _L_Lp, n * n, b)  # noqa: F821
                        wl = _lane(work, _L_wl, work_length(n), b)  # noqa: F821
                        wo = _lane(work, _L_wo, work_length(n), b)  # noqa: F821
                        fr = _lane(work, _L_fr, n, b)  # noqa: F821
                        arm = part(plant_b, _P_ARM, _SIZE_ARM, n)
                        q = part(x, _S_Q, _SIZE_N, n)
                        qd = part(x, _S_QD, _SIZE_N, n)
                        xo = fixed(x, at(_S_OBS, n), _NO)  # noqa: F821
                        xc = fixed(x, at(_S_OBS, n) + _NO, _NC)  # noqa: F821
                        dxo = fixed(dx, at(_S_OBS, n), _NO)  # noqa: F821
                        dxc = fixed(dx, at(_S_OBS, n) + _NO, _NC)  # noqa: F821
                        trig = part(pw, _KW_TRIG, _SIZE_TRIG, n)
                        c = part(pw, _KW_C, _SIZE_N, n)
                        g = part(pw, _KW_G, _SIZE_N, n)
                        jf = part(pw, _KW_JF, _SIZE_N, n)
                        rhs = part(pw, _KW_RHS, _SIZE_N, n)
                        mass_matrix_into(trig, arm, Mp, pw)
                        gravity_into(trig, arm, g, pw)
                        ldl_factor_into(Mp, Lp)
                        if copy_model:
                            for i in range(n * n):
                                nom[at(_NOM_M, n) + i] = Mp[i]
                                nom[at(_NOM_L, n) + i] = Lp[i]
                            for i in range(n):
                                nom[at(_NOM_G, n) + i] = g[i]
                        else:
                            nominal_terms_into(part(nom, _NOM_ARM, _SIZE_ARM, n), nom, part(pw, _KW_NOM, _SIZE_KW_NOM, n))
                        umax = plant_b[at(_P_UMAX, n)]
                        _ctrl_output(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wl)  # noqa: F821
                        if _FILTER:  # noqa: F821 (compile-time constant)
                            for i in range(n):
                                rr[i] = res[i] - cout[i] if plain else res[i]
                            _res_filter(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wl)  # noqa: F821
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
                            hu[i] = dead_zone(ui, plant_b[at(_P_TAIL, n) + _HR], plant_b[at(_P_TAIL, n) + _HL],
                                              plant_b[at(_P_TAIL, n) + _TR], plant_b[at(_P_TAIL, n) + _TL])
                        # plant_b: M qdd = H(u) - C qd - G - J^T f_ext - tau_fric   (paper eq. 1)
                        coriolis_times_into(trig, qd, qd, arm, c, pw)
                        wrench_torque_into(trig, arm, fixed(plant_b, at(_P_FX, n), at(_P_MZ, n) + 1 - at(_P_FX, n)), jf)
                        on = force_active(tb, plant_b[at(_P_ONSET, n)]) > 0.0
                        for i in range(n):
                            jf[i] = jf[i] if on else 0.0
                        for i in range(n):
                            rhs[i] = hu[i] - c[i] - g[i] - jf[i] - fr[i]
                            dx[at(_S_Q, n) + i] = qd[i]
                        ldl_solve_factored(Lp, rhs, part(dx, _S_QD, _SIZE_N, n))
                        _obs_rhs(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wo)  # noqa: F821
                        _ctrl_update(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wl)  # noqa: F821
                    # into K0..K3: apart, since a view at an offset that depends on stage would keep
                    # LLVM from proving the lanes of the loop above independent
                    for b in range(LN):
                        _copy(_lane(work, _L_dx, nx, b), _lane(work, _L_K0 + stage * nx, nx, b))  # noqa: F821
                if stage == 3:
                    _check_stability(work, arm0, dt, sps, sums, status, unstable_run)  # noqa: F821
                    continue
                if stage > 0:
                    continue
                _sample(work, arm0, j, dt, sps, terminate, nominal, rec, nrec, status, last, sums, unstable_run)  # noqa: F821
            any_fsal = _commit(work, arm0, j, n_steps, status)  # noqa: F821
        _store_block(work, arm0, N, dt, terminate, X, ksteps, nominal, status, last, unstable_run)  # noqa: F821


def _load_block_template(work, arm0, N, n_steps, X, ksteps, plant, nominal, rp, bp, lg, og, fgains, residual, noise,
                         status, sums):
    """Load block ``work``'s lanes from the arms ``arm0``, ``arm0 + 1``, ... (a padding lane past the
    last arm copies the block's first arm and stays inactive); clear their flags, status and sums."""
    n = _N  # noqa: F821
    nx = _NX  # noqa: F821
    LN = _LN  # noqa: F821
    has_noise = noise.shape[1] > 0

    for b in range(LN):
        a = arm0 + b if arm0 + b < N else arm0
        _copy(X[a], _lane(work, _L_x, nx, b))  # noqa: F821
        _copy(plant[a], _lane(work, _L_plant, _NPL, b))  # noqa: F821
        nom = _lane(work, _L_nom, nominal_length(n), b)  # noqa: F821
        same_arm = True
        for i in range(at(_SIZE_ARM, n)):
            nom[at(_NOM_ARM, n) + i] = nominal[a, i]
            if nominal[a, i] != plant[a, at(_P_ARM, n) + i]:
                same_arm = False
        _copy(rp[a], _lane(work, _L_rp, _NRP, b))  # noqa: F821
        _copy(bp[a], _lane(work, _L_bp, _NBP, b))  # noqa: F821
        _copy(lg[a], _lane(work, _L_lg, _NLG, b))  # noqa: F821
        _copy(og[a], _lane(work, _L_og, _NOG, b))  # noqa: F821
        _copy(fgains[a], _lane(work, _L_fg, _NFG, b))  # noqa: F821
        _copy(residual[a], _lane(work, _L_res, n, b))  # noqa: F821
        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
        for i in range(_N_FLAGS):
            flags[i] = 0.0
        real = arm0 + b < N
        flags[_F_STOPPED] = 0.0 if real else 1.0
        flags[_F_K0] = ksteps[a]
        flags[_F_SAME_ARM] = 1.0 if same_arm else 0.0
        # a noisy arm's measurement changes every step: its check runs once per sample period
        noisy = False
        if has_noise:
            for j in range(n_steps):
                for i in range(n):
                    if noise[a, j, i] != 0.0:
                        noisy = True
        flags[_F_NOISY] = 1.0 if noisy else 0.0
        if real:
            st_b = status[a]
            sm_b = sums[a]
            for i in range(st_b.shape[0]):
                st_b[i] = 0
            st_b[ST_FIRST_VIOL] = -1
            for i in range(sm_b.shape[0]):
                sm_b[i] = 0.0


def _begin_step_template(work, arm0, N, j, sps, noise):
    """Per lane, at step ``j`` of the call: the step's noise sample, whether its instability check
    runs; returns (the lanes still going, whether any of them checks)."""
    n = _N  # noqa: F821
    LN = _LN  # noqa: F821
    has_noise = noise.shape[1] > 0

    n_active = 0
    any_check = False
    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
        if flags[_F_STOPPED] == 0.0:
            flags[_F_HALT] = 0.0
        k = np.int64(flags[_F_K0]) + j
        check = flags[_F_NOISY] == 0.0 or (k + 1) % sps == 0
        flags[_F_CHECK] = 1.0 if check else 0.0
        nz = _lane(work, _L_nz, n, b)  # noqa: F821
        a = arm0 + b if arm0 + b < N else arm0
        for i in range(n):
            nz[i] = noise[a, j, i] if has_noise else 0.0
        if flags[_F_STOPPED] == 0.0:
            n_active += 1
            if check:
                any_check = True
    return n_active, any_check


def _check_stability_template(work, arm0, dt, sps, sums, status, unstable_run):
    """After a step's update, per checking lane: ODE3's embedded error estimate against its
    tolerance (:func:`_error_ratio`), its running maximum, and the count of consecutive unstable
    steps (:func:`_instability`), which flags a divergence (code 2)."""
    n = _N  # noqa: F821
    nx = _NX  # noqa: F821
    LN = _LN  # noqa: F821

    # the embedded error estimate grows without bound when h is outside ODE3's
    # stability region, even when the actuator limit keeps the state finite
    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
        if flags[_F_STOPPED] != 0.0 or flags[_F_HALT] != 0.0 or flags[_F_OK] == 0.0 or flags[_F_CHECK] == 0.0:
            continue
        a = arm0 + b
        plant_l = _lane(work, _L_plant, _NPL, b)  # noqa: F821
        en = _error_ratio(_lane(work, _L_ep, nx, b), _lane(work, _L_K3, nx, b), _lane(work, _L_xn, nx, b), dt,  # noqa: F821
                          plant_l[at(_P_ATOL, n)], plant_l[at(_P_RTOL, n)])
        if en > sums[a, SUM_ERR_MAX]:
            sums[a, SUM_ERR_MAX] = en
        err_run, unstable = _instability(en, flags[_F_NOISY] != 0.0, sps, unstable_run[a],
                                         plant_l[at(_P_UNSTABLE, n)])
        unstable_run[a] = err_run
        if unstable:
            status[a, ST_DIVERGED] = 2


def _sample_template(work, arm0, j, dt, sps, terminate, nominal, rec, nrec, status, last, sums, unstable_run):
    """Per lane, at step ``j``'s start time (state x, after its first stage evaluation): the
    violation and saturation bookkeeping (:func:`_step_bookkeeping`), the filter's monitors; at a
    1 ms sample also the true lumped disturbance, the reward's sums
    (:func:`blf_gym.kernel.reward.accumulate_sample`) and the record; then the last applied signals."""
    n = _N  # noqa: F821
    nx = _NX  # noqa: F821
    LN = _LN  # noqa: F821

    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
        if flags[_F_STOPPED] != 0.0:
            continue
        a = arm0 + b
        k = np.int64(flags[_F_K0]) + j
        x = _lane(work, _L_x, nx, b)  # noqa: F821
        ref = _lane(work, _L_ref, _NREF, b)  # noqa: F821
        bnd = _lane(work, _L_bnd, BOUND_LEN, b)  # noqa: F821
        u = _lane(work, _L_u, n, b)  # noqa: F821
        satf = _lane(work, _L_satf, n, b)  # noqa: F821
        cout = _lane(work, _L_cout, _NOUT, b)  # noqa: F821
        fout = _lane(work, _L_fout, _NFOUT, b)  # noqa: F821
        st_b = status[a]
        last_b = last[a]
        if _step_bookkeeping(j, k, x, ref, bnd, satf, terminate, st_b, n):
            flags[_F_HALT] = 1.0
            if unstable_run[a] > 0:
                # the bound broke while ODE3's error estimate was above tolerance: the
                # integration's violation, not the arm's (code 3, a divergence)
                st_b[ST_DIVERGED] = 3
            continue
        if _BREACH >= 0 and fout[_BREACH] > 0.0:  # noqa: F821 (the filter's own monitors)
            st_b[ST_FILTER_BREACHES] += 1
        if _ASSUME >= 0 and fout[_ASSUME] < 0.5:  # noqa: F821
            st_b[ST_ASSUMPTION_FAILURES] += 1
        if k % sps == 0:
            # a 1 ms sample: the true lumped disturbance, the reward/metric sums, the record
            y = _lane(work, _L_y, n, b)  # noqa: F821
            x3 = _lane(work, _L_x3, n, b)  # noqa: F821
            K0 = _lane(work, _L_K0, nx, b)  # noqa: F821
            recording = nrec[a] < rec.shape[1]
            nom_a = nominal[a]
            if recording:
                _lumped_true(part(x, _S_Q, _SIZE_N, n), part(x, _S_QD, _SIZE_N, n), part(K0, _S_QD, _SIZE_N, n), u, nom_a,
                             x3, _lane(work, _L_Mp, n * n, b),  # noqa: F821
                             _lane(work, _L_Lp, n * n, b), _lane(work, _L_pw, _NPW, b))  # noqa: F821
                for i in range(n):
                    last_b[LAST_X3 * n + i] = x3[i]
            else:
                pending = _lane(work, _L_smp, _NSMP, b)  # noqa: F821
                for i in range(n):
                    pending[at(_PD_Q, n) + i] = x[at(_S_Q, n) + i]
                    pending[at(_PD_QD, n) + i] = x[at(_S_QD, n) + i]
                    pending[at(_PD_QDD, n) + i] = K0[at(_S_QD, n) + i]
                    pending[at(_PD_U, n) + i] = u[i]
                flags[_F_PENDING] = 1.0
            plant_l = _lane(work, _L_plant, _NPL, b)  # noqa: F821
            if accumulate_sample(x, y, ref, bnd, u, cout, plant_l[at(_P_UMAX, n)], sums[a], n):
                st_b[ST_VIOL_SAMPLES] += 1
            for i in range(n):
                last_b[LAST_X3HAT * n + i] = x[_X3H + i] if _X3H >= 0 else np.nan  # noqa: F821
            if recording:
                _record(rec[a, nrec[a]], k * dt, x, y, ref, bnd, u, _lane(work, _L_hu, n, b), cout[:n], satf,  # noqa: F821
                        x3, _X1H, _X2H, _X3H)  # noqa: F821
                nrec[a] += 1
        for i in range(n):
            last_b[LAST_U * n + i] = u[i]
            last_b[LAST_ULAW * n + i] = cout[i]
            last_b[LAST_SAT * n + i] = satf[i]
        for i in range(_NOUT):  # noqa: F821
            last_b[N_LAST * n + i] = cout[i]
        for i in range(_NFOUT):  # noqa: F821
            last_b[N_LAST * n + _NOUT + i] = fout[i]  # noqa: F821


def _commit_template(work, arm0, j, n_steps, status):
    """Per lane, after step ``j``: keep the new state or flag the divergence, stop lanes that halted;
    returns whether every going lane may reuse its check evaluation as the next step's first one
    (first-same-as-last)."""
    nx = _NX  # noqa: F821
    LN = _LN  # noqa: F821

    any_fsal = True
    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
        if flags[_F_STOPPED] != 0.0:
            continue
        a = arm0 + b
        if flags[_F_HALT] == 0.0 and flags[_F_OK] == 0.0:
            status[a, ST_DIVERGED] = 1
        if flags[_F_HALT] == 0.0 and flags[_F_OK] != 0.0:
            _copy(_lane(work, _L_xn, nx, b), _lane(work, _L_x, nx, b))  # noqa: F821
            status[a, ST_STEPS] += 1
        if flags[_F_HALT] != 0.0 or status[a, ST_DIVERGED] != 0:
            flags[_F_STOPPED] = 1.0
            continue
        # first-same-as-last: the check's evaluation is the next step's first one when the
        # inputs are the same (no noise, and the residual is held for the whole call)
        if not (flags[_F_CHECK] != 0.0 and flags[_F_NOISY] == 0.0 and j + 1 < n_steps):
            any_fsal = False
    return any_fsal


def _store_block_template(work, arm0, N, dt, terminate, X, ksteps, nominal, status, last, unstable_run):
    """After the call's last step, per arm of the block: a pending sample's true disturbance, the
    end state's violation check, and the state and step counter back into ``X`` and ``ksteps``."""
    n = _N  # noqa: F821
    nx = _NX  # noqa: F821
    LN = _LN  # noqa: F821

    for b in range(LN):
        a = arm0 + b
        if a >= N:
            continue
        flags = _lane(work, _L_flags, _N_FLAGS, b)  # noqa: F821
        x = _lane(work, _L_x, nx, b)  # noqa: F821
        x3 = _lane(work, _L_x3, n, b)  # noqa: F821
        last_b = last[a]
        st_b = status[a]
        if flags[_F_PENDING] != 0.0:
            pending = _lane(work, _L_smp, _NSMP, b)  # noqa: F821
            _lumped_true(part(pending, _PD_Q, _SIZE_N, n), part(pending, _PD_QD, _SIZE_N, n),
                         part(pending, _PD_QDD, _SIZE_N, n), part(pending, _PD_U, _SIZE_N, n), nominal[a], x3,  # noqa: F821
                         _lane(work, _L_Mp, n * n, b), _lane(work, _L_Lp, n * n, b), _lane(work, _L_pw, _NPW, b))  # noqa: F821
            for i in range(n):
                last_b[LAST_X3 * n + i] = x3[i]
        steps = st_b[ST_STEPS]
        k0 = np.int64(flags[_F_K0])
        if flags[_F_STOPPED] == 0.0:
            t_end = (k0 + steps) * dt
            ref = _lane(work, _L_ref, _NREF, b)  # noqa: F821
            bnd = _lane(work, _L_bnd, BOUND_LEN, b)  # noqa: F821
            plant_l = _lane(work, _L_plant, _NPL, b)  # noqa: F821
            reference_into(t_end, _lane(work, _L_rp, _NRP, b), part(plant_l, _P_ARM, _SIZE_ARM, n), ref)  # noqa: F821
            bounds_into(t_end, _lane(work, _L_bp, _NBP, b), bnd)  # noqa: F821
            if _violates(x, ref, bnd, n):
                st_b[ST_VIOL_STEPS] += 1
                if st_b[ST_FIRST_VIOL] < 0:
                    st_b[ST_FIRST_VIOL] = k0 + steps
                if terminate and unstable_run[a] > 0:
                    st_b[ST_DIVERGED] = 3  # as above: this violation ends the episode, on an unstable integration
        _copy(x, X[a])
        ksteps[a] = k0 + steps


_PARTS = {"_load_block": _load_block_template, "_begin_step": _begin_step_template,
          "_check_stability": _check_stability_template, "_sample": _sample_template, "_commit": _commit_template,
          "_store_block": _store_block_template}
"""The kernel's parts, each one job, cloned with the same bindings as :func:`_lanes_template` and
inlined into it."""


# ---------------------------------------------------------------------------------------------
# specialisation: clone the templates with the law and observer bound, compile with a disk cache


def kernel_digest(conn: Connection) -> str:
    """The 10-hex-digit digest in a kernel's name: the sources of this module's import closure
    (:func:`blf_gym.jit.sources.digest`: the templates, every block they inline, every packed layout's
    declaration, found by following the imports, not from a list) and the connection's own digest
    (the plug-ins' closures and the generated glue, :func:`blf_gym.plugins.blocks.connect`). An edit to any
    of those files, a comment included, builds a new kernel; an edit to a module the kernel does not
    import (the env, agents/, docs/) does not."""
    return hashlib.sha1((sources.digest(__name__) + conn.digest).encode()).hexdigest()[:10]


def _cache_dir(dispatcher) -> Path:
    """Where numba keeps this dispatcher's cache: next to the sources if that folder is writable,
    otherwise its fallback (``NUMBA_CACHE_DIR`` or the user's cache folder)."""
    return Path(dispatcher._cache._cache_path)


def _is_cached(dispatcher) -> bool:
    """True if machine code for this dispatcher is in memory or in numba's disk cache under its
    current source stamp (an index written for other sources is stale: numba would recompile)."""
    if dispatcher.signatures:
        return True
    try:
        return bool(dispatcher._cache._cache_file._load_index())
    except Exception:  # noqa: BLE001 (an unreadable index is a miss: numba rebuilds it)
        return False


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


def kernel_label(controller: str, observer: str, residual_filter: str | None = None) -> str:
    """A compiled closed loop in a user's words: the law (or none, for plain torques), the filter and
    what it acts on, the observer. One build of a filtered loop serves both of the filter's uses."""
    law = "plain torques (no inner law)" if controller == "none" else f"the {controller} law"
    filt = ("" if residual_filter is None else
            f", its {residual_filter} filter (on the agent's residual, or in plain mode its whole torque)")
    return f"{law}{filt}, with the {observer} observer"


def compile_notice(label: str, cache: Path) -> None:
    """Tell the user why the first run waits (printed once per kernel, on standard error); ``label``
    is :func:`kernel_label`'s."""
    print(f"blf-gym: compiling the closed loop for {label} (first run only, about 15-50 s; "
          f"cached in {cache})", file=sys.stderr, flush=True)


@contextlib.contextmanager
def _compile_lock(kernel, label: str):
    """Hold an exclusive lock on one kernel's entry in numba's cache while it compiles, so that
    processes started together (pytest workers, sweep trials, subprocess vector envs) compile it
    once: the others wait, then load it from the cache. Without ``fcntl`` (not POSIX) or with a
    cache folder that cannot hold the lock file, each process compiles its own, as before. ``label``
    (:func:`kernel_label`'s) names the kernel in the waiting notice: one process may compile one
    kernel while it waits for another."""
    try:
        import fcntl
    except ImportError:
        fcntl = None
    f = None
    if fcntl is not None:
        # named like the kernel's cache files, so that remove_stale_cache drops it with them
        path = _cache_dir(kernel) / f"simulate.{kernel.py_func.__qualname__}-compile.lock"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            f = open(path, "a")
        except OSError:
            f = None
    if f is None:
        yield
        return
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            print(f"blf-gym: another process is compiling the closed loop for {label}; waiting for it",
                  file=sys.stderr, flush=True)
            fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


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


def _specialise(conn: Connection, lanes: int = LANES):
    """The compiled kernel for one connection (controller, observer, n) and block width ``lanes``
    (1 or :data:`LANES`): the templates cloned with the generated glue, the sizes and the block
    layout bound as globals, compiled with a disk cache."""
    key = (conn, lanes)
    if key not in _KERNELS:
        n = conn.n
        digest = kernel_digest(conn)
        pair = f"{conn.controller.name}__{conn.observer.name}"
        if conn.filter is not None:
            pair += f"__{conn.filter.name}"
        tag = f"{pair}__{digest}"
        off = {k: STATE.length(n) + conn.obs_offsets[k][0] if k in conn.obs_offsets and conn.obs_offsets[k][1] == n else -1
               for k in ("x1_hat", "x2_hat", "x3_hat")}
        fo = conn.fout_offsets
        sizes = {"_N": n, "_NO": conn.n_obs, "_NC": conn.n_ctrl, "_NX": STATE.length(n) + conn.n_obs + conn.n_ctrl,
                 "_NOUT": conn.n_out, "_X1H": off["x1_hat"], "_X2H": off["x2_hat"], "_X3H": off["x3_hat"],
                 "_FILTER": conn.filter is not None, "_NFOUT": conn.n_fout,
                 "_BREACH": fo["breach"][0] if "breach" in fo else -1,
                 "_ASSUME": fo["assumptions"][0] if "assumptions" in fo else -1}
        layout = _layout(conn)
        sizes.update({f"_L_{k}": o for k, (o, _) in layout.items() if k != "_total"})
        sizes.update(_NPL=layout["plant"][1], _NRP=layout["rp"][1], _NBP=layout["bp"][1], _NLG=layout["lg"][1],
                     _NOG=layout["og"][1], _NFG=layout["fg"][1], _NPW=layout["pw"][1], _LN=lanes,
                     _NREF=layout["ref"][1], _NSMP=layout["smp"][1],
                     _NANG=layout["ang"][1], _NEX=layout["ex"][1],
                     _lane=_lane1 if lanes == 1 else _laneN)
        parts = {name: _clone(tpl, f"{name[1:]}{lanes}__n{n}__{tag}", sizes, inline="always")
                 for name, tpl in _PARTS.items()}
        kernel = _clone(_lanes_template, f"advance{lanes}__n{n}__{tag}",
                        {"_ctrl_output": conn.ctrl_output, "_obs_rhs": conn.obs_rhs, "_ctrl_update": conn.ctrl_update,
                         "_res_filter": conn.res_filter, **sizes, **parts}, nogil=True, _nrt=False)
        cache = _cache_dir(kernel)
        remove_stale_cache(cache, f"stage__n{n}__{pair}__", digest)  # the stage function of older versions
        remove_stale_cache(cache, f"advance{lanes}__n{n}__{pair}__", digest)
        _KERNELS[key] = kernel
    return _KERNELS[key]


def kernels_cached(controller: str = "proposed", observer: str = "leso", n: int = 3) -> bool:
    """Whether the closed loop of ``controller`` and ``observer`` for ``n`` joints is compiled for
    the current sources (in numba's disk cache, one arm or a block), without compiling it: how a
    command or the test suite tells a user that a first run compiles before it starts."""
    conn = connect(make_controller(controller), make_observer(observer), n)
    return _is_cached(_specialise(conn, 1)) or _is_cached(_specialise(conn, LANES))


def _choose_lanes(conn: Connection, n_arms: int) -> int:
    """The block width for ``n_arms`` arms when the caller leaves it open: :data:`LANES` for two
    arms or more (two arms in a block of four cost what two single arms cost); for a single arm 1
    (a block would charge it for four), unless only the batch build is compiled already, since
    both give the same numbers and a build costs tens of seconds."""
    if n_arms >= 2:
        return LANES
    if not _is_cached(_specialise(conn, 1)) and _is_cached(_specialise(conn, LANES)):
        return LANES
    return 1


def _layout(conn: Connection) -> dict[str, tuple[int, int]]:
    """:func:`lane_layout` for one connection."""
    return lane_layout(conn.n, conn.n_obs, conn.n_ctrl, conn.n_out, conn.n_fout, len(conn.controller.gains),
                       len(conn.observer.gains), len(conn.filter.gains) if conn.filter is not None else 0)


# ---------------------------------------------------------------------------------------------
# Python-side shells


def _compile_error(conn: Connection, exc: Exception) -> str:
    """A one-paragraph message for a kernel numba could not compile, naming the plug-in at fault
    (each of its functions is compiled alone on the kernel's argument types to find it)."""
    from numba import njit as _njit
    from numba import types as _t

    c, o = conn.controller, conn.observer
    arr = _t.float64[::1]
    for fn, params, owner in ((c.output, c.output_params, f"{c.owner}.output"),
                              (c.update, c.update_params, f"{c.owner}.update"),
                              (o.rhs, o.rhs_params, f"{o.owner}.rhs")):
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
        from blf_gym.results.io import atomic_write_npz

        meta = dict(scenario=self.scenario, controller=self.controller, dt=self.dt,
                    diverged=self.diverged, diverged_at=self.diverged_at)
        atomic_write_npz(path, {**self.signals, **{f"meta_{k}": np.asarray(v if v is not None else np.nan)
                                                  for k, v in meta.items()}})


@dataclass
class Batch:
    """The arms' packed per-arm parameters as the kernel reads them, one row per arm: the plant,
    the controller's nominal model, the reference, the bounds and the law's, observer's and filter's
    gains. Written by :meth:`ClosedLoop.reset`; :attr:`ClosedLoop.batch` gives it to readers."""

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

    ``lanes`` is the number of arms the kernel steps together in one block: 1 or :data:`LANES`.
    Blocks of LANES arms run the per-arm arithmetic on vector registers, about 1.7 times faster
    per arm on a mixed batch of 64 (docs/speed.md), with the same numbers bit for bit. The two are
    separate builds of the kernel, each compiled on first use. The default, None, is
    :func:`_choose_lanes`: blocks for two arms or more, one lane for a single arm unless only the
    batch build is compiled already.
    """

    def __init__(
        self,
        scenarios: Sequence[Scenario],
        controller: str | Controller = "proposed",
        observer: str | Observer = "leso",
        threads: int | None = None,
        residual_filter: "str | ResidualFilter | None" = None,
        plain: bool = False,
        lanes: int | None = None,
    ) -> None:
        if len(scenarios) == 0:
            raise ValueError("ClosedLoop needs at least one scenario")
        if lanes is not None and lanes not in (1, LANES):
            raise ValueError(f"ClosedLoop.lanes must be 1, {LANES} or None (chosen by the arms per thread), "
                             f"got {lanes!r}")
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
        cores = usable_cores()
        if threads is None:
            threads = min(len(scenarios), cores)
        self.threads = check_int("ClosedLoop", "threads", threads, lo=1, hi=cores,
                                 hint=" (the cores this process may use: more threads than cores only wait)")
        self._pool = None
        self._helpers = 0  # threads beside the caller's that step blocks of this batch
        n = self.n
        if self.controller.nominal.n_links != n or self.observer.nominal.n_links != n:
            raise ValueError("controller/observer nominal model must have as many links as the plant")
        self.residual_filter = self.controller.make_filter(residual_filter)
        """The residual filter between the residual and the actuator (None: none)."""
        if plain and self.residual_filter is None:
            raise ValueError("ClosedLoop: plain=True needs a residual filter (it acts on the agent's torque minus the law's)")
        self.plain = bool(plain)
        """With a filter: the residual passed to advance() is the agent's whole torque, and the filter
        sees it minus the law's. A runtime flag: the residual and the plain mode share one build."""
        self.connection = connect(self.controller, self.observer, n, self.residual_filter)
        if lanes is None:
            lanes = _choose_lanes(self.connection, len(scenarios))
        self.lanes = int(lanes)
        """Arms per block of the kernel (1 or :data:`LANES`)."""
        self._kernel = _specialise(self.connection, self.lanes)
        fresh = not _is_cached(self._kernel)
        label = kernel_label(self.controller.name, self.observer.name,
                             self.residual_filter.name if self.residual_filter else None)
        # a batch's kernel and a single arm's are two builds of the same code: say which
        label += ", stepping one arm" if self.lanes == 1 else f", stepping {self.lanes} arms at once"
        if fresh and self._kernel not in _NOTICED:
            _NOTICED.add(self._kernel)
            compile_notice(label, _cache_dir(self._kernel))
        c = self.connection
        self.N = len(scenarios)
        self.nx = STATE.length(n) + c.n_obs + c.n_ctrl
        """State entries per arm: [q, qd, observer states, controller states]."""
        self.X = np.zeros((self.N, self.nx))
        self.ksteps = np.zeros(self.N, dtype=np.int64)
        self.unstable_run = np.zeros(self.N, dtype=np.int64)
        """Per arm, the consecutive integration steps the instability check has failed so far
        (carried across calls, reset with the arm)."""
        self.last = np.zeros((self.N, N_LAST * n + c.n_out + c.n_fout))
        """Per arm, the columns of blf_gym.kernel.status.LAST_COLUMNS (n each), then the controller's
        outputs in its declared order (see :meth:`outputs`)."""
        self._block = _layout(c)["_total"][0] * self.lanes
        self._scratch = np.zeros((-(-self.N // self.lanes), self._block))
        self._zeros_residual = np.zeros((self.N, n))
        self._no_noise = np.zeros((self.N, 0, n))
        self._no_record = np.zeros((self.N, 0, N_CHANNELS, n))
        self.set_scenarios(scenarios)
        if fresh:
            with _compile_lock(self._kernel, label):
                self._compile()  # after another process built it: loaded from numba's cache

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

    @property
    def batch(self) -> Batch:
        """The arms' packed parameters as the kernel reads them (:class:`Batch`), set by
        :meth:`set_scenarios`; the env's observation filler reads the reference and bounds here."""
        return self._batch

    def set_scenarios(self, scenarios: Sequence[Scenario], which: Sequence[int] | None = None,
                      start_steps: Sequence[int] | None = None) -> None:
        """Install scenarios (all, or the arms listed in ``which``) and reset those arms.

        ``start_steps`` (one per reset arm, default all 0) starts an arm at that global integration
        step instead of t = 0: the arm on its reference at that time (angles plus the scenario's
        initial error, the reference's velocities), the observer's ``x2_hat`` (when it has one) at
        those velocities, its other states and the controller's as at t = 0 from those angles; the
        bounds are then those of that time, since they are functions of time. A training aid
        (EnvCore's ``start_time``); 0 is the usual start, unchanged."""
        idx = list(range(self.N)) if which is None else list(which)
        if len(scenarios) != len(idx):
            raise ValueError("one scenario per reset arm is required")
        if start_steps is None:
            start_steps = [0] * len(idx)
        elif len(start_steps) != len(idx):
            raise ValueError("one start step per reset arm is required")
        if not hasattr(self, "_batch"):
            n = self.n
            self._batch = Batch(
                plant=np.zeros((self.N, PLANT.length(n))),
                nominal=np.tile(self.controller.nominal.pack(), (self.N, 1)),
                ref=np.zeros((self.N, REFERENCE.length(n))),
                bnd=np.zeros((self.N, BOUNDS.length())),
                law_gains=np.tile(self.controller.gains, (self.N, 1)),
                obs_gains=np.tile(self.observer.gains, (self.N, 1)),
                filter_gains=np.tile(self.residual_filter.gains if self.residual_filter else np.zeros(0),
                                     (self.N, 1)),
            )
        b = self._batch
        for i, sc, k0 in zip(idx, scenarios, start_steps):
            if sc.arm.n_links != self.n or sc.sim.dt != self.dt or sc.sim.steps_per_sample != self.steps_per_sample:
                raise ValueError("a replacement scenario must keep n links, dt and sample_period")
            if not (isinstance(k0, (int, np.integer)) and 0 <= k0 < sc.sim.n_steps):
                raise ValueError(f"a start step must be an integer in [0, {sc.sim.n_steps}) (the scenario's "
                                 f"integration steps), got {k0!r}")
            b.plant[i] = sc.pack_plant()
            b.ref[i] = sc.pack_reference()
            b.bnd[i] = sc.bounds.pack()
            self._reset_arm(i, sc, int(k0))

    def _reset_arm(self, i: int, sc: Scenario, k0: int = 0) -> None:
        from blf_gym.model.reference import joint_reference

        n = self.n
        q_d0, qd_d0, _ = joint_reference(k0 * self.dt, sc)
        q0 = q_d0 + np.asarray(sc.initial_error)
        no = self.connection.n_obs
        head = STATE.length(n)
        self.X[i] = 0.0
        self.X[i, STATE.slice("q", n)] = q0
        obs0 = self.observer.initial(q0.copy())
        if k0:
            self.X[i, STATE.slice("qd", n)] = qd_d0
            x2 = self.observer.state_offsets(n).get("x2_hat")
            if x2 is not None and x2[1] == n:
                obs0[x2[0] : x2[0] + n] = qd_d0
        self.X[i, head : head + no] = obs0
        self.X[i, head + no :] = self.controller.initial(q0.copy())
        self.ksteps[i] = k0
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
        out: np.ndarray | None = None,
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

        ``out``, a C-contiguous float64 array of shape (N, record_samples, channels, n), receives the
        samples instead of a new array (of arm i, only the first ``nrec[i]`` are written).
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
        if out is not None:
            if (type(out) is not np.ndarray or out.dtype != np.float64 or not out.flags.c_contiguous
                    or out.shape != (N, record_samples, N_CHANNELS, n)):
                raise ValueError(f"out must be a C-contiguous float64 array of shape "
                                 f"{(N, record_samples, N_CHANNELS, n)}")
            rec = out
        else:
            rec = np.zeros((N, record_samples, N_CHANNELS, n)) if record_samples else self._no_record
        nrec = np.zeros(N, dtype=np.int64)
        status = np.empty((N, N_STATUS), dtype=np.int64)  # every column is set by the kernel
        sums = np.empty((N, SUM_E2_JOINT + n))
        b = self._batch
        taken = np.zeros(1, dtype=np.int64)  # blocks taken so far (the kernel's _claim)
        args = (self.X, self.ksteps, int(n_steps), float(self.dt), int(self.steps_per_sample), b.plant, b.nominal,
                b.ref, b.bnd, b.law_gains, b.obs_gains, b.filter_gains, res, nz, bool(terminate), self.plain, rec,
                nrec, status, self.last, self._scratch, sums, self.unstable_run, taken)
        blocks = self._scratch.shape[0]
        if self.threads > 1 and blocks > 1:
            # The kernel releases the GIL: helper threads run it on the same arrays, each block
            # going to whichever thread takes it first, and the caller runs it too (one hand-over
            # fewer). Each arm's arithmetic is the same as alone, whichever thread steps it.
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._helpers = min(self.threads, blocks) - 1
                self._pool = ThreadPoolExecutor(max_workers=self._helpers, thread_name_prefix="blf")
            futures = [self._pool.submit(self._kernel, *args) for _ in range(self._helpers)]
            self._kernel(*args)
            for f in futures:
                f.result()
        else:
            self._kernel(*args)
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
    lanes: int | None = None,
) -> list[Trajectory]:
    """Run whole episodes (each scenario's ``sim.duration``) for N scenarios in one kernel call.

    The law is evaluated at every ODE3 stage; episodes are not terminated on violation (they are
    counted). A diverging arm stops early and its trajectory says so (``diverged``, ``message``).
    ``residual`` (N, n) N m, held over the whole episode, is added to the law's torque, through
    ``residual_filter`` if given (one of the controller's filters). ``lanes`` is
    :class:`ClosedLoop`'s (None: chosen by the number of arms).
    """
    loop = ClosedLoop(scenarios, controller, observer, threads=threads, residual_filter=residual_filter, lanes=lanes)
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
        from blf_gym.model.params import preset

        scenario = preset(scenario)
    traj = simulate_batch([scenario], controller, observer, noise_seeds=[noise_seed], threads=1)[0]
    if traj.diverged and raise_on_divergence:
        raise SimulationDiverged(traj.message)
    return traj

