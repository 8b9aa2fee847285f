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

from collections.abc import Callable
from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel.kernels.aabb import TWO_ULP


def splat(builder: Any, vec_type: Any, value: Any) -> Any:
    """Return a vector of ``vec_type`` with ``value`` in every lane."""
    vec = ir.Constant(vec_type, ir.Undefined)
    for lane in range(vec_type.count):
        vec = builder.insert_element(vec, value, ir.Constant(ir.IntType(32), lane))
    return vec


def emit_slab_test(
    builder: Any,
    vec_type: Any,
    lo: Any,
    hi: Any,
    plane: Callable[[int], Any],
    origin: Callable[[int], Any],
    inverse: Callable[[int], Any],
) -> tuple[Any, Any]:
    """Emit the robust slab test on vectors; return the entry distances and the hit lanes.

    ``plane(k)`` gives the near (``k = 2 * axis``) and far (``2 * axis + 1``) planes,
    ``origin(axis)`` and ``inverse(axis)`` the rays', ``lo``/``hi`` the interval, all as
    vectors of ``vec_type`` (a box's lanes against one ray here, one box against a
    packet's rays in :mod:`rayaccel.kernels.aabb_packet`). The operations are the scalar
    test's (:func:`rayaccel.kernels.aabb.ray_box_entry_py`), in the same order.
    """

    def take_if(cond: str, candidate: Any, current: Any) -> Any:
        # Ordered compare: a NaN lane keeps ``current`` (no constraint).
        keep = builder.fcmp_ordered(cond, candidate, current)
        return builder.select(keep, candidate, current)

    float_type = vec_type.element
    enter = lo
    leave = splat(builder, vec_type, ir.Constant(float_type, float("inf")))
    # Per axis: distances to the near and far planes; entry = max, exit = min.
    for axis in range(3):
        near = builder.fmul(builder.fsub(plane(2 * axis), origin(axis)), inverse(axis))
        far = builder.fmul(builder.fsub(plane(2 * axis + 1), origin(axis)), inverse(axis))
        enter = take_if(">", near, enter)
        leave = take_if("<", far, leave)
    # Widen the exit by 2 ulp (Ize 2013), clamp to the interval, keep hit lanes.
    name = f"llvm.fabs.v{vec_type.count}{'f64' if isinstance(float_type, ir.DoubleType) else 'f32'}"
    fabs = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(vec_type, [vec_type]), name
    )
    widening = splat(builder, vec_type, ir.Constant(float_type, float(TWO_ULP)))
    leave = builder.fadd(leave, builder.fmul(builder.call(fabs, [leave]), widening))
    leave = take_if("<", hi, leave)
    return enter, builder.fcmp_ordered("<=", enter, leave)


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
        box_view = context.make_array(box_type)(context, builder, args[0])
        out_view = context.make_array(out_type)(context, builder, args[16])
        row_index = context.cast(builder, args[1], signature.args[1], types.intp)

        def scalar(i: int) -> Any:
            return splat(builder, vec_type, context.cast(builder, args[i], signature.args[i], real))

        def plane(i: int) -> Any:
            column = context.cast(builder, args[i], signature.args[i], types.intp)
            pointer = cgutils.get_item_pointer(
                context, builder, box_type, box_view, [row_index, column], wraparound=False
            )
            loaded = builder.load(builder.bitcast(pointer, plane_type.as_pointer()), align=4)
            # float32 planes against float64 rays: widen exactly (fpext is exact).
            return loaded if plane_type == vec_type else builder.fpext(loaded, vec_type)

        enter, hit = emit_slab_test(
            builder, vec_type, scalar(14), scalar(15),
            lambda k: plane(2 + k), lambda axis: scalar(8 + axis), lambda axis: scalar(11 + axis),
        )  # fmt: skip
        inf = splat(builder, vec_type, ir.Constant(float_type, float("inf")))
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
