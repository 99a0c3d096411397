"""Views of the kernel's scratch arrays whose length LLVM sees as a constant.

The closed-loop kernel (:mod:`blf_gym.kernel.simulate`) and the glue generated for plug-ins
(:mod:`blf_gym.plugins.blocks`) cut every per-joint signal out of larger arrays with these, so that each
per-joint loop has a compile-time length.
"""

from __future__ import annotations

from numba import njit
from blf_gym.jit import sources  # noqa: F401  (before any @njit: numba's cache keys on each module's import closure)
from numba import types as nbtypes
from numba.core import cgutils
from numba.core.imputils import impl_ret_borrowed
from numba.extending import intrinsic
from numba.np.arrayobj import populate_array

__all__ = ["fixed", "window"]


@intrinsic
def window(typingctx, arr, start, length):
    """The view arr[start:start+length] of a 1-D contiguous array, built without a bounds clamp
    or a runtime reshape, so that a compile-time ``length`` stays a constant LLVM can see.

    The kernel carves all its scratch views with this: with constant shapes (n = _N is bound at
    specialisation) LLVM unrolls every per-joint loop of the plant, law and observer, and with
    constant offsets from one base pointer it can tell the views apart (no aliasing reloads).
    Callers guarantee ``start + length <= len(arr)`` (lane_layout lays the views out).
    """
    if not (isinstance(arr, nbtypes.Array) and arr.ndim == 1 and arr.layout in ("C", "A")):
        return None
    sig = arr(arr, nbtypes.intp, nbtypes.intp)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        src = context.make_array(aryty)(context, builder, args[0])
        out = context.make_array(aryty)(context, builder)
        if aryty.layout == "C":
            stride = context.get_constant(nbtypes.intp, context.get_abi_sizeof(context.get_data_type(aryty.dtype)))
            data = builder.gep(src.data, [args[1]])
        else:  # a lane's view (see _lane): the same stride, the start counted in strides
            stride = cgutils.unpack_tuple(builder, src.strides)[0]
            raw = builder.gep(builder.bitcast(src.data, cgutils.voidptr_t), [builder.mul(args[1], stride)])
            data = builder.bitcast(raw, src.data.type)
        populate_array(out, data=data, shape=cgutils.pack_array(builder, [args[2]]),
                       strides=cgutils.pack_array(builder, [stride]),
                       itemsize=src.itemsize, meminfo=src.meminfo, parent=src.parent)
        return impl_ret_borrowed(context, builder, aryty, out._getvalue())

    return sig, codegen


@njit(cache=True, error_model="numpy", inline="always")
def fixed(w, start, length):
    """w[start:start+length] with a shape LLVM sees as a constant when ``length`` is one."""
    return window(w, start, length)
