"""The per-ray constants of a packet of rays, computed in LLVM vectors.

:func:`rayaccel.trace.ray_setup.ray_prologue_py` for the sixteen rays of a packet at
once: each quantity is one ``<16 x float>`` operation over the rays (the reciprocal
direction, the watertight test's shear axes and constants, Woop et al. 2013, the sheared
origin, the culling pad and the hit interval), with every operation of the scalar code
in the same order, so each lane's values are the scalar prologue's bit for bit (the
tests check it lane by lane). The scalar prologue's four divisions and dozen selects
per ray become that many vector operations per packet.

:data:`packet_setup` ``(origin, direction, tmin, tmax, first, last, root_box, lanes,
pad_row, base, axes) -> int32`` reads rays ``first`` to ``first + 15`` (those from
``last`` on repeat ray ``last - 1`` and stay out of the result) and writes, lane by
lane, rows 0 to 5 of ``lanes`` (origin and reciprocal direction, the rows of
:data:`rayaccel.kernels.aabb_packet.packet_slab_test`; its ``lo`` and ``hi`` rows are the
caller's, set per descent), the culling pad in row ``pad_row``, and from row ``base``
on the rows of :data:`rayaccel.kernels.triangle_packet.packet_triangle` (``t_lo``,
``t_hit``, shear, sheared origin, ``u = v = 0``). ``axes`` (int64, rows of 16 lanes)
gets ``kx, ky, kz`` and the octant (bit 0, 1, 2 set for a negative ``x, y, z``
direction) in rows 0 to 3. The result has bit ``i`` set for a valid ray (finite origin
and direction, a non-zero direction, ``tmin <= tmax``).
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel.kernels.aabb import INTERVAL_SLACK
from rayaccel.kernels.aabb_packet import (
    INVERSE_ROW,
    ORIGIN_ROW,
    PACKET,
    lane_row_pointer,
)
from rayaccel.kernels.aabb_wide import splat
from rayaccel.kernels.triangle_packet import SHEAR, SHEARED_ORIGIN, T_HIT, T_LO, U, V

#: Rows of ``axes``.
KX, KY, KZ, OCTANT = range(4)


def _codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
    """Emit the packet's prologue (see the module docstring)."""
    origin_t, direction_t, tmin_t, tmax_t = signature.args[:4]
    root_t, lanes_t = signature.args[6:8]
    axes_t = signature.args[10]
    real = lanes_t.dtype
    float_type = context.get_value_type(real)
    vec = ir.VectorType(float_type, PACKET)
    i32, i64 = ir.IntType(32), ir.IntType(64)
    ivec = ir.VectorType(i64, PACKET)
    bvec = ir.VectorType(ir.IntType(1), PACKET)
    intp = types.intp

    def as_intp(i: int) -> Any:
        return context.cast(builder, args[i], signature.args[i], intp)

    first, last = as_intp(4), as_intp(5)
    one = context.get_constant(intp, 1)
    # Ray of each lane: first + lane, repeating the last ray past ``last``.
    rows = []
    in_batch = ir.Constant(bvec, [0] * PACKET)
    for lane in range(PACKET):
        r = builder.add(first, context.get_constant(intp, lane))
        inside = builder.icmp_signed("<", r, last)
        rows.append(builder.select(inside, r, builder.sub(last, one)))
        in_batch = builder.insert_element(in_batch, inside, ir.Constant(i32, lane))

    def gather(array_type: Any, value: Any, column: int | None) -> Any:
        view = context.make_array(array_type)(context, builder, value)
        out = ir.Constant(vec, ir.Undefined)
        for lane, r in enumerate(rows):
            index = [r] if column is None else [r, context.get_constant(intp, column)]
            item = cgutils.get_item_pointer(context, builder, array_type, view, index,
                                            wraparound=False)  # fmt: skip
            loaded = builder.load(item)
            if array_type.dtype != real:
                loaded = builder.fpext(loaded, float_type)
            out = builder.insert_element(out, loaded, ir.Constant(i32, lane))
        return out

    o = [gather(origin_t, args[0], a) for a in range(3)]
    d = [gather(direction_t, args[1], a) for a in range(3)]
    t_lo = gather(tmin_t, args[2], None)
    t_max = gather(tmax_t, args[3], None)

    def const(x: float) -> Any:
        return ir.Constant(vec, [x] * PACKET)

    def iconst(x: int) -> Any:
        return ir.Constant(ivec, [x] * PACKET)

    fabs = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(vec, [vec]),
        f"llvm.fabs.v{PACKET}{'f64' if real == types.float64 else 'f32'}",
    )  # fmt: skip

    def absolute(x: Any) -> Any:
        return builder.call(fabs, [x])

    # t_hit = next_up(tmax): the bits step by one away from zero ... as _jit._next_up.
    width = 64 if real == types.float64 else 32
    bits_t = ir.VectorType(ir.IntType(width), PACKET)
    bits = builder.bitcast(t_max, bits_t)
    positive = builder.icmp_signed(">=", bits, ir.Constant(bits_t, [0] * PACKET))
    stepped = builder.select(positive, builder.add(bits, ir.Constant(bits_t, [1] * PACKET)),
                             builder.sub(bits, ir.Constant(bits_t, [1] * PACKET)))  # fmt: skip
    is_zero = builder.fcmp_ordered("==", t_max, const(0.0))
    stepped = builder.bitcast(
        builder.select(is_zero, ir.Constant(bits_t, [1] * PACKET), stepped), vec
    )
    keep = builder.or_(builder.fcmp_unordered("uno", t_max, t_max),
                       builder.fcmp_ordered("==", t_max, const(float("inf"))))  # fmt: skip
    t_hit = builder.select(keep, t_max, stepped)
    # Valid: tmin <= tmax, a non-zero direction, finite origin and direction.
    valid = builder.fcmp_ordered("<=", t_lo, t_max)
    zero_dir = builder.and_(
        builder.and_(builder.fcmp_ordered("==", d[0], const(0.0)),
                     builder.fcmp_ordered("==", d[1], const(0.0))),
        builder.fcmp_ordered("==", d[2], const(0.0)),
    )  # fmt: skip
    valid = builder.and_(valid, builder.not_(zero_dir))
    for x in (*d, *o):
        valid = builder.and_(valid, builder.fcmp_ordered("<", absolute(x), const(float("inf"))))
    valid = builder.and_(valid, in_batch)
    # Reciprocal direction and the octant.
    inverse = [builder.fdiv(const(1.0), x) for x in d]
    octant = iconst(0)
    for axis in range(3):
        negative = builder.not_(builder.fcmp_ordered(">=", inverse[axis], const(0.0)))
        octant = builder.or_(octant, builder.select(negative, iconst(1 << axis), iconst(0)))
    # Shear axes: kz the dominant axis, kx and ky the next ones, swapped for a negative d[kz].
    ax, ay, az = (absolute(x) for x in d)
    on_y = builder.and_(builder.fcmp_ordered(">", ay, ax), builder.fcmp_ordered(">=", ay, az))
    on_z = builder.and_(
        builder.not_(on_y),
        builder.and_(builder.fcmp_ordered(">", az, ax), builder.fcmp_ordered(">", az, ay)),
    )
    kz = builder.select(on_y, iconst(1), builder.select(on_z, iconst(2), iconst(0)))
    dkz = builder.select(on_y, d[1], builder.select(on_z, d[2], d[0]))

    def next_axis(k: Any) -> Any:
        return builder.select(builder.icmp_signed("==", k, iconst(2)), iconst(0),
                              builder.add(k, iconst(1)))  # fmt: skip

    kx = next_axis(kz)
    ky = next_axis(kx)
    flip = builder.fcmp_ordered("<", dkz, const(0.0))
    kx, ky = builder.select(flip, ky, kx), builder.select(flip, kx, ky)

    def pick(k: Any, values: list[Any]) -> Any:
        is_0 = builder.icmp_signed("==", k, iconst(0))
        is_1 = builder.icmp_signed("==", k, iconst(1))
        return builder.select(is_0, values[0], builder.select(is_1, values[1], values[2]))

    shear = [builder.fdiv(pick(kx, d), dkz), builder.fdiv(pick(ky, d), dkz),
             builder.fdiv(const(1.0), dkz)]  # fmt: skip
    sheared_origin = [pick(kx, o), pick(ky, o), pick(kz, o)]
    # Culling pad: max(|lo_kz - o_kz|, |hi_kz - o_kz|) * |Sz| * slack (kernels/aabb.py).
    root_view = context.make_array(root_t)(context, builder, args[6])

    def root(i: int) -> Any:
        index = [context.get_constant(intp, i)]
        item = cgutils.get_item_pointer(context, builder, root_t, root_view, index,
                                        wraparound=False)  # fmt: skip
        value = builder.load(item)
        wide = value if root_t.dtype == real else builder.fpext(value, float_type)
        return splat(builder, vec, wide)

    lo_kz = pick(kz, [root(0), root(2), root(4)])
    hi_kz = pick(kz, [root(1), root(3), root(5)])
    below = absolute(builder.fsub(lo_kz, sheared_origin[2]))
    above = absolute(builder.fsub(hi_kz, sheared_origin[2]))
    # numba's max(a, b) for floats: ``b`` unless ``a > b`` (NaN lanes are invalid anyway).
    farthest = builder.select(builder.fcmp_ordered(">", below, above), below, above)
    pad = builder.fmul(builder.fmul(farthest, absolute(shear[2])), const(float(INTERVAL_SLACK)))
    # Stores.
    lane_pointer = lane_row_pointer(context, builder, lanes_t, args[7])
    pad_row, base = as_intp(8), as_intp(9)

    def store(row: Any, value: Any) -> None:
        builder.store(value, lane_pointer(row), align=4)

    def at(offset: int, start: Any = None) -> Any:
        return context.get_constant(intp, offset) if start is None else builder.add(
            start, context.get_constant(intp, offset))  # fmt: skip

    for axis in range(3):
        store(at(ORIGIN_ROW + axis), o[axis])
        store(at(INVERSE_ROW + axis), inverse[axis])
        store(at(SHEAR + axis, base), shear[axis])
        store(at(SHEARED_ORIGIN + axis, base), sheared_origin[axis])
    store(pad_row, pad)
    store(at(T_LO, base), t_lo)
    store(at(T_HIT, base), t_hit)
    store(at(U, base), const(0.0))
    store(at(V, base), const(0.0))
    axes_view = context.make_array(axes_t)(context, builder, args[10])
    for row, value in ((KX, kx), (KY, ky), (KZ, kz), (OCTANT, octant)):
        item = cgutils.get_item_pointer(context, builder, axes_t, axes_view,
                                        [at(row), at(0)], wraparound=False)  # fmt: skip
        builder.store(value, builder.bitcast(item, ivec.as_pointer()), align=8)
    return builder.zext(builder.bitcast(valid, ir.IntType(PACKET)), i32)


@intrinsic
def packet_setup(
    typingctx: Any, origin: Any, direction: Any, tmin: Any, tmax: Any, first: Any, last: Any,
    root_box: Any, lanes: Any, pad_row: Any, base: Any, axes: Any,
) -> Any:  # fmt: skip
    """Compute the per-ray constants of sixteen rays in vectors (see the module docstring)."""
    real = lanes.dtype
    if lanes.ndim != 2 or lanes.layout != "C" or real not in (types.float32, types.float64):
        raise TypeError("packet setup: a C-contiguous 2D float32 or float64 lane array")
    if origin.dtype != real or direction.dtype != real or tmin.dtype != real:
        raise TypeError("packet setup: rays in the lanes' precision expected")
    if axes.dtype != types.int64 or axes.ndim != 2 or axes.layout != "C":
        raise TypeError("packet setup: a C-contiguous 2D int64 axes array expected")
    return types.int32(
        origin, direction, tmin, tmax, first, last, root_box, lanes, pad_row, base, axes
    ), _codegen
