"""Two, four or eight ray/box slab tests at once, as explicit LLVM vector code.

The robust slab test of :mod:`rayaccel.kernels.aabb` (Williams et al. 2005 plane
selection, Ize 2013 2-ulp exit widening, NaN never tightening a bound) applied to the
child boxes of a wide BVH row (:mod:`rayaccel.bvh.layouts.wide`) or of a binary row of the
pairs layout (:mod:`rayaccel.bvh.layouts.pairs`, two lanes), whose planes are stored
structure-of-arrays: the children's ``lo.x`` side by side, then their ``hi.x``, and
so on. Each slab is one ``<N x float>`` load, subtract and multiply; the bounds are
merged with ordered compares and selects, which is exactly the scalar test's
``if t > entry: entry = t`` per lane.

numba leaves LLVM's SLP vectorizer off by default, and the loop vectorizer does not
touch a 4-iteration loop, so a plain lane loop compiles to scalar code; the
intrinsics :data:`slab_test2`, :data:`slab_test4` and :data:`slab_test8` write the
vector IR themselves. They compile for the CPU only (the CUDA traversals have their own box test).

Signature (all three): ``slab_testN(box, row, near_x, far_x, near_y, far_y, near_z, far_z,
ox, oy, oz, ix, iy, iz, t_lo, t_hi, out) -> int32``. ``box`` is a 2D float32 array;
the ray scalars are float32, or float64 for float64 rays (``precision="float64"``), in
which case the planes are widened exactly to float64 and the whole test runs in
``<N x double>`` vectors;
the N lanes of each plane start at the given columns of row ``row`` (the caller picks
near and far planes by the signs of ``ix, iy, iz``). Lane ``i`` of ``out`` gets
``max(t_lo, entry)`` when box ``i`` is hit within ``[t_lo, t_hi]`` and ``inf``
otherwise, exactly as :func:`rayaccel.kernels.aabb.ray_box_entry_py` (the tests check
it lane by lane); bit ``i`` of the result is set for a hit.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel.kernels.aabb import TWO_ULP


def _slab_codegen(lanes: int) -> Any:
    """Return the LLVM code generator of the ``lanes``-wide slab test."""

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        box_type = signature.args[0]
        out_type = signature.args[16]
        real = signature.args[8]
        float_type = context.get_value_type(real)
        vec_type = ir.VectorType(float_type, lanes)
        plane_type = ir.VectorType(context.get_value_type(box_type.dtype), lanes)
        out_vec_type = ir.VectorType(context.get_value_type(out_type.dtype), lanes)
        suffix = "f64" if real == types.float64 else "f32"
        box_view = context.make_array(box_type)(context, builder, args[0])
        out_view = context.make_array(out_type)(context, builder, args[16])
        row_index = context.cast(builder, args[1], signature.args[1], types.intp)

        def splat(value: Any) -> Any:
            vec = ir.Constant(vec_type, ir.Undefined)
            for lane in range(lanes):
                vec = builder.insert_element(vec, value, ir.Constant(ir.IntType(32), lane))
            return vec

        def scalar(i: int) -> Any:
            return splat(context.cast(builder, args[i], signature.args[i], real))

        def plane(i: int) -> Any:
            column = context.cast(builder, args[i], signature.args[i], types.intp)
            pointer = cgutils.get_item_pointer(
                context, builder, box_type, box_view, [row_index, column], wraparound=False
            )
            loaded = builder.load(builder.bitcast(pointer, plane_type.as_pointer()), align=4)
            # float32 planes against float64 rays: widen exactly (fpext is exact).
            return loaded if plane_type == vec_type else builder.fpext(loaded, vec_type)

        def take_if(cond: str, candidate: Any, current: Any) -> Any:
            # Ordered compare: a NaN lane keeps ``current`` (no constraint).
            keep = builder.fcmp_ordered(cond, candidate, current)
            return builder.select(keep, candidate, current)

        inf = splat(ir.Constant(float_type, float("inf")))
        enter = scalar(14)
        leave = inf
        # Per axis: distances to the near and far planes; entry = max, exit = min.
        for axis in range(3):
            origin = scalar(8 + axis)
            inverse = scalar(11 + axis)
            near = builder.fmul(builder.fsub(plane(2 + 2 * axis), origin), inverse)
            far = builder.fmul(builder.fsub(plane(3 + 2 * axis), origin), inverse)
            enter = take_if(">", near, enter)
            leave = take_if("<", far, leave)
        # Widen the exit by 2 ulp (Ize 2013), clamp to the interval, keep hit lanes.
        fabs = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(vec_type, [vec_type]), f"llvm.fabs.v{lanes}{suffix}"
        )
        widening = splat(ir.Constant(float_type, float(TWO_ULP)))
        leave = builder.fadd(leave, builder.fmul(builder.call(fabs, [leave]), widening))
        leave = take_if("<", scalar(15), leave)
        hit = builder.fcmp_ordered("<=", enter, leave)
        zero = context.get_constant(types.intp, 0)
        out_pointer = cgutils.get_item_pointer(
            context, builder, out_type, out_view, [zero], wraparound=False
        )
        result = builder.select(hit, enter, inf)
        if out_vec_type != vec_type:
            # Entry distances of float64 rays kept in a float32 scratch array (rounded to
            # nearest: the traversals' culling pad is far wider than that rounding).
            result = builder.fptrunc(result, out_vec_type)
        builder.store(result, builder.bitcast(out_pointer, out_vec_type.as_pointer()), align=4)
        # Lane i of the mask is bit i (one movmskps).
        return builder.zext(builder.bitcast(hit, ir.IntType(lanes)), ir.IntType(32))

    return codegen


def _signature(box: Any, columns: tuple[Any, ...], scalars: tuple[Any, ...], out: Any) -> Any:
    """Return the test's signature: float64 if any ray scalar is float64, else float32."""
    real = types.float64 if types.float64 in scalars else types.float32
    if box.dtype != types.float32 or out.dtype not in (types.float32, real):
        raise TypeError(f"slab test: float32 boxes and a {real} out array expected")
    return types.int32(box, *columns, *([real] * 8), out)


def _slab_test(lanes: int, count: str) -> Any:
    """Return the intrinsic of ``lanes`` slab tests in ``<lanes x float>`` vectors."""

    def slab_test(
        typingctx: Any, box: Any, row: Any, near_x: Any, far_x: Any, near_y: Any, far_y: Any,
        near_z: Any, far_z: Any, ox: Any, oy: Any, oz: Any, ix: Any, iy: Any, iz: Any,
        t_lo: Any, t_hi: Any, out: Any,
    ) -> Any:  # fmt: skip
        columns = (row, near_x, far_x, near_y, far_y, near_z, far_z)
        scalars = (ox, oy, oz, ix, iy, iz, t_lo, t_hi)
        return _signature(box, columns, scalars, out), _slab_codegen(lanes)

    slab_test.__name__ = slab_test.__qualname__ = f"slab_test{lanes}"
    slab_test.__doc__ = (
        f"{count} slab tests in ``<{lanes} x float>`` vectors (see the module docstring)."
    )
    return intrinsic(slab_test)


slab_test2 = _slab_test(2, "Two")
slab_test4 = _slab_test(4, "Four")
slab_test8 = _slab_test(8, "Eight")
