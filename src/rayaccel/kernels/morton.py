"""Morton codes (Z-order keys) of primitive centroids, 30 or 63 bits.

A Morton code interleaves the bits of the quantized coordinates (x in bit 0 of each
triple, then y, then z, Morton 1966), so sorting primitives by code orders them along
a Z-shaped space-filling curve and neighbours in the order are mostly neighbours in
space (Lauterbach et al. 2009, "Fast BVH Construction on GPUs", Eurographics).
Centroids are quantized in the bounds of the *centroids* (not of the scene), so the
full resolution is spent where primitives are: 10 bits per axis for 30-bit codes,
21 bits per axis for 63-bit codes. An axis with zero extent quantizes to 0.

Codes are int64 with bit 63 clear (numba promotes uint64/int64 mixes to float).
:func:`count_leading_zeros` is LLVM's ``ctlz``, used by Karras' common-prefix test.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from llvmlite import ir
from numba import prange
from numba.core import types
from numba.extending import intrinsic

from rayaccel._hugepages import empty_huge
from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.kernels.box_grow import grow_bounds


@intrinsic
def count_leading_zeros(typingctx: Any, value: Any) -> Any:
    """Return the number of leading zero bits of an int64 (64 for 0)."""
    sig = types.int64(types.int64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.ctlz(args[0], ir.Constant(ir.IntType(1), 0))

    return sig, codegen


def _spread3_py(x):
    """Spread the low 21 bits of ``x`` (int64) to every third bit."""
    x &= 0x1FFFFF
    x = (x | (x << 32)) & 0x1F00000000FFFF
    x = (x | (x << 16)) & 0x1F0000FF0000FF
    x = (x | (x << 8)) & 0x100F00F00F00F00F
    x = (x | (x << 4)) & 0x10C30C30C30C30C3
    x = (x | (x << 2)) & 0x1249249249249249
    return x


spread3 = cpu_inline(_spread3_py)

#: Chunks of the parallel centroid-bounds pass (a constant: the result never depends on it).
BOUNDS_CHUNKS = 64


@cpu_kernel(parallel=True)
def morton_codes(prim_lo, prim_hi, bits_per_axis):
    """Return the ``(n,)`` int64 Morton codes of the box centres of ``prim_lo/prim_hi``.

    Parameters
    ----------
    prim_lo, prim_hi : (n, 3) float32
        Primitive (or reference) boxes; the key is the box centre.
    bits_per_axis : int
        10 (30-bit codes) or 21 (63-bit codes).
    """
    n = prim_lo.shape[0]
    # Centroid bounds (doubled centroids lo + hi: same order, no multiply), per chunk in
    # parallel, then combined (min and max are exact, so the order does not matter).
    n_chunks = BOUNDS_CHUNKS
    size = (n + n_chunks - 1) // n_chunks
    part = np.empty((n_chunks, 6))
    for k in prange(n_chunks):
        bounds = (np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf)
        for i in range(k * size, min(n, (k + 1) * size)):
            cx = np.float64(prim_lo[i, 0]) + prim_hi[i, 0]
            cy = np.float64(prim_lo[i, 1]) + prim_hi[i, 1]
            cz = np.float64(prim_lo[i, 2]) + prim_hi[i, 2]
            bounds = grow_bounds(bounds, cx, cy, cz)
        for a in range(6):
            part[k, a] = bounds[a]
    c_lo = np.full(3, np.inf)
    c_hi = np.full(3, -np.inf)
    for k in range(n_chunks):
        for a in range(3):
            c_lo[a] = min(c_lo[a], part[k, a])
            c_hi[a] = max(c_hi[a], part[k, 3 + a])
    cells = np.float64((1 << bits_per_axis) - 1)
    scale = np.zeros(3)
    for a in range(3):
        if c_hi[a] > c_lo[a]:
            scale[a] = cells / (c_hi[a] - c_lo[a])
    codes = empty_huge(n, np.int64)
    for i in prange(n):
        code = np.int64(0)
        for a in range(3):
            c = np.float64(prim_lo[i, a]) + prim_hi[i, a]
            q = np.int64((c - c_lo[a]) * scale[a])
            if q > (1 << bits_per_axis) - 1:
                q = (1 << bits_per_axis) - 1
            if q < 0:
                q = 0
            code |= spread3(q) << a
        codes[i] = code
    return codes
