"""Precision-generic scalar helpers: the per-ray code compiles for float32 and float64 rays.

Traversal kernels are lazily typed numba dispatchers, so float64 rays and triangle rows
(``TriangleMesh(..., precision="float64")``) compile float64 specialisations of the
very same per-ray code. Four operations in that code depend on the precision and are
written here once, as plain Python functions (the readable form the tests call) with
a numba ``overload`` choosing the compiled form by the argument types at compile time:

- :func:`next_up`: the next representable value above ``x`` in ``x``'s own precision
  (``tmax`` is inclusive while the triangle test's bound is strict).
- :func:`as_real_like`: ``x`` converted to the precision of ``ref``.
- :func:`in_precision_of`: of two arrays, the one whose dtype is ``ref``'s (a
  body's float32 or float64 scratch, allocated ahead since a traversal body
  allocates nothing, :mod:`rayaccel.trace.skeleton`).
- :func:`edge_function`: ``a*b - c*d`` in float64, the 2D edge function of the
  watertight triangle test (Woop, Benthin, Wald 2013). For float32 operands the
  products are exact in float64, so the sign is exact (the paper's double-precision
  fallback, always taken). For float64 operands the products round, as in Embree's
  and pbrt's double builds; the function is then emitted *without* the ``contract``
  fast-math flag, so LLVM cannot fuse one product into an FMA. Both products are then
  rounded the same way, ``edge_function(a, b, c, d) == -edge_function(c, d, a, b)``
  holds exactly, and a shared edge is classified consistently from both of its
  triangles: the test stays watertight, though a value within a rounding error of
  zero may take the wrong sign (the ray is then assigned to the neighbouring triangle).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import types
from numba.extending import intrinsic, overload

from rayaccel._jit import FASTMATH, next_up_float32, next_up_float64


def next_up(x: Any) -> Any:
    """Return the smallest value of ``x``'s float type above ``x`` (NaN and +inf unchanged)."""
    return np.nextafter(x, type(x)(np.inf))


def as_real_like(x: Any, ref: Any) -> Any:
    """Return ``x`` converted to the float type of ``ref`` (float32 or float64)."""
    return type(ref)(x)


def in_precision_of(ref: Any, single: Any, double: Any) -> Any:
    """Return ``double`` for a float64 array ``ref``, else ``single``."""
    return double if ref.dtype == np.float64 else single


def edge_function(a: Any, b: Any, c: Any, d: Any) -> Any:
    """Return ``a*b - c*d`` computed in float64 (exact products for float32 operands)."""
    return np.float64(a) * np.float64(b) - np.float64(c) * np.float64(d)


#: The fast-math flags of the float64 edge function: ``FASTMATH`` without ``contract``.
#: numba adds its flags only to instructions that carry none, so these stay.
_NO_CONTRACT = tuple(sorted(FASTMATH - {"contract"}))


@intrinsic
def edge_function_float64(typingctx: Any, a: Any, b: Any, c: Any, d: Any) -> Any:
    """``a*b - c*d`` in float64 with both products rounded (no FMA contraction)."""
    f64 = types.float64
    sig = f64(f64, f64, f64, f64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        ab = builder.fmul(args[0], args[1], flags=_NO_CONTRACT)
        cd = builder.fmul(args[2], args[3], flags=_NO_CONTRACT)
        return builder.fsub(ab, cd, flags=_NO_CONTRACT)

    return sig, codegen


@overload(next_up, inline="always")
def _next_up_overload(x):
    if x == types.float32:
        return lambda x: next_up_float32(x)
    if x == types.float64:
        return lambda x: next_up_float64(x)
    return None


@overload(as_real_like, inline="always")
def _as_real_like_overload(x, ref):
    if ref == types.float32:
        return lambda x, ref: np.float32(x)
    if ref == types.float64:
        return lambda x, ref: np.float64(x)
    return None


@overload(in_precision_of, inline="always")
def _in_precision_of_overload(ref, single, double):
    if ref.dtype == types.float64:
        return lambda ref, single, double: double
    return lambda ref, single, double: single


@overload(edge_function, inline="always")
def _edge_function_overload(a, b, c, d):
    if all(arg == types.float32 for arg in (a, b, c, d)):
        # Exact products: FMA contraction cannot change the result.
        return lambda a, b, c, d: np.float64(a) * np.float64(b) - np.float64(c) * np.float64(d)
    if all(isinstance(arg, types.Float) for arg in (a, b, c, d)):
        return lambda a, b, c, d: edge_function_float64(
            np.float64(a), np.float64(b), np.float64(c), np.float64(d)
        )
    return None
