"""Parallel least-significant-digit radix sort of int64 keys with int32 payloads.

Each pass sorts by one 8-bit digit, stably: the input is cut into fixed chunks,
every chunk counts its digits in parallel (one private histogram per chunk),
a serial exclusive scan over (digit, chunk) turns the counts into write offsets,
and every chunk scatters its keys in parallel to its reserved slots, in order.
Stability makes the result the unique stable sort, whatever the number of chunks
or threads (Satish, Harris, Garland 2009, "Designing Efficient Sorting Algorithms
for Manycore GPUs", IPDPS, is the GPU form). A pass whose digit is the same for
every key is skipped, so equal or short keys cost one counting pass per digit.
Cost O(passes · n); 30-bit Morton codes need 4 passes, 63-bit ones 8.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from rayaccel._hugepages import empty_huge
from rayaccel._jit import cpu_kernel

RADIX_BITS = 8
RADIX = 1 << RADIX_BITS
#: Below this many keys the sort runs in one chunk.
MIN_CHUNK = 16384


@cpu_kernel(parallel=True)
def _radix_sort_kernel(keys, values, n_bits, n_chunks):
    """Sort ``keys`` (int64) and carry ``values`` (int32) along; return both sorted."""
    n = keys.shape[0]
    src_k = empty_huge(n, np.int64)
    src_v = empty_huge(n, np.int32)
    src_k[:] = keys
    src_v[:] = values
    dst_k = empty_huge(n, np.int64)
    dst_v = empty_huge(n, np.int32)
    size = (n + n_chunks - 1) // n_chunks
    hist = np.zeros((n_chunks, RADIX), dtype=np.int64)
    shift = 0
    while shift < n_bits:
        # Count each chunk's digits.
        for c in prange(n_chunks):
            for d in range(RADIX):
                hist[c, d] = 0
            # Unsigned indices: no negative-index wraparound code per access.
            for i in range(c * size, min(n, (c + 1) * size)):
                ui = np.uint64(i)
                hist[c, np.uint64((src_k[ui] >> shift) & (RADIX - 1))] += 1
        # Skip a pass whose digit is constant.
        used = 0
        for d in range(RADIX):
            total = 0
            for c in range(n_chunks):
                total += hist[c, d]
            if total > 0:
                used += 1
        if used > 1:
            # Exclusive scan in (digit, chunk) order gives each chunk its slots.
            offset = 0
            for d in range(RADIX):
                for c in range(n_chunks):
                    count = hist[c, d]
                    hist[c, d] = offset
                    offset += count
            # Stable scatter, chunk by chunk in parallel.
            for c in prange(n_chunks):
                for i in range(c * size, min(n, (c + 1) * size)):
                    ui = np.uint64(i)
                    d = np.uint64((src_k[ui] >> shift) & (RADIX - 1))
                    j = hist[c, d]
                    hist[c, d] = j + 1
                    uj = np.uint64(j)
                    dst_k[uj] = src_k[ui]
                    dst_v[uj] = src_v[ui]
            src_k, dst_k = dst_k, src_k
            src_v, dst_v = dst_v, src_v
        shift += RADIX_BITS
    return src_k, src_v


def radix_sort(keys: np.ndarray, values: np.ndarray, n_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(keys, values)`` stably sorted by the low ``n_bits`` bits of ``keys``.

    Parameters
    ----------
    keys : (n,) int64
        Sort keys, non-negative.
    values : (n,) int32
        Payload carried along with its key.
    n_bits : int
        Significant key bits (keys must be below ``2**n_bits``).

    Returns
    -------
    keys, values : (n,) int64, (n,) int32
        New arrays, sorted; equal keys keep their input order.
    """
    n = keys.shape[0]
    n_chunks = int(min(max(1, n // MIN_CHUNK), 4 * numba.get_num_threads()))
    sorted_pair: tuple[np.ndarray, np.ndarray] = _radix_sort_kernel(
        np.ascontiguousarray(keys, dtype=np.int64),
        np.ascontiguousarray(values, dtype=np.int32),
        int(n_bits),
        n_chunks,
    )
    return sorted_pair
