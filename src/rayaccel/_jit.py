"""One decorator policy for every CPU kernel (STYLE §4.1).

``fastmath`` keeps IEEE infinities and NaN (no ``nnan``/``ninf``): slab tests for
axis-parallel rays rely on ``1/±0 = ±inf``. ``error_model="numpy"`` makes division
by zero give ``inf`` instead of raising.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

FASTMATH = frozenset({"nsz", "arcp", "contract"})


def cpu_kernel(*, parallel: bool = False) -> Callable[[Callable[..., Any]], Any]:
    """Return the ``njit`` decorator used for every CPU kernel.

    Parameters
    ----------
    parallel : bool
        Compile ``prange`` loops as parallel loops.
    """
    return numba.njit(  # type: ignore[no-any-return]
        parallel=parallel,
        cache=True,
        nogil=True,
        fastmath=set(FASTMATH),
        error_model="numpy",
    )


def cpu_inline(fn: Callable[..., Any]) -> Any:
    """Compile a leaf helper that is always inlined into its callers."""
    return numba.njit(
        inline="always", cache=True, nogil=True, fastmath=set(FASTMATH), error_model="numpy"
    )(fn)


@intrinsic
def prefetch_row(typingctx: Any, array: Any, row: Any) -> Any:
    """Hint the CPU to start loading row ``row`` of a 2D array (``llvm.prefetch``, no fault).

    Used by traversals to overlap the memory latency of the next node with the box
    tests of the current one. Out-of-range rows are harmless (prefetches never fault).
    """
    sig = types.void(array, row)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        array_type = signature.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        index = context.cast(builder, args[1], signature.args[1], types.intp)
        zero = context.get_constant(types.intp, 0)
        pointer = cgutils.get_item_pointer(
            context, builder, array_type, view, [index, zero], wraparound=False
        )
        byte_pointer = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        function_type = ir.FunctionType(ir.VoidType(), [byte_pointer, i32, i32, i32])
        function = cgutils.get_or_insert_function(builder.module, function_type, "llvm.prefetch.p0")
        # Read access, high temporal locality, data cache.
        builder.call(function, [builder.bitcast(pointer, byte_pointer), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen
