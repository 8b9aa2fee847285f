"""Grow a stored box by another box with one 8-lane vector min/max.

Binning builders (:mod:`rayaccel.bvh.builders.binned_sah`, :mod:`rayaccel.bvh.builders.sbvh`)
add every reference's box to a bin's box, once per axis and level: three mins and three
maxes into memory, repeated for consecutive references that often land in the same bin.
Both the reference rows and the bin boxes are stored as 8 floats, ``[lo.x, lo.y, lo.z,
-, hi.x, hi.y, hi.z, -]``, so the update is one ``<8 x float>`` load of each, a vector
min and max, a shuffle taking lanes 0–3 of the min and 4–7 of the max, and one store.
numba leaves LLVM's SLP vectorizer off, so the lane loop does not become this by
itself. Lanes 3 and 7 of the bin box receive don't-care values (a reference's lane 3
holds its id bits); only lanes 0–2 and 4–6 are meaningful.

The min and max are ordered compare-and-select, as ``min``/``max`` in the scalar code,
so the boxes are bit-identical to a lane loop for finite input.

:func:`grow_bounds` is the counterpart for a box kept in registers, as a 6-tuple.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel._jit import cpu_inline


@intrinsic
def grow_box_row(typingctx: Any, bins: Any, axis: Any, slot: Any, rows: Any, row: Any) -> Any:
    """``bins[axis, slot]`` (3D float32, last dim 8) grows by ``rows[row]`` (2D, 8 wide)."""
    sig = types.void(bins, axis, slot, rows, row)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        vec = ir.VectorType(ir.FloatType(), 8)
        bins_view = context.make_array(signature.args[0])(context, builder, args[0])
        rows_view = context.make_array(signature.args[3])(context, builder, args[3])
        zero = context.get_constant(types.intp, 0)

        def index(i: int) -> Any:
            return context.cast(builder, args[i], signature.args[i], types.intp)

        dst = cgutils.get_item_pointer(
            context, builder, signature.args[0], bins_view, [index(1), index(2), zero],
            wraparound=False,
        )  # fmt: skip
        src = cgutils.get_item_pointer(
            context, builder, signature.args[3], rows_view, [index(4), zero], wraparound=False
        )
        dst = builder.bitcast(dst, vec.as_pointer())
        current = builder.load(dst, align=4)
        other = builder.load(builder.bitcast(src, vec.as_pointer()), align=4)
        low = builder.select(builder.fcmp_ordered("<", other, current), other, current)
        high = builder.select(builder.fcmp_ordered(">", other, current), other, current)
        lanes = ir.Constant(ir.VectorType(ir.IntType(32), 8), [0, 1, 2, 3, 12, 13, 14, 15])
        builder.store(builder.shuffle_vector(low, high, lanes), dst, align=4)
        return context.get_dummy_value()

    return sig, codegen


def _grow_bounds_py(bounds, x, y, z):
    """Return ``bounds`` (``(lo.x, lo.y, lo.z, hi.x, hi.y, hi.z)``, a tuple) grown by a point.

    For loops that keep a box in registers: a box in array elements is reloaded and
    stored back around every store LLVM cannot prove unrelated (a row swap, a bin update).
    """
    return (
        min(bounds[0], x), min(bounds[1], y), min(bounds[2], z),
        max(bounds[3], x), max(bounds[4], y), max(bounds[5], z),
    )  # fmt: skip


grow_bounds = cpu_inline(_grow_bounds_py)
