"""Four ray/box slab tests at once, as explicit 4-lane LLVM vector code.

The robust slab test of :mod:`rayaccel.kernels.aabb` (Williams et al. 2005 plane
selection, Ize 2013 2-ulp exit widening, NaN never tightening a bound) applied to the
four child boxes of a wide BVH row (:mod:`rayaccel.bvh.wide`), whose planes are
stored structure-of-arrays: four ``lo.x`` in a row, then four ``hi.x``, and so on.
Each slab is one ``<4 x float>`` load, subtract and multiply; the bounds are merged
with ordered compares and selects, which is exactly the scalar test's
``if t > entry: entry = t`` per lane.

numba leaves LLVM's SLP vectorizer off by default, and the loop vectorizer does not
touch a 4-iteration loop, so a plain lane loop compiles to scalar code; this
intrinsic writes the vector IR itself. It compiles for the CPU only (the CUDA
traversals have their own box test).
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel.kernels.aabb import TWO_ULP

LANES = 4


@intrinsic
def slab_test4(
    typingctx: Any,
    box: Any,
    row: Any,
    near_x: Any,
    far_x: Any,
    near_y: Any,
    far_y: Any,
    near_z: Any,
    far_z: Any,
    ox: Any,
    oy: Any,
    oz: Any,
    ix: Any,
    iy: Any,
    iz: Any,
    t_lo: Any,
    t_hi: Any,
    out: Any,
) -> Any:
    """Test four boxes of row ``row`` of ``box``; return the hit lanes as a 4-bit mask.

    The entry distances go to ``out[0:4]``.

    ``box`` is a 2D float32 array; the four lanes of each plane start at the columns
    ``near_x`` ... ``far_z`` (the caller picks near and far planes by the signs of
    ``ix, iy, iz``). A lane gets ``max(t_lo, entry)`` when the box is hit within
    ``[t_lo, t_hi]`` and ``inf`` otherwise, exactly as
    :func:`rayaccel.kernels.aabb.ray_box_entry_py` (up to the rounding of the 2-ulp
    widening, which may differ by an FMA contraction).
    """
    f32 = types.float32
    sig = types.int32(
        box, row, near_x, far_x, near_y, far_y, near_z, far_z,
        f32, f32, f32, f32, f32, f32, f32, f32, out,
    )  # fmt: skip

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        box_type = signature.args[0]
        out_type = signature.args[16]
        float_type = ir.FloatType()
        vec_type = ir.VectorType(float_type, LANES)
        box_view = context.make_array(box_type)(context, builder, args[0])
        out_view = context.make_array(out_type)(context, builder, args[16])
        row_index = context.cast(builder, args[1], signature.args[1], types.intp)

        def scalar(i: int) -> Any:
            return context.cast(builder, args[i], signature.args[i], f32)

        def splat(value: Any) -> Any:
            vec = ir.Constant(vec_type, ir.Undefined)
            for lane in range(LANES):
                vec = builder.insert_element(vec, value, ir.Constant(ir.IntType(32), lane))
            return vec

        def plane(i: int) -> Any:
            column = context.cast(builder, args[i], signature.args[i], types.intp)
            pointer = cgutils.get_item_pointer(
                context, builder, box_type, box_view, [row_index, column], wraparound=False
            )
            return builder.load(builder.bitcast(pointer, vec_type.as_pointer()), align=4)

        def take_if(cond: str, candidate: Any, current: Any) -> Any:
            # Ordered compare: a NaN lane keeps ``current`` (no constraint).
            keep = builder.fcmp_ordered(cond, candidate, current)
            return builder.select(keep, candidate, current)

        origin = [splat(scalar(8)), splat(scalar(9)), splat(scalar(10))]
        inverse = [splat(scalar(11)), splat(scalar(12)), splat(scalar(13))]
        enter = splat(scalar(14))
        t_hi_vec = splat(scalar(15))
        leave = splat(ir.Constant(float_type, float("inf")))
        # Per axis: distances to the near and far planes; entry = max, exit = min.
        for axis in range(3):
            near = builder.fmul(builder.fsub(plane(2 + 2 * axis), origin[axis]), inverse[axis])
            far = builder.fmul(builder.fsub(plane(3 + 2 * axis), origin[axis]), inverse[axis])
            enter = take_if(">", near, enter)
            leave = take_if("<", far, leave)
        # Widen the exit by 2 ulp (Ize 2013), clamp to the interval, keep hit lanes.
        fabs = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(vec_type, [vec_type]), "llvm.fabs.v4f32"
        )
        widening = splat(ir.Constant(float_type, float(TWO_ULP)))
        leave = builder.fadd(leave, builder.fmul(builder.call(fabs, [leave]), widening))
        leave = take_if("<", t_hi_vec, leave)
        hit = builder.fcmp_ordered("<=", enter, leave)
        result = builder.select(hit, enter, splat(ir.Constant(float_type, float("inf"))))
        zero = context.get_constant(types.intp, 0)
        out_pointer = cgutils.get_item_pointer(
            context, builder, out_type, out_view, [zero], wraparound=False
        )
        builder.store(result, builder.bitcast(out_pointer, vec_type.as_pointer()), align=4)
        # Lane i of the mask is bit i (one movmskps).
        mask = builder.bitcast(hit, ir.IntType(LANES))
        return builder.zext(mask, ir.IntType(32))

    return sig, codegen
