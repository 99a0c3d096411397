"""The closed loop's compiled templates: the time loop (:func:`advance`), its parts and their helpers.

A build of the kernel (:func:`blf_gym.kernel.simulate.build_source`) is a generated module that
imports this module's helpers, defines the names of :data:`BUILD_NAMES` for one connection
(controller, observer, filter, n) and block width, and holds a copy of the source of each function in
:data:`TEMPLATES`, compiled there with numba (docs/model.md section 6, and the module docstring of
:mod:`blf_gym.kernel.simulate` for why the build is generated source). In this file those names are
placeholders (the section "bound per build" below), so that the templates read, lint and navigate as
ordinary code; they are never compiled or run from here.

State layout per arm, ``X[b]``: ``[q, qd, observer states, controller states]`` (5n with the LESO).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)
from numba import types as nbtypes
from numba.core import cgutils
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic
from numba.np.arrayobj import populate_array

from blf_gym.jit import vmath
from blf_gym.jit.layout import (ARM, CHANNELS, EXP_ARGS, FLAGS, KERNEL_WORK, NOMINAL, PENDING, PLANT, PLANT_TAIL, RECORD,
                                REF, STATE, TAIL, TRIG, TRIG_ARGS, at, part)
from blf_gym.jit.views import fixed
from blf_gym.kernel.reward import SUM_ERR_MAX
from blf_gym.kernel.status import (LAST_SAT, LAST_U, LAST_ULAW, LAST_X3, LAST_X3HAT, N_LAST, ST_ASSUMPTION_FAILURES,
                                   ST_DIVERGED, ST_FILTER_BREACHES, ST_FIRST_VIOL, ST_SAT_STEPS, ST_STEPS, ST_VIOL_SAMPLES,
                                   ST_VIOL_STEPS)
from blf_gym.model.bounds import BOUND_LEN, KA, KB, bounds_exponent, bounds_from, bounds_into
from blf_gym.model.dynamics import (abs_trig_into, coriolis_times_into, gravity_into, ldl_factor_into, ldl_solve_factored,
                                    ldl_solve_into, mass_matrix_into, wrench_torque_into)
from blf_gym.model.reference import reference_angle, reference_from, reference_into
from blf_gym.model.uncertainty import dead_zone, force_active, friction, friction_exponent, friction_from
from blf_gym.plugins.blocks import nominal_length, nominal_terms_into, work_length

__all__ = ["BUILD_NAMES", "CHANNELS", "LANES", "N_CHANNELS", "TEMPLATES", "lane_view"]

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
lane_view = {1: _lane1, LANES: _laneN}
"""The intrinsic :func:`_lane_intrinsic` of each block width a build may have."""


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
def _measure(q, nz, y, n):
    """The measurement y = q + nz of a stage, for one lane; True when it equals q (no noise)."""
    same = True
    for i in range(n):
        y[i] = q[i] + nz[i]
        if y[i] != q[i]:
            same = False
    return same


@njit(cache=True, error_model="numpy", inline="always")
def _stage_trig(ts, q, qd, nz, y, rp, arm, tail, bp, ref, bnd, trig, ntrig, fr, ang, sn, cs, ex, ev, n):
    """The part of a stage evaluation that calls the elementary functions (:mod:`blf_gym.jit.vmath`:
    sin and cos, acos, atan2, exp), for a one-lane build: the measurement y, the reference and the
    bounds at ``ts``, the cos and sin of the plant's and the nominal model's link angles, and the
    friction torques; True when y == q. It runs in a loop of its own, so that the rest of the stage,
    in :func:`advance`, vectorises.

    The 2n + 1 angles (the plant's links, the measured links, the reference's) go through one loop
    of ``sincos`` and the n + 1 exponents (the friction's, the bounds') through one loop of ``exp``,
    padded to whole vectors (``ang``/``sn``/``cs`` and ``ex``/``ev``), so that the single arm's calls
    vectorise. A block's build calls :func:`_stage_trig_lane` instead, whose loop over the lanes
    vectorises; every number is the same function of the same argument either way, so a block's
    arms and single arms agree bit for bit. (Two functions, not one with a flag: the build's
    ``LN == 1`` test is pruned before numba inlines, so a build copies only the one it runs, and
    numba's inlining copies a function's whole IR once per block of it.)"""
    same = _measure(q, nz, y, n)
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
    return same


@njit(cache=True, error_model="numpy", inline="always")
def _stage_trig_lane(ts, q, qd, nz, y, rp, arm, tail, bp, ref, bnd, trig, ntrig, fr, n):
    """:func:`_stage_trig` for one lane of a block (a build of several lanes): the same numbers,
    each elementary function called once per argument, in the loop over the block's lanes."""
    same = _measure(q, nz, y, n)
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


# per-lane flags of a block (floats, 1.0 true): blf_gym.jit.layout.FLAGS
(_F_NOISY, _F_PENDING, _F_HALT, _F_CHECK, _F_OK, _F_STOPPED, _F_K0, _F_SAME_ARM, _F_SAME_Y) = (FLAGS.index(f) for f in (
    "noisy", "pending", "halt", "check", "ok", "stopped", "k0", "same_arm", "same_y"))
_N_FLAGS = FLAGS.length()


# ---------------------------------------------------------------------------------------------
# bound per build: placeholders here (a build's module assigns each its value above its copy of the
# templates; tests/test_codegen.py checks that these are exactly the names a build defines)

_N = _NO = _NC = _NX = _NOUT = _NFOUT = _LN = 0  # joints, observer and controller states, state, outputs, lanes
_X1H = _X2H = _X3H = _BREACH = _ASSUME = -1  # the observer's estimates' and the filter's monitors' offsets
_FILTER = False  # a residual filter between the residual and the actuator
_NPL = _NRP = _NBP = _NLG = _NOG = _NFG = _NPW = _NANG = _NEX = _NREF = _NSMP = 0  # sizes of the block's parts
(_L_K0, _L_K1, _L_K2, _L_K3, _L_dx, _L_xs, _L_xn, _L_ep, _L_x, _L_y, _L_nz, _L_ref, _L_bnd, _L_u, _L_hu, _L_satf, _L_x3,
 _L_cout, _L_fout, _L_rr, _L_Mp, _L_Lp, _L_nom, _L_pw, _L_wl, _L_wo, _L_smp, _L_fr, _L_res, _L_plant, _L_rp, _L_bp,
 _L_lg, _L_og, _L_fg, _L_ts, _L_flags, _L_ang, _L_sn, _L_cs, _L_ex, _L_ev) = (0,) * 42  # the block's parts' offsets


def _unbound(*args):
    """A placeholder for a function a build binds."""
    raise RuntimeError("a template runs only as a build's copy (blf_gym.kernel.simulate)")


_lane = _lane1  # the lane view of the build's width
_ctrl_output = _obs_rhs = _ctrl_update = _res_filter = _unbound  # the plug-ins' glue
accumulate_sample = _unbound  # the reward's per-sample sums, written from blf_gym.kernel.reward.TERMS

BUILD_NAMES = ("_N", "_NO", "_NC", "_NX", "_NOUT", "_NFOUT", "_LN", "_X1H", "_X2H", "_X3H", "_BREACH", "_ASSUME",
               "_FILTER", "_NPL", "_NRP", "_NBP", "_NLG", "_NOG", "_NFG", "_NPW", "_NANG", "_NEX", "_NREF", "_NSMP",
               *(f"_L_{k}" for k in ("K0", "K1", "K2", "K3", "dx", "xs", "xn", "ep", "x", "y", "nz", "ref", "bnd", "u",
                                     "hu", "satf", "x3", "cout", "fout", "rr", "Mp", "Lp", "nom", "pw", "wl", "wo", "smp",
                                     "fr", "res", "plant", "rp", "bp", "lg", "og", "fg", "ts", "flags", "ang", "sn", "cs",
                                     "ex", "ev")),
               "_lane", "_ctrl_output", "_obs_rhs", "_ctrl_update", "_res_filter", "accumulate_sample")
"""The names a build's module defines before its copy of :data:`TEMPLATES`."""


# long: the kernel's time loop is one compiled function (the parts it calls are inlined into it, and
# a split of its stage evaluation would put the lanes' state through argument tuples)
def advance(X, ksteps, n_steps, dt, sps, plant, nominal, rp, bp, lg, og, fgains, residual,
                    noise, terminate, plain, rec, nrec, status, last, scratch, sums, unstable_run, taken):
    """Advance every arm b by up to ``n_steps`` ODE3 steps from global step ``ksteps[b]``, the arms
    in blocks of ``_LN`` lanes stepped in lockstep (``scratch[k]`` is block k, laid out by
    :func:`lane_layout`, lanes innermost).

    A block is loaded (:func:`_load_block`), stepped, and stored back
    (:func:`_store_block`). One step is: its lanes' inputs (:func:`_begin_step`),
    the stage evaluations (:func:`_stage_input`, :func:`_stage_trig` or :func:`_stage_trig_lane` and the rest of the right-hand
    side, in two loops over the lanes), the step's bookkeeping at its start
    (:func:`_sample`: violations, the reward's sums, the record), the update
    (:func:`_ode3_update`), the instability check (:func:`_check_stability`) and the commit
    (:func:`_commit`). The parts are copied into the build's module with it and inlined (the load and
    the store, which run once a call, are called: :data:`ONCE_A_CALL`). Every lane
    computes every stage the block needs; a lane's own control
    flow (stopped, noisy, first-same-as-last, instability checks) only decides what it keeps, so
    each arm's numbers are those it would get alone.

    The rest of a stage evaluation at (ts, x), for one lane, into ``dx``: branch-free where the lanes
    may differ, so that its loop over the lanes vectorises. The measurement is y = q(stage) + noise,
    the noise sample held over the step, so without noise the law and the observer see the angles at
    every stage like Simulink's continuous blocks. ``x`` = [q, qd, observer states, controller
    states]. ``_ctrl_output``, ``_obs_rhs`` and ``_ctrl_update`` are the generated glue of
    :func:`blf_gym.plugins.blocks.connect`, bound with the sizes ``_N``, ``_NO``, ``_NC`` by
    the build (:data:`BUILD_NAMES`); with a residual filter (``_FILTER``), ``_res_filter`` turns the residual
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
    n = _N  # the number of joints, a compile-time constant bound at specialisation
    nx = _NX
    LN = _LN  # lanes per block
    n_blocks = (N + LN - 1) // LN
    while True:
        block = _claim(taken)
        if block >= n_blocks:
            break
        work = scratch[block]
        arm0 = block * LN
        _load_block(work, arm0, N, n_steps, X, ksteps, plant, nominal, rp, bp, lg, og, fgains, residual, noise,
                    status, sums)
        any_fsal = False  # every active lane's stage 0 is its last step's check evaluation
        for j in range(n_steps):
            n_active, any_check = _begin_step(work, arm0, N, j, sps, noise)
            if n_active == 0:
                break
            for stage in range(4):
                if stage == 0 and any_fsal:
                    # the check's evaluation at this state, with these inputs, was last step's: K3
                    for b in range(LN):
                        _copy(_lane(work, _L_K3, nx, b), _lane(work, _L_K0, nx, b))
                elif stage == 3:
                    # the update; a lane whose state turns non-finite or leaves the limit halts
                    for b in range(LN):
                        flags = _lane(work, _L_flags, _N_FLAGS, b)
                        plant_l = _lane(work, _L_plant, _NPL, b)
                        ok = _ode3_update(_lane(work, _L_x, nx, b), _lane(work, _L_K0, nx, b), _lane(work, _L_K1, nx, b),
                                          _lane(work, _L_K2, nx, b), dt, plant_l[at(_P_DIVLIM, n)],
                                          _lane(work, _L_xn, nx, b), _lane(work, _L_ep, nx, b))
                        flags[_F_OK] = 1.0 if ok else 0.0
                    if not any_check:
                        break
                if stage > 0 or not any_fsal:
                    # the stage's time and state, then the two parts of the evaluation, each a
                    # loop over the lanes with the same code for every lane (they vectorise)
                    for b in range(LN):
                        flags = _lane(work, _L_flags, _N_FLAGS, b)
                        xs = _lane(work, _L_xs, nx, b)
                        if stage < 3:
                            _stage_input(stage, _lane(work, _L_x, nx, b), _lane(work, _L_K0, nx, b), _lane(work, _L_K1, nx, b), dt,
                                         xs)
                        else:
                            _copy(_lane(work, _L_xn, nx, b), xs)
                        k = np.int64(flags[_F_K0]) + j
                        t = k * dt
                        _lane(work, _L_ts, 1, b)[0] = (t if stage == 0 else (t + 0.5 * dt if stage == 1 else
                                                    (t + 0.75 * dt if stage == 2 else (k + 1) * dt)))
                    for b in range(LN):
                        ts_b = _lane(work, _L_ts, 1, b)[0]
                        q_b = _lane(work, _L_xs + at(_S_Q, n), n, b)
                        qd_b = _lane(work, _L_xs + at(_S_QD, n), n, b)
                        nz_b, y_b = _lane(work, _L_nz, n, b), _lane(work, _L_y, n, b)
                        rp_b, bp_b = _lane(work, _L_rp, _NRP, b), _lane(work, _L_bp, _NBP, b)
                        arm_b = _lane(work, _L_plant + at(_P_ARM, n), at(_SIZE_ARM, n), b)
                        tail_b = _lane(work, _L_plant + at(_P_TAIL, n), at(_SIZE_TAIL, n), b)
                        ref_b, bnd_b = _lane(work, _L_ref, _NREF, b), _lane(work, _L_bnd, BOUND_LEN, b)
                        trig_b = _lane(work, _L_pw + at(_KW_TRIG, n), at(_SIZE_TRIG, n), b)
                        ntrig_b = _lane(work, _L_nom + at(_NOM_TRIG, n), at(_SIZE_TRIG, n), b)
                        fr_b = _lane(work, _L_fr, n, b)
                        if LN == 1:  # a compile-time constant: the build inlines one of the two
                            same_y = _stage_trig(ts_b, q_b, qd_b, nz_b, y_b, rp_b, arm_b, tail_b, bp_b, ref_b, bnd_b,
                                                 trig_b, ntrig_b, fr_b, _lane(work, _L_ang, _NANG, b),
                                                 _lane(work, _L_sn, _NANG, b), _lane(work, _L_cs, _NANG, b),
                                                 _lane(work, _L_ex, _NEX, b), _lane(work, _L_ev, _NEX, b), n)
                        else:
                            same_y = _stage_trig_lane(ts_b, q_b, qd_b, nz_b, y_b, rp_b, arm_b, tail_b, bp_b, ref_b,
                                                      bnd_b, trig_b, ntrig_b, fr_b, n)
                        _lane(work, _L_flags, _N_FLAGS, b)[_F_SAME_Y] = 1.0 if same_y else 0.0
                    for b in range(LN):
                        # the rest of the evaluation at (tb, xs) into dx, written here rather than
                        # inlined from a function of its own: numba copies an inlined function's
                        # whole IR, and this part, with the plug-ins in it, is most of the kernel
                        tb = _lane(work, _L_ts, 1, b)[0]
                        flags_b = _lane(work, _L_flags, _N_FLAGS, b)
                        copy_model = LN == 1 and flags_b[_F_SAME_ARM] != 0.0 and flags_b[_F_SAME_Y] != 0.0
                        x = _lane(work, _L_xs, nx, b)
                        y = _lane(work, _L_y, n, b)
                        res = _lane(work, _L_res, n, b)
                        plant_b = _lane(work, _L_plant, _NPL, b)
                        nom = _lane(work, _L_nom, nominal_length(n), b)
                        lgb = _lane(work, _L_lg, _NLG, b)
                        ogb = _lane(work, _L_og, _NOG, b)
                        fg = _lane(work, _L_fg, _NFG, b)
                        ref = _lane(work, _L_ref, _NREF, b)
                        bnd = _lane(work, _L_bnd, BOUND_LEN, b)
                        cout = _lane(work, _L_cout, _NOUT, b)
                        fout = _lane(work, _L_fout, _NFOUT, b)
                        rr = _lane(work, _L_rr, n, b)
                        u = _lane(work, _L_u, n, b)
                        hu = _lane(work, _L_hu, n, b)
                        satf = _lane(work, _L_satf, n, b)
                        dx = _lane(work, _L_dx, nx, b)  # a constant offset: see below
                        pw = _lane(work, _L_pw, _NPW, b)
                        Mp = _lane(work, _L_Mp, n * n, b)
                        Lp = _lane(work, _L_Lp, n * n, b)
                        wl = _lane(work, _L_wl, work_length(n), b)
                        wo = _lane(work, _L_wo, work_length(n), b)
                        fr = _lane(work, _L_fr, n, b)
                        arm = part(plant_b, _P_ARM, _SIZE_ARM, n)
                        q = part(x, _S_Q, _SIZE_N, n)
                        qd = part(x, _S_QD, _SIZE_N, n)
                        xo = fixed(x, at(_S_OBS, n), _NO)
                        xc = fixed(x, at(_S_OBS, n) + _NO, _NC)
                        dxo = fixed(dx, at(_S_OBS, n), _NO)
                        dxc = fixed(dx, at(_S_OBS, n) + _NO, _NC)
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
                        _ctrl_output(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wl)
                        if _FILTER:  # compile-time constant
                            for i in range(n):
                                rr[i] = res[i] - cout[i] if plain else res[i]
                            _res_filter(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wl)
                        for i in range(n):
                            ui = cout[i] + (fout[i] if _FILTER else res[i])
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
                        _obs_rhs(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wo)
                        _ctrl_update(tb, y, q, qd, xo, xc, ref, bnd, nom, ogb, lgb, fg, u, cout, rr, fout, umax, dxo, dxc, wl)
                    # into K0..K3: apart, since a view at an offset that depends on stage would keep
                    # LLVM from proving the lanes of the loop above independent
                    for b in range(LN):
                        _copy(_lane(work, _L_dx, nx, b), _lane(work, _L_K0 + stage * nx, nx, b))
                if stage == 3:
                    _check_stability(work, arm0, dt, sps, sums, status, unstable_run)
                    continue
                if stage > 0:
                    continue
                _sample(work, arm0, j, dt, sps, terminate, nominal, rec, nrec, status, last, sums, unstable_run)
            any_fsal = _commit(work, arm0, j, n_steps, status)
        _store_block(work, arm0, N, dt, terminate, X, ksteps, nominal, status, last, unstable_run)


def _load_block(work, arm0, N, n_steps, X, ksteps, plant, nominal, rp, bp, lg, og, fgains, residual, noise,
                         status, sums):
    """Load block ``work``'s lanes from the arms ``arm0``, ``arm0 + 1``, ... (a padding lane past the
    last arm copies the block's first arm and stays inactive); clear their flags, status and sums."""
    n = _N
    nx = _NX
    LN = _LN
    has_noise = noise.shape[1] > 0

    for b in range(LN):
        a = arm0 + b if arm0 + b < N else arm0
        _copy(X[a], _lane(work, _L_x, nx, b))
        _copy(plant[a], _lane(work, _L_plant, _NPL, b))
        nom = _lane(work, _L_nom, nominal_length(n), b)
        same_arm = True
        for i in range(at(_SIZE_ARM, n)):
            nom[at(_NOM_ARM, n) + i] = nominal[a, i]
            if nominal[a, i] != plant[a, at(_P_ARM, n) + i]:
                same_arm = False
        _copy(rp[a], _lane(work, _L_rp, _NRP, b))
        _copy(bp[a], _lane(work, _L_bp, _NBP, b))
        _copy(lg[a], _lane(work, _L_lg, _NLG, b))
        _copy(og[a], _lane(work, _L_og, _NOG, b))
        _copy(fgains[a], _lane(work, _L_fg, _NFG, b))
        _copy(residual[a], _lane(work, _L_res, n, b))
        flags = _lane(work, _L_flags, _N_FLAGS, b)
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


def _begin_step(work, arm0, N, j, sps, noise):
    """Per lane, at step ``j`` of the call: the step's noise sample, whether its instability check
    runs; returns (the lanes still going, whether any of them checks)."""
    n = _N
    LN = _LN
    has_noise = noise.shape[1] > 0

    n_active = 0
    any_check = False
    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)
        if flags[_F_STOPPED] == 0.0:
            flags[_F_HALT] = 0.0
        k = np.int64(flags[_F_K0]) + j
        check = flags[_F_NOISY] == 0.0 or (k + 1) % sps == 0
        flags[_F_CHECK] = 1.0 if check else 0.0
        nz = _lane(work, _L_nz, n, b)
        a = arm0 + b if arm0 + b < N else arm0
        for i in range(n):
            nz[i] = noise[a, j, i] if has_noise else 0.0
        if flags[_F_STOPPED] == 0.0:
            n_active += 1
            if check:
                any_check = True
    return n_active, any_check


def _check_stability(work, arm0, dt, sps, sums, status, unstable_run):
    """After a step's update, per checking lane: ODE3's embedded error estimate against its
    tolerance (:func:`_error_ratio`), its running maximum, and the count of consecutive unstable
    steps (:func:`_instability`), which flags a divergence (code 2)."""
    n = _N
    nx = _NX
    LN = _LN

    # the embedded error estimate grows without bound when h is outside ODE3's
    # stability region, even when the actuator limit keeps the state finite
    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)
        if flags[_F_STOPPED] != 0.0 or flags[_F_HALT] != 0.0 or flags[_F_OK] == 0.0 or flags[_F_CHECK] == 0.0:
            continue
        a = arm0 + b
        plant_l = _lane(work, _L_plant, _NPL, b)
        en = _error_ratio(_lane(work, _L_ep, nx, b), _lane(work, _L_K3, nx, b), _lane(work, _L_xn, nx, b), dt,
                          plant_l[at(_P_ATOL, n)], plant_l[at(_P_RTOL, n)])
        if en > sums[a, SUM_ERR_MAX]:
            sums[a, SUM_ERR_MAX] = en
        err_run, unstable = _instability(en, flags[_F_NOISY] != 0.0, sps, unstable_run[a],
                                         plant_l[at(_P_UNSTABLE, n)])
        unstable_run[a] = err_run
        if unstable:
            status[a, ST_DIVERGED] = 2


def _sample(work, arm0, j, dt, sps, terminate, nominal, rec, nrec, status, last, sums, unstable_run):
    """Per lane, at step ``j``'s start time (state x, after its first stage evaluation): the
    violation and saturation bookkeeping (:func:`_step_bookkeeping`), the filter's monitors; at a
    1 ms sample also the true lumped disturbance, the reward's sums (``accumulate_sample``,
    :func:`blf_gym.kernel.reward.accumulate_source`) and the record; then the last applied signals."""
    n = _N
    nx = _NX
    LN = _LN

    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)
        if flags[_F_STOPPED] != 0.0:
            continue
        a = arm0 + b
        k = np.int64(flags[_F_K0]) + j
        x = _lane(work, _L_x, nx, b)
        ref = _lane(work, _L_ref, _NREF, b)
        bnd = _lane(work, _L_bnd, BOUND_LEN, b)
        u = _lane(work, _L_u, n, b)
        satf = _lane(work, _L_satf, n, b)
        cout = _lane(work, _L_cout, _NOUT, b)
        fout = _lane(work, _L_fout, _NFOUT, b)
        st_b = status[a]
        last_b = last[a]
        if _step_bookkeeping(j, k, x, ref, bnd, satf, terminate, st_b, n):
            flags[_F_HALT] = 1.0
            if unstable_run[a] > 0:
                # the bound broke while ODE3's error estimate was above tolerance: the
                # integration's violation, not the arm's (code 3, a divergence)
                st_b[ST_DIVERGED] = 3
            continue
        if _BREACH >= 0 and fout[_BREACH] > 0.0:  # the filter's own monitors
            st_b[ST_FILTER_BREACHES] += 1
        if _ASSUME >= 0 and fout[_ASSUME] < 0.5:
            st_b[ST_ASSUMPTION_FAILURES] += 1
        if k % sps == 0:
            # a 1 ms sample: the true lumped disturbance, the reward/metric sums, the record
            y = _lane(work, _L_y, n, b)
            x3 = _lane(work, _L_x3, n, b)
            K0 = _lane(work, _L_K0, nx, b)
            recording = nrec[a] < rec.shape[1]
            nom_a = nominal[a]
            if recording:
                _lumped_true(part(x, _S_Q, _SIZE_N, n), part(x, _S_QD, _SIZE_N, n), part(K0, _S_QD, _SIZE_N, n), u, nom_a,
                             x3, _lane(work, _L_Mp, n * n, b),
                             _lane(work, _L_Lp, n * n, b), _lane(work, _L_pw, _NPW, b))
                for i in range(n):
                    last_b[LAST_X3 * n + i] = x3[i]
            else:
                pending = _lane(work, _L_smp, _NSMP, b)
                for i in range(n):
                    pending[at(_PD_Q, n) + i] = x[at(_S_Q, n) + i]
                    pending[at(_PD_QD, n) + i] = x[at(_S_QD, n) + i]
                    pending[at(_PD_QDD, n) + i] = K0[at(_S_QD, n) + i]
                    pending[at(_PD_U, n) + i] = u[i]
                flags[_F_PENDING] = 1.0
            plant_l = _lane(work, _L_plant, _NPL, b)
            if accumulate_sample(x, y, ref, bnd, u, cout, plant_l[at(_P_UMAX, n)], sums[a], n):
                st_b[ST_VIOL_SAMPLES] += 1
            for i in range(n):
                last_b[LAST_X3HAT * n + i] = x[_X3H + i] if _X3H >= 0 else np.nan
            if recording:
                _record(rec[a, nrec[a]], k * dt, x, y, ref, bnd, u, _lane(work, _L_hu, n, b), cout[:n], satf,
                        x3, _X1H, _X2H, _X3H)
                nrec[a] += 1
        for i in range(n):
            last_b[LAST_U * n + i] = u[i]
            last_b[LAST_ULAW * n + i] = cout[i]
            last_b[LAST_SAT * n + i] = satf[i]
        for i in range(_NOUT):
            last_b[N_LAST * n + i] = cout[i]
        for i in range(_NFOUT):
            last_b[N_LAST * n + _NOUT + i] = fout[i]


def _commit(work, arm0, j, n_steps, status):
    """Per lane, after step ``j``: keep the new state or flag the divergence, stop lanes that halted;
    returns whether every going lane may reuse its check evaluation as the next step's first one
    (first-same-as-last)."""
    nx = _NX
    LN = _LN

    any_fsal = True
    for b in range(LN):
        flags = _lane(work, _L_flags, _N_FLAGS, b)
        if flags[_F_STOPPED] != 0.0:
            continue
        a = arm0 + b
        if flags[_F_HALT] == 0.0 and flags[_F_OK] == 0.0:
            status[a, ST_DIVERGED] = 1
        if flags[_F_HALT] == 0.0 and flags[_F_OK] != 0.0:
            _copy(_lane(work, _L_xn, nx, b), _lane(work, _L_x, nx, b))
            status[a, ST_STEPS] += 1
        if flags[_F_HALT] != 0.0 or status[a, ST_DIVERGED] != 0:
            flags[_F_STOPPED] = 1.0
            continue
        # first-same-as-last: the check's evaluation is the next step's first one when the
        # inputs are the same (no noise, and the residual is held for the whole call)
        if not (flags[_F_CHECK] != 0.0 and flags[_F_NOISY] == 0.0 and j + 1 < n_steps):
            any_fsal = False
    return any_fsal


def _store_block(work, arm0, N, dt, terminate, X, ksteps, nominal, status, last, unstable_run):
    """After the call's last step, per arm of the block: a pending sample's true disturbance, the
    end state's violation check, and the state and step counter back into ``X`` and ``ksteps``."""
    n = _N
    nx = _NX
    LN = _LN

    for b in range(LN):
        a = arm0 + b
        if a >= N:
            continue
        flags = _lane(work, _L_flags, _N_FLAGS, b)
        x = _lane(work, _L_x, nx, b)
        x3 = _lane(work, _L_x3, n, b)
        last_b = last[a]
        st_b = status[a]
        if flags[_F_PENDING] != 0.0:
            pending = _lane(work, _L_smp, _NSMP, b)
            _lumped_true(part(pending, _PD_Q, _SIZE_N, n), part(pending, _PD_QD, _SIZE_N, n),
                         part(pending, _PD_QDD, _SIZE_N, n), part(pending, _PD_U, _SIZE_N, n), nominal[a], x3,
                         _lane(work, _L_Mp, n * n, b), _lane(work, _L_Lp, n * n, b), _lane(work, _L_pw, _NPW, b))
            for i in range(n):
                last_b[LAST_X3 * n + i] = x3[i]
        steps = st_b[ST_STEPS]
        k0 = np.int64(flags[_F_K0])
        if flags[_F_STOPPED] == 0.0:
            t_end = (k0 + steps) * dt
            ref = _lane(work, _L_ref, _NREF, b)
            bnd = _lane(work, _L_bnd, BOUND_LEN, b)
            plant_l = _lane(work, _L_plant, _NPL, b)
            reference_into(t_end, _lane(work, _L_rp, _NRP, b), part(plant_l, _P_ARM, _SIZE_ARM, n), ref)
            bounds_into(t_end, _lane(work, _L_bp, _NBP, b), bnd)
            if _violates(x, ref, bnd, n):
                st_b[ST_VIOL_STEPS] += 1
                if st_b[ST_FIRST_VIOL] < 0:
                    st_b[ST_FIRST_VIOL] = k0 + steps
                if terminate and unstable_run[a] > 0:
                    st_b[ST_DIVERGED] = 3  # as above: this violation ends the episode, on an unstable integration
        _copy(x, X[a])
        ksteps[a] = k0 + steps


TEMPLATES = (_load_block, _begin_step, _check_stability, _sample, _commit, _store_block, advance)
"""The functions a build copies, in order: the parts (inlined into the loop, or called: :data:`ONCE_A_CALL`),
then the loop."""

ONCE_A_CALL = (_load_block, _store_block)
"""The parts a build calls instead of inlining: they run once per block and call, not once a step, so a
call costs nothing measurable, while inlining them cost a third of a build's compile time (numba copies
an inlined function's whole IR, once per block of it: benchmarks/compile_time.py)."""
