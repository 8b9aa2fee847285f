"""One triangle against a packet of rays, as explicit LLVM vector code.

The watertight test of :mod:`rayaccel.kernels.triangle` (Woop, Benthin, Wald 2013)
with the rays of a packet in the lanes of ``<16 x float>`` vectors: the rays must
share their shear axes ``kx, ky, kz`` (a packet of camera or shadow rays nearly always
does; the caller tests the others one at a time), and then every operation of the
scalar test is one vector operation, in the same order, with the same rounding: the
shear and ``t`` in the rays' precision, the edge functions in float64 (exact products
for float32 rays; rounded products without FMA contraction for float64 rays). A lane's
``t, u, v`` are the scalar test's bit for bit (the tests check it lane by lane).

:data:`packet_triangle` ``(tri, row, kx, ky, kz, lanes, base, mask) -> int32`` tests
triangle ``row`` of ``tri`` (``(n, 9)`` rows, float32 or the rays' precision) for the
lanes of ``mask``.
``lanes`` is the packet's C-contiguous 2D array of the rays' precision; its rows
``base + T_LO``, ... hold each ray's ``t_lo``, current ``t_hit``, shear constants
``Sx, Sy, Sz``, permuted origin ``okx, oky, okz`` and hit coordinates ``u, v``. A lane
whose triangle hit lies in ``[t_lo, t_hit)`` gets ``t_hit, u, v`` replaced and its bit
set in the result; the others are left as they were.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel._jit import FASTMATH
from rayaccel.kernels.aabb_packet import PACKET, lane_row_pointer
from rayaccel.kernels.aabb_wide import splat

# Rows of the packet's lane array from ``base`` on.
T_LO = 0
T_HIT = 1
SHEAR = 2
SHEARED_ORIGIN = 5
U = 8
V = 9
#: Rows the test reads or writes from ``base`` on.
ROWS = 10

#: The fast-math flags of the float64 rays' edge functions: no FMA contraction.
_NO_CONTRACT = tuple(sorted(FASTMATH - {"contract"}))


def _codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
    """Emit the packet triangle test (see the module docstring)."""
    tri_type, _, _, _, _, lanes_type, _, _ = signature.args
    real = lanes_type.dtype
    float_type = context.get_value_type(real)
    vec = ir.VectorType(float_type, PACKET)
    vec64 = ir.VectorType(ir.DoubleType(), PACKET)
    i32 = ir.IntType(32)
    tri_view = context.make_array(tri_type)(context, builder, args[0])
    row = context.cast(builder, args[1], signature.args[1], types.intp)
    axes = [context.cast(builder, args[i], signature.args[i], types.intp) for i in (2, 3, 4)]
    base = context.cast(builder, args[6], signature.args[6], types.intp)
    lane_pointer = lane_row_pointer(context, builder, lanes_type, args[5])

    def pointer(offset: int) -> Any:
        return lane_pointer(builder.add(base, context.get_constant(types.intp, offset)))

    def load(offset: int) -> Any:
        return builder.load(pointer(offset), align=4)

    def corner(vertex: int, axis: Any) -> Any:
        column = builder.add(axis, context.get_constant(types.intp, 3 * vertex))
        item = cgutils.get_item_pointer(
            context, builder, tri_type, tri_view, [row, column], wraparound=False
        )
        value = builder.load(item)
        same = tri_type.dtype == real
        return splat(builder, vec, value if same else builder.fpext(value, float_type))

    ok = [load(SHEARED_ORIGIN + k) for k in range(3)]
    sx, sy, sz = (load(SHEAR + k) for k in range(3))
    # Vertices relative to the origin in the permuted frame, then sheared.
    rel = [[builder.fsub(corner(v, axes[k]), ok[k]) for k in range(3)] for v in range(3)]
    sheared = [
        (builder.fsub(r[0], builder.fmul(sx, r[2])), builder.fsub(r[1], builder.fmul(sy, r[2])))
        for r in rel
    ]
    (ax_, ay_), (bx_, by_), (cx_, cy_) = sheared

    def wide(x: Any) -> Any:
        return x if real == types.float64 else builder.fpext(x, vec64)

    flags = _NO_CONTRACT if real == types.float64 else ()

    def edge(a: Any, b: Any, c: Any, d: Any) -> Any:
        ab = builder.fmul(wide(a), wide(b), flags=flags)
        cd = builder.fmul(wide(c), wide(d), flags=flags)
        return builder.fsub(ab, cd, flags=flags)

    u64 = edge(cx_, by_, cy_, bx_)
    v64 = edge(ax_, cy_, ay_, cx_)
    w64 = edge(bx_, ay_, by_, ax_)
    zero64 = ir.Constant(vec64, [0.0] * PACKET)

    def any_of(cond: str) -> Any:
        parts = [builder.fcmp_ordered(cond, x, zero64) for x in (u64, v64, w64)]
        return builder.or_(builder.or_(parts[0], parts[1]), parts[2])

    mixed = builder.and_(any_of("<"), any_of(">"))
    flat = builder.fcmp_ordered("==", builder.fadd(builder.fadd(u64, v64), w64), zero64)

    def narrow(x: Any) -> Any:
        return x if real == types.float64 else builder.fptrunc(x, vec)

    u, v, w = narrow(u64), narrow(v64), narrow(w64)
    det = builder.fadd(builder.fadd(u, v), w)
    az, bz, cz = (r[2] for r in rel)
    t_scaled = builder.fadd(
        builder.fadd(builder.fmul(u, builder.fmul(sz, az)), builder.fmul(v, builder.fmul(sz, bz))),
        builder.fmul(w, builder.fmul(sz, cz)),
    )
    rcp = builder.fdiv(ir.Constant(vec, [1.0] * PACKET), det)
    t = builder.fmul(t_scaled, rcp)
    t_hit = load(T_HIT)
    inside = builder.and_(
        builder.fcmp_ordered(">=", t, load(T_LO)), builder.fcmp_ordered("<", t, t_hit)
    )
    bits = builder.trunc(args[7], ir.IntType(PACKET))
    active = builder.bitcast(bits, ir.VectorType(ir.IntType(1), PACKET))
    hit = builder.and_(builder.and_(active, inside), builder.not_(builder.or_(mixed, flat)))
    builder.store(builder.select(hit, t, t_hit), pointer(T_HIT), align=4)
    builder.store(builder.select(hit, builder.fmul(v, rcp), load(U)), pointer(U), align=4)
    builder.store(builder.select(hit, builder.fmul(w, rcp), load(V)), pointer(V), align=4)
    return builder.zext(builder.bitcast(hit, ir.IntType(PACKET)), i32)


@intrinsic
def packet_triangle(
    typingctx: Any, tri: Any, row: Any, kx: Any, ky: Any, kz: Any, lanes: Any, base: Any,
    mask: Any,
) -> Any:  # fmt: skip
    """One triangle against the lanes of ``mask`` in vectors (see the module docstring)."""
    if tri.ndim != 2 or tri.dtype not in (types.float32, lanes.dtype):
        raise TypeError("packet triangle test: (n, 9) triangle rows of float32 or the rays' type")
    if lanes.ndim != 2 or lanes.layout != "C" or lanes.dtype not in (types.float32, types.float64):
        raise TypeError("packet triangle test: a C-contiguous 2D float32 or float64 lane array")
    return types.int32(tri, row, kx, ky, kz, lanes, base, types.int32), _codegen
