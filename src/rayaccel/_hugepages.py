"""Large arrays allocated inside kernels, backed by transparent huge pages on Linux.

numpy asks Linux for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on every
array of 4 MiB or more, but arrays that numba allocates inside a kernel come from
``malloc`` with no such advice. Where the kernel's ``transparent_hugepage`` mode is
``madvise`` (the common default), such arrays are faulted in 4 KiB pages, 512 page
faults where a huge page takes one. A builder allocates hundreds of MB per million
triangles and touches them once, so those faults are a large share of a build (the
first-touch timings are in ``docs/performance.md``, What was tried, Builders).

:func:`advise_huge_pages` gives the advice numpy gives (on the 2 MiB-aligned interior
of an array of at least 4 MiB, before its pages are touched); :func:`empty_huge`,
:func:`zeros_huge` and :func:`full_huge` are ``np.empty``/``np.zeros``/``np.full``
with the advice. On other systems, or where huge pages are unavailable, the advice
is not given or is ignored and nothing else changes.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from rayaccel._jit import cpu_inline

HUGE_PAGE = 2 << 20
MADV_HUGEPAGE = 14


@intrinsic
def advise_huge_pages(typingctx: Any, array: Any) -> Any:
    """Advise Linux to back ``array``'s 2 MiB-aligned interior with huge pages."""
    sig = types.void(array)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        if not sys.platform.startswith("linux"):
            return context.get_dummy_value()
        i64 = ir.IntType(64)
        view = context.make_array(signature.args[0])(context, builder, args[0])
        data = builder.ptrtoint(view.data, i64)
        nbytes = builder.mul(view.nitems, view.itemsize)
        mask = ir.Constant(i64, ~(HUGE_PAGE - 1))
        start = builder.and_(builder.add(data, ir.Constant(i64, HUGE_PAGE - 1)), mask)
        end = builder.and_(builder.add(data, nbytes), mask)
        large = builder.icmp_signed(">=", nbytes, ir.Constant(i64, 2 * HUGE_PAGE))
        spans = builder.icmp_signed(">", end, start)
        with builder.if_then(builder.and_(large, spans)):
            char_p = ir.IntType(8).as_pointer()
            madvise = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.IntType(32), [char_p, i64, ir.IntType(32)]),
                "madvise",
            )  # fmt: skip
            builder.call(
                madvise,
                [builder.inttoptr(start, char_p), builder.sub(end, start),
                 ir.Constant(ir.IntType(32), MADV_HUGEPAGE)],
            )  # fmt: skip
        return context.get_dummy_value()

    return sig, codegen


@cpu_inline
def empty_huge(shape, dtype):
    """``np.empty(shape, dtype)`` advised onto huge pages."""
    out = np.empty(shape, dtype=dtype)
    advise_huge_pages(out)
    return out


@cpu_inline
def zeros_huge(shape, dtype):
    """``np.zeros(shape, dtype)`` advised onto huge pages (advice before the first touch)."""
    out = np.empty(shape, dtype=dtype)
    advise_huge_pages(out)
    out.fill(0)
    return out


@cpu_inline
def full_huge(shape, value, dtype):
    """``np.full(shape, value, dtype)`` advised onto huge pages."""
    out = np.empty(shape, dtype=dtype)
    advise_huge_pages(out)
    out.fill(value)
    return out
