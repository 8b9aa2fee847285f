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

:func:`grow_bounds` is the counterpart for a box kept in registers, as a 6-tuple;
:func:`union_bounds` grows such a box by a stored box, :func:`store_bounds` writes it
to 6 floats and :func:`store_box` to a pair of corner arrays (:func:`load_box` reads it
back). A sweep starts from :data:`EMPTY_BOUNDS`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
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


#: The empty box ``(+inf, +inf, +inf, -inf, -inf, -inf)`` (float64) a sweep grows from.
EMPTY_BOUNDS = (np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf)


def _union_bounds_py(bounds, lo, hi, i, h):
    """Return ``bounds`` (a 6-tuple) grown by the box ``lo[i, 0:3]`` .. ``hi[i, h:h + 3]``.

    One array of rows holding both corners (``lo`` and ``hi`` the same; ``h`` the high
    corner's column: 4 for reference rows and bin boxes, 3 for 6-float boxes) or two
    arrays of corners (``h`` 0). The min and max are taken in the scalar code's order,
    so the box is the one a loop over six scalars gives.
    """
    return (
        min(bounds[0], lo[i, 0]), min(bounds[1], lo[i, 1]), min(bounds[2], lo[i, 2]),
        max(bounds[3], hi[i, h]), max(bounds[4], hi[i, h + 1]), max(bounds[5], hi[i, h + 2]),
    )  # fmt: skip


def _store_bounds_py(out, at, bounds):
    """Write the 6-tuple ``bounds`` to ``out[at:at + 6]`` (lo 0:3, hi 3:6)."""
    out[at] = bounds[0]
    out[at + 1] = bounds[1]
    out[at + 2] = bounds[2]
    out[at + 3] = bounds[3]
    out[at + 4] = bounds[4]
    out[at + 5] = bounds[5]


def _load_box_py(lo, hi, i):
    """Return box ``i`` of the corner arrays ``lo``/``hi`` (``(n, 3)``) as a 6-tuple."""
    return lo[i, 0], lo[i, 1], lo[i, 2], hi[i, 0], hi[i, 1], hi[i, 2]


def _store_box_py(lo, hi, i, bounds):
    """Write the 6-tuple ``bounds`` to box ``i`` of the corner arrays ``lo``/``hi``."""
    lo[i, 0] = bounds[0]
    lo[i, 1] = bounds[1]
    lo[i, 2] = bounds[2]
    hi[i, 0] = bounds[3]
    hi[i, 1] = bounds[4]
    hi[i, 2] = bounds[5]


grow_bounds = cpu_inline(_grow_bounds_py)
union_bounds = cpu_inline(_union_bounds_py)
store_bounds = cpu_inline(_store_bounds_py)
load_box = cpu_inline(_load_box_py)
store_box = cpu_inline(_store_box_py)
