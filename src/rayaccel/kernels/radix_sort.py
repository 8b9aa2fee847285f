"""Parallel least-significant-digit radix sort of int32 or int64 keys with int32 payloads.

Each pass sorts by one digit of at most 12 bits (the key's bits split evenly over the
fewest passes, so 23-bit cell ids take two passes and 30-bit Morton codes three),
stably: the input is cut into fixed chunks, every chunk counts its digits in parallel
(one private histogram per chunk), a serial exclusive scan over (digit, chunk) turns
the counts into write offsets, and every chunk scatters its keys in parallel to its
reserved slots, in order.
Stability makes the result the unique stable sort, whatever the number of chunks
or threads (Satish, Harris, Garland 2009, "Designing Efficient Sorting Algorithms
for Manycore GPUs", IPDPS, is the GPU form). A pass whose digit is the same for
every key is skipped, so equal or short keys cost one counting pass per digit.
Cost O(passes · n); 63-bit keys need 6 passes.
"""

from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
from numba import prange

from rayaccel._hugepages import empty_huge
from rayaccel._jit import cpu_kernel

#: Widest digit: a chunk's 4,096 counters (32 KiB) fit a 48 KiB L1 data cache.
MAX_DIGIT_BITS = 12
#: Below this many keys the sort runs in one chunk.
MIN_CHUNK = 16384


@functools.cache
def _sort_kernel(key_type: type) -> Any:
    """Return the compiled sort of ``key_type`` keys (one kernel, one signature, per width)."""

    def radix_sort_py(keys, values, n_bits, digit_bits, n_chunks):
        """Sort ``keys`` and carry ``values`` (int32) along; return both sorted."""
        radix = 1 << digit_bits
        n = keys.shape[0]
        src_k = empty_huge(n, key_type)
        src_v = empty_huge(n, np.int32)
        src_k[:] = keys
        src_v[:] = values
        dst_k = empty_huge(n, key_type)
        dst_v = empty_huge(n, np.int32)
        size = (n + n_chunks - 1) // n_chunks
        hist = np.zeros((n_chunks, radix), dtype=np.int64)
        shift = 0
        while shift < n_bits:
            # Count each chunk's digits.
            for c in prange(n_chunks):
                for d in range(radix):
                    hist[c, d] = 0
                # Unsigned indices: no negative-index wraparound code per access.
                for i in range(c * size, min(n, (c + 1) * size)):
                    ui = np.uint64(i)
                    hist[c, np.uint64((src_k[ui] >> shift) & (radix - 1))] += 1
            # Skip a pass whose digit is constant.
            used = 0
            for d in range(radix):
                total = 0
                for c in range(n_chunks):
                    total += hist[c, d]
                if total > 0:
                    used += 1
            if used > 1:
                # Exclusive scan in (digit, chunk) order gives each chunk its slots.
                offset = 0
                for d in range(radix):
                    for c in range(n_chunks):
                        count = hist[c, d]
                        hist[c, d] = offset
                        offset += count
                # Stable scatter, chunk by chunk in parallel.
                for c in prange(n_chunks):
                    for i in range(c * size, min(n, (c + 1) * size)):
                        ui = np.uint64(i)
                        d = np.uint64((src_k[ui] >> shift) & (radix - 1))
                        j = hist[c, d]
                        hist[c, d] = j + 1
                        uj = np.uint64(j)
                        dst_k[uj] = src_k[ui]
                        dst_v[uj] = src_v[ui]
                src_k, dst_k = dst_k, src_k
                src_v, dst_v = dst_v, src_v
            shift += digit_bits
        return src_k, src_v

    return cpu_kernel(parallel=True)(radix_sort_py)


def digit_bits(n_bits: int) -> int:
    """Return the digit width that sorts ``n_bits``-bit keys in the fewest even passes."""
    passes = max(1, -(-n_bits // MAX_DIGIT_BITS))
    return max(1, -(-n_bits // passes))


def radix_sort(keys: np.ndarray, values: np.ndarray, n_bits: int) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(keys, values)`` stably sorted by the low ``n_bits`` bits of ``keys``.

    Parameters
    ----------
    keys : (n,) int32 or int64
        Sort keys, non-negative (int32 keys move a third less memory per pass).
    values : (n,) int32
        Payload carried along with its key.
    n_bits : int
        Significant key bits (keys must be below ``2**n_bits``).

    Returns
    -------
    keys, values : (n,) int32 or int64 as given (other integers: int64), (n,) int32
        New arrays, sorted; equal keys keep their input order.
    """
    key_type = np.int32 if np.asarray(keys).dtype == np.int32 else np.int64
    n = keys.shape[0]
    n_chunks = int(min(max(1, n // MIN_CHUNK), 4 * numba.get_num_threads()))
    sorted_pair: tuple[np.ndarray, np.ndarray] = _sort_kernel(key_type)(
        np.ascontiguousarray(keys, dtype=key_type),
        np.ascontiguousarray(values, dtype=np.int32),
        int(n_bits),
        digit_bits(int(n_bits)),
        n_chunks,
    )
    return sorted_pair
