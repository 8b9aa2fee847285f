"""Minimal perfect hashing of node keys (two-level displacement, greedy construction).

Binder & Keller 2016 (building block 2) map a node's *key* (root 1, children
``2k`` and ``2k + 1``) to its address with a perfect hash, so backtracking to any
ancestor's sibling costs one lookup. The hash is the two-level scheme of Tarjan &
Yao 1979, "Storing a Sparse Table" (CACM 22(11))::

    h(k) = (k mod |T| + D[k mod |D|]) mod |T|,        value = T[h(k)]

The displacement table ``D`` is filled greedily (Fox, Heath, Chen & Daoud 1992,
"Practical Minimal Perfect Hash Functions for Large Databases", CACM 35(1)):
bucket the keys by ``k mod |D|``, place the buckets in decreasing size (ties by
bucket index), and give each a displacement ``δ`` whose slots ``(k mod |T| + δ) mod
|T|`` are all distinct and free. The candidates are the free slots for the bucket's
first key (a union-find "next free slot" structure skips the taken ones), searched
cyclically from a start scattered per bucket (``scatter``, the default) or from
``δ = 0`` (the smallest displacement, as in the paper). Node keys are structured
(the keys of one bucket are congruent modulo the power of two ``|D|``, and many
buckets share the same key differences), so buckets searched from ``δ = 0`` pile up
where earlier buckets of the same shape went and probe thousands of candidates each;
a scattered start spreads them like random probing. With ``|T| = n`` the hash is
*minimal*: no empty slot and no stored keys (lookups only ever ask for existing keys).
When a bucket's keys collide modulo ``|T|`` (checked before any is placed) or a
bucket finds no displacement, the table grows by ``max(4, 5%)`` and the construction
restarts.

Test vector (the talk): ``S = {1,2,3,4,5,8,9,18,19,38,39}``, ``|T| = 11``,
``|D| = 8``, searched from ``δ = 0``, gives ``D = [2,0,0,0,0,0,1,5]`` and
``T = [39,1,2,3,4,5,38,18,19,9,8]`` (values equal to keys).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_kernel
from rayaccel.dtypes import INDEX, IntArray
from rayaccel.errors import InvalidInputError

#: Bytes per table and displacement entry (int32).
ENTRY_BYTES = 4
#: Knuth's multiplicative hash constant: bucket ``b`` starts its search ``b · _SCATTER``
#: slots beyond its first key's base (mod ``|T|``).
_SCATTER = 2654435761


@dataclass(frozen=True, slots=True, eq=False)
class PerfectHash:
    """A two-level minimal perfect hash from int64 keys to int32 values.

    Attributes
    ----------
    table : (n_table,) int32
        ``T``: the value of the key hashed to each slot (``-1`` for an empty slot).
    disp : (n_disp,) int32
        ``D``: the displacement of each bucket.
    """

    table: IntArray
    disp: IntArray

    def lookup(self, keys: np.ndarray) -> IntArray:
        """Return the values of ``keys`` (which must be among the keys hashed)."""
        k = np.asarray(keys, dtype=np.int64)
        n_table, n_disp = self.table.shape[0], self.disp.shape[0]
        values: IntArray = self.table[(k % n_table + self.disp[k % n_disp]) % n_table]
        return values

    def nbytes(self) -> int:
        """Bytes of both tables."""
        return int(self.table.nbytes + self.disp.nbytes)


@cpu_kernel()
def _find_free(next_free, slot):
    """Return the first free slot at or after ``slot`` (cyclic), compressing the path."""
    root = slot
    while next_free[root] != root:
        root = next_free[root]
    while next_free[slot] != root:
        following = next_free[slot]
        next_free[slot] = root
        slot = following
    return root


@cpu_kernel()
def _next_free_slot(next_free, slot, n_table):
    """Return the first free slot at or after ``slot``, cyclically (-1: the table is full)."""
    found = _find_free(next_free, slot)
    if found == n_table:
        found = _find_free(next_free, np.int64(0))
    return found if found < n_table else -1


@cpu_kernel()
def _place(keys, values, n_table, n_disp, table, disp, scatter):
    """Greedy displacement search; return True when every bucket was placed."""
    n = keys.shape[0]
    # Bucket the keys by k mod |D| (CSR layout).
    size = np.zeros(n_disp, dtype=np.int64)
    for i in range(n):
        size[keys[i] % n_disp] += 1
    start = np.zeros(n_disp + 1, dtype=np.int64)
    for b in range(n_disp):
        start[b + 1] = start[b] + size[b]
    fill = start[:-1].copy()
    member = np.empty(n, dtype=np.int64)
    for i in range(n):
        b = keys[i] % n_disp
        member[fill[b]] = i
        fill[b] += 1
    # Two keys of one bucket that collide modulo |T| can never be separated: checked for
    # every bucket before any is placed, so a table that must grow fails at once.
    base = np.empty(max(int(size.max()) if n_disp > 0 else 1, 1), dtype=np.int64)
    for b in range(n_disp):
        for j in range(size[b]):
            base[j] = keys[member[start[b] + j]] % n_table
            for jj in range(j):
                if base[jj] == base[j]:
                    return False
    # Largest buckets first ("decreasing number of dependencies"); stable: ties by index.
    order = np.argsort(-size, kind="mergesort")
    occupied = np.zeros(n_table, dtype=np.bool_)
    # next_free[s] leads to the first free slot at or after s; n_table wraps to 0.
    next_free = np.arange(n_table + 1, dtype=np.int64)
    table[:] = -1
    disp[:] = 0
    for b in order:
        m = size[b]
        if m == 0:
            break
        for j in range(m):
            base[j] = keys[member[start[b] + j]] % n_table
        # A displacement that fits puts the bucket's first key on a free slot, so the
        # candidates are the free slots from ``base[0] + shift`` on, cyclically.
        shift = (b * _SCATTER) % n_table if scatter else 0
        delta = -1
        slot = _next_free_slot(next_free, (base[0] + shift) % n_table, n_table)
        searched = -1
        while slot >= 0:
            distance = (slot - base[0] - shift) % n_table
            if distance <= searched:  # wrapped around: no displacement fits
                break
            searched = distance
            d = (slot - base[0]) % n_table
            ok = True
            for j in range(1, m):
                if occupied[(base[j] + d) % n_table]:
                    ok = False
                    break
            if ok:
                delta = d
                break
            slot = _next_free_slot(next_free, (slot + 1) % n_table, n_table)
        if delta < 0:
            return False
        disp[b] = delta
        for j in range(m):
            slot = (base[j] + delta) % n_table
            occupied[slot] = True
            next_free[slot] = slot + 1
            table[slot] = values[member[start[b] + j]]
    return True


def default_disp_size(n_keys: int) -> int:
    """Return ``|D|``: the largest power of two ``<= max(1, (n - 1) // 2)``."""
    target = max(1, (n_keys - 1) // 2)
    return 1 << (target.bit_length() - 1)


def build_perfect_hash(
    keys: np.ndarray,
    values: np.ndarray,
    n_table: int | None = None,
    n_disp: int | None = None,
    *,
    scatter: bool = True,
) -> PerfectHash:
    """Build a perfect hash from distinct non-negative int64 ``keys`` to int32 ``values``.

    Parameters
    ----------
    keys : (n,) int64
        Distinct non-negative keys.
    values : (n,) int32
        The value each key maps to.
    n_table : int, optional
        ``|T|``; default ``n`` (minimal). Grown by ``max(4, 5%)`` until every bucket fits.
    n_disp : int, optional
        ``|D|``; default the largest power of two ``<= (n - 1) / 2``.
    scatter : bool
        Search each bucket's displacement from a start scattered per bucket (default),
        or from 0 (the smallest displacement that fits, the paper's rule).

    Returns
    -------
    PerfectHash
    """
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    values = np.ascontiguousarray(values, dtype=INDEX)
    n = keys.shape[0]
    if values.shape != keys.shape:
        raise InvalidInputError(f"values: expected shape {keys.shape}, got {values.shape}")
    if n and (keys.min() < 0 or np.unique(keys).size != n):
        raise InvalidInputError("keys: expected distinct non-negative integers")
    size = max(n, 1) if n_table is None else int(n_table)
    n_d = default_disp_size(n) if n_disp is None else int(n_disp)
    if size < n or n_d < 1:
        raise InvalidInputError(f"n_table must be >= {n} and n_disp >= 1")
    while True:
        table = np.empty(size, dtype=INDEX)
        disp = np.empty(n_d, dtype=INDEX)
        if _place(keys, values, size, n_d, table, disp, scatter):
            return PerfectHash(table, disp)
        size += max(4, size // 20)
