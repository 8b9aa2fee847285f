"""Linear BVH (LBVH): Morton-sorted primitives, Karras 2012 hierarchy emission.

Lauterbach et al. 2009 ("Fast BVH Construction on GPUs", Eurographics) sort the
primitives along a Morton curve so that a BVH is implied by the bit prefixes of the
sorted codes: every inner node covers a key range sharing a common prefix and splits
where the next bit flips. Karras 2012 ("Maximizing Parallelism in the Construction of
BVHs, Octrees, and k-d Trees", HPG, §3–4) numbers the n−1 inner nodes so that each
can find its own range and split independently:

1. direction ``d = sign(δ(i, i+1) − δ(i, i−1))``; ``δ_min = δ(i, i−d)``, where
   ``δ(i, j)`` is the common-prefix length of keys i and j (−1 outside the array;
   equal keys fall back to ``64 + clz(i xor j)``, which splits duplicates by index);
2. exponential then binary search for the other end ``j`` of the range;
3. binary search for the split ``γ``; children are leaf ``γ`` / inner ``γ`` and leaf
   ``γ+1`` / inner ``γ+1``.

All inner nodes run in parallel (``prange``). Boxes come from one bottom-up refit
(:mod:`rayaccel.bvh.refit`), which also collapses subtrees into leaves of up to
``max_leaf_size`` primitives where the SAH prefers a leaf (as the PLOC authors do).
Degenerate input (all centroids equal) gives equal keys, split by index: a balanced
tree. Keys with 63 bits can nest deeper than ``MAX_DEPTH`` on very skewed scenes;
the canonical conversion rebalances such subtrees (:mod:`rayaccel.bvh.linked`).
Cost O(n) after an O(n) radix sort; the fastest builder, with the lowest quality.

Given ``refs`` (:class:`~rayaccel.bvh.refs.BuildRefs`, e.g. from ``+presplit``),
it builds over those boxes instead of one per triangle; leaves name mesh triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh._build_common import reference_boxes
from rayaccel.bvh.layout import Bvh2
from rayaccel.bvh.linked import LinkedTree, collapsed_to_canonical
from rayaccel.bvh.morton import count_leading_zeros, morton_codes
from rayaccel.bvh.radix_sort import radix_sort
from rayaccel.bvh.refs import BuildRefs
from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class LbvhOptions:
    """Options of :func:`build_lbvh`.

    Attributes
    ----------
    morton_bits : int
        30 (10 bits per axis) or 63 (21 bits per axis). 30 is the classic choice and
        sorts in half the passes; 63 separates primitives in large scenes better.
    max_leaf_size : int
        Largest leaf the SAH collapse may form (1..64).
    traversal_cost, intersection_cost : float
        SAH constants of the leaf collapse (Karras & Aila 2013 use 1.2 and 1).
    """

    morton_bits: int = 30
    max_leaf_size: int = 8
    traversal_cost: float = 1.2
    intersection_cost: float = 1.0

    def __post_init__(self) -> None:
        if self.morton_bits not in (30, 63):
            raise InvalidInputError(f"morton_bits: expected 30 or 63, got {self.morton_bits}")
        check_leaf_costs(self.max_leaf_size, self.traversal_cost, self.intersection_cost)


def check_leaf_costs(max_leaf_size: int, traversal_cost: float, intersection_cost: float) -> None:
    """Raise :class:`InvalidInputError` for an out-of-range leaf size or SAH constant."""
    if not 1 <= max_leaf_size <= 64:
        raise InvalidInputError(f"max_leaf_size: expected 1..64, got {max_leaf_size}")
    if not traversal_cost >= 0:
        raise InvalidInputError(f"traversal_cost: expected >= 0, got {traversal_cost}")
    if not intersection_cost > 0:
        raise InvalidInputError(f"intersection_cost: expected > 0, got {intersection_cost}")


def _delta_py(codes, i, j):
    """Karras' δ(i, j): common prefix of keys i and j; index bits break ties; −1 outside."""
    if j < 0 or j >= codes.shape[0]:
        return -1
    x = codes[i] ^ codes[j]
    if x == 0:
        return 64 + count_leading_zeros(np.int64(i ^ j))
    return count_leading_zeros(x)


_delta = cpu_inline(_delta_py)


@cpu_kernel(parallel=True)
def _karras_kernel(codes, left, right):
    """Write the children of inner nodes ``0..n-2`` (leaf k is node ``n - 1 + k``)."""
    n = codes.shape[0]
    for i in prange(n - 1):
        # Direction of the range and the prefix the other end must beat.
        d = 1 if _delta(codes, i, i + 1) - _delta(codes, i, i - 1) > 0 else -1
        delta_min = _delta(codes, i, i - d)
        # Exponential search for an upper bound of the range length, then binary search.
        l_max = 2
        while _delta(codes, i, i + l_max * d) > delta_min:
            l_max *= 2
        length = 0
        t = l_max // 2
        while t >= 1:
            if _delta(codes, i, i + (length + t) * d) > delta_min:
                length += t
            t //= 2
        j = i + length * d
        delta_node = _delta(codes, i, j)
        # Binary search for the split: the last key sharing more than delta_node bits with i.
        s = 0
        t = length
        while True:
            t = (t + 1) // 2
            if _delta(codes, i, i + (s + t) * d) > delta_node:
                s += t
            if t <= 1:
                break
        gamma = i + s * d + min(d, 0)
        lo_end = min(i, j)
        hi_end = max(i, j)
        left[i] = n - 1 + gamma if lo_end == gamma else gamma
        right[i] = n - 1 + gamma + 1 if hi_end == gamma + 1 else gamma + 1


@cpu_kernel(parallel=True)
def _leaf_rows(order, prim_lo, prim_hi, left, right, lo, hi, first, count, n_inner):
    """Fill the leaf rows (one primitive each, in sorted order) of the linked arrays."""
    for k in prange(order.shape[0]):
        node = n_inner + k
        p = order[k]
        for a in range(3):
            lo[node, a] = prim_lo[p, a]
            hi[node, a] = prim_hi[p, a]
        left[node] = -1
        right[node] = -1
        first[node] = k
        count[node] = 1


def sorted_leaf_tree(
    prim_lo: np.ndarray, prim_hi: np.ndarray, prim_id: np.ndarray, morton_bits: int
) -> tuple[np.ndarray, LinkedTree]:
    """Sort references by Morton code; return the sorted codes and an empty linked tree.

    The tree has ``n - 1`` inner slots (ids ``0..n-2``) and one leaf per reference
    (ids ``n - 1 + k``, in code order), with leaf rows filled; its ``prim_index``
    names each leaf's primitive (``prim_id`` of the reference). The inner slots are
    left uninitialised: the caller's hierarchy (Karras emission, PLOC merges) writes
    every one of their children and the refit their boxes.
    """
    n = prim_lo.shape[0]
    bits_per_axis = 10 if morton_bits == 30 else 21
    codes = morton_codes(prim_lo, prim_hi, bits_per_axis)
    codes, order = radix_sort(codes, np.arange(n, dtype=np.int32), 3 * bits_per_axis)
    n_nodes = 2 * n - 1
    lo = np.empty((n_nodes, 3), dtype=np.float32)
    hi = np.empty((n_nodes, 3), dtype=np.float32)
    first = np.empty(n_nodes, dtype=np.int32)
    count = np.empty(n_nodes, dtype=np.int32)
    left = np.empty(n_nodes, dtype=np.int32)
    right = np.empty(n_nodes, dtype=np.int32)
    _leaf_rows(order, prim_lo, prim_hi, left, right, lo, hi, first, count, n - 1)
    prim_index = np.ascontiguousarray(prim_id[order], dtype=np.int32)
    return codes, LinkedTree(left, right, lo, hi, first, count, prim_index)


def build_lbvh_refs(
    prim_lo: np.ndarray, prim_hi: np.ndarray, prim_id: np.ndarray, n_prims: int, opt: LbvhOptions
) -> Bvh2:
    """Build an LBVH over reference boxes (``prim_id`` maps references to primitives)."""
    n = prim_lo.shape[0]
    codes, tree = sorted_leaf_tree(prim_lo, prim_hi, prim_id, opt.morton_bits)
    if n > 1:
        _karras_kernel(codes, tree.left, tree.right)
    return collapsed_to_canonical(tree, 0, n_prims, opt)


@register(
    "builder",
    "bvh2.lbvh",
    options=LbvhOptions,
    summary="linear BVH: Morton codes, parallel radix sort, Karras 2012 emission, SAH collapse",
    reference="Karras 2012, Maximizing Parallelism in the Construction of BVHs, Octrees, and "
    "k-d Trees; Lauterbach et al. 2009",
)
def build_lbvh(
    mesh: TriangleMesh, options: LbvhOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Build a linear BVH (see the module docstring).

    Parameters
    ----------
    mesh : TriangleMesh
    options : LbvhOptions, optional
    refs : BuildRefs, optional
        References to build over (e.g. pre-split triangle parts); default one per triangle.

    Returns
    -------
    Bvh2
        Canonical tree; depth at most ``MAX_DEPTH``.
    """
    opt = options or LbvhOptions()
    prim_lo, prim_hi, ids = reference_boxes(mesh, refs, "bvh2.lbvh")
    return build_lbvh_refs(prim_lo, prim_hi, ids, mesh.n_triangles, opt)
