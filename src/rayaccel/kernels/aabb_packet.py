"""One box against a packet of sixteen rays, as explicit LLVM vector code.

The transpose of :mod:`rayaccel.kernels.aabb_wide`: there one ray meets the N boxes of
a wide row, here one box meets sixteen rays (Wald, Slusallek, Benthin, Wagner 2001,
"Interactive Rendering with Coherent Ray Tracing": a packet of rays shares each node
fetch and each box test is one SIMD operation over the packet). The rays of a packet
share the signs of their directions, so they share the near and far plane columns of
the box (Williams et al. 2005); each plane is one scalar load, broadcast to the
lanes. The arithmetic per lane is exactly the scalar test's
(:func:`rayaccel.kernels.aabb.ray_box_entry_py`: the robust slab test, Ize 2013 2-ulp
exit widening, NaN never tightening a bound), so a lane's answer is the single ray's
bit for bit (the tests check it lane by lane).

:data:`packet_slab_test` ``(box, row, near_x, far_x, near_y, far_y, near_z, far_z,
lanes, out_row) -> int32``: ``box`` is a 2D float32 array; ``lanes`` is a 2D array of
the rays' precision (float32, or float64 for float64 rays, in which case the planes
are widened exactly and the test runs in ``<16 x double>``) whose rows 0 to 7 hold
the packet's ``ox, oy, oz, ix, iy, iz`` and the interval ``lo, hi`` of each lane;
lane ``i`` of ``lanes[out_row]`` gets ``max(lo, entry)`` when the box is hit within
``[lo, hi]`` and ``inf`` otherwise, and bit ``i`` of the result is set for a hit. A
lane whose ``hi`` is ``-inf`` never hits: a packet retires a lane that way.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel.kernels.aabb_wide import emit_slab_test, splat

#: Rays of a packet (one AVX register of float32 lanes).
PACKET = 16
#: Rows of the lane array the test reads: ``ox, oy, oz, ix, iy, iz, lo, hi``.
ORIGIN_ROW = 0
INVERSE_ROW = 3
LO_ROW = 6
HI_ROW = 7


def _packet_codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
    """Emit the packet's slab test (see the module docstring)."""
    box_type = signature.args[0]
    lanes_type = signature.args[8]
    real = lanes_type.dtype
    float_type = context.get_value_type(real)
    vec_type = ir.VectorType(float_type, PACKET)
    box_view = context.make_array(box_type)(context, builder, args[0])
    row_index = context.cast(builder, args[1], signature.args[1], types.intp)
    lane_pointer = lane_row_pointer(context, builder, lanes_type, args[8])

    def lane_row(row: int) -> Any:
        return builder.load(lane_pointer(context.get_constant(types.intp, row)), align=4)

    def plane(i: int) -> Any:
        column = context.cast(builder, args[i], signature.args[i], types.intp)
        pointer = cgutils.get_item_pointer(
            context, builder, box_type, box_view, [row_index, column], wraparound=False
        )
        value = builder.load(pointer)
        # float32 planes against float64 rays: widen exactly (fpext is exact).
        wide = value if real == types.float32 else builder.fpext(value, float_type)
        return splat(builder, vec_type, wide)

    inf = splat(builder, vec_type, ir.Constant(float_type, float("inf")))
    origins = [lane_row(ORIGIN_ROW + axis) for axis in range(3)]
    inverses = [lane_row(INVERSE_ROW + axis) for axis in range(3)]
    enter, hit = emit_slab_test(
        builder, vec_type, lane_row(LO_ROW), lane_row(HI_ROW),
        lambda k: plane(2 + k), origins.__getitem__, inverses.__getitem__,
    )  # fmt: skip
    out_row = context.cast(builder, args[9], signature.args[9], types.intp)
    builder.store(builder.select(hit, enter, inf), lane_pointer(out_row), align=4)
    # Lane i of the mask is bit i (one movmskps).
    return builder.zext(builder.bitcast(hit, ir.IntType(PACKET)), ir.IntType(32))


@intrinsic
def packet_slab_test(
    typingctx: Any, box: Any, row: Any, near_x: Any, far_x: Any, near_y: Any, far_y: Any,
    near_z: Any, far_z: Any, lanes: Any, out_row: Any,
) -> Any:  # fmt: skip
    """Sixteen rays against one box in ``<16 x float>`` vectors (see the module docstring)."""
    if box.dtype != types.float32 or lanes.dtype not in (types.float32, types.float64):
        raise TypeError("packet slab test: float32 boxes and float32 or float64 lanes expected")
    if box.ndim != 2 or lanes.ndim != 2 or lanes.layout != "C":
        raise TypeError("packet slab test: 2D boxes and a C-contiguous 2D lane array expected")
    columns = (row, near_x, far_x, near_y, far_y, near_z, far_z)
    return types.int32(box, *columns, lanes, out_row), _packet_codegen


def lane_row_pointer(context: Any, builder: Any, lanes_type: Any, lanes_value: Any) -> Any:
    """Return ``pointer(row)``: the ``<16 x real>*`` of row ``row`` of a lane array."""
    view = context.make_array(lanes_type)(context, builder, lanes_value)
    vec_type = ir.VectorType(context.get_value_type(lanes_type.dtype), PACKET)
    zero = context.get_constant(types.intp, 0)

    def pointer(row: Any) -> Any:
        item = cgutils.get_item_pointer(
            context, builder, lanes_type, view, [row, zero], wraparound=False
        )
        return builder.bitcast(item, vec_type.as_pointer())

    return pointer


def _check_lanes(lanes: Any) -> None:
    if lanes.ndim != 2 or lanes.layout != "C" or lanes.dtype not in (types.float32, types.float64):
        raise TypeError("packet lanes: a C-contiguous 2D float32 or float64 array expected")


@intrinsic
def lanes_at_most(typingctx: Any, lanes: Any, row: Any, bound_row: Any) -> Any:
    """Return the mask of the lanes where ``lanes[row] <= lanes[bound_row]`` and is finite.

    A packet's stack entry holds each ray's entry distance (``inf`` for a ray that missed
    the box); compared with the rays' ``hi`` it gives the rays that still go on there. A
    ray that missed the box stays out even while its ``hi`` is still ``inf`` (no hit yet).
    """
    _check_lanes(lanes)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        pointer = lane_row_pointer(context, builder, signature.args[0], args[0])
        rows = [context.cast(builder, args[i], signature.args[i], types.intp) for i in (1, 2)]
        value, bound = (builder.load(pointer(r), align=4) for r in rows)
        vec_type = ir.VectorType(context.get_value_type(signature.args[0].dtype), PACKET)
        inf = splat(builder, vec_type, ir.Constant(vec_type.element, float("inf")))
        # A missed box's inf is never "at most" a ray's bound, not even an inf bound.
        at_most = builder.and_(
            builder.fcmp_ordered("<=", value, bound), builder.fcmp_ordered("<", value, inf)
        )
        return builder.zext(builder.bitcast(at_most, ir.IntType(PACKET)), ir.IntType(32))

    return types.int32(lanes, row, bound_row), codegen


@intrinsic
def copy_lane_row(typingctx: Any, lanes: Any, source: Any, target: Any) -> Any:
    """Copy row ``source`` of a lane array to row ``target`` (one vector load and store)."""
    _check_lanes(lanes)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        pointer = lane_row_pointer(context, builder, signature.args[0], args[0])
        rows = [context.cast(builder, args[i], signature.args[i], types.intp) for i in (1, 2)]
        builder.store(builder.load(pointer(rows[0]), align=4), pointer(rows[1]), align=4)
        return context.get_dummy_value()

    return types.none(lanes, source, target), codegen
