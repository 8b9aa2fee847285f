"""Linear BVH (LBVH): Morton-sorted primitives, Apetrei 2014 or Karras 2012 hierarchy.

Lauterbach et al. 2009 ("Fast BVH Construction on GPUs", Eurographics) sort the
primitives along a Morton curve so that a BVH is implied by the bit prefixes of the
sorted codes: every inner node covers a key range sharing a common prefix and splits
where the next bit flips. ``δ(i, j)`` is the common-prefix length of keys i and j
(−1 outside the array; equal keys fall back to ``64 + clz(i xor j)``, which splits
duplicates by index). Two ways to find that radix tree, giving the same tree:

- **Apetrei 2014** ("Fast and Simple Agglomerative LBVH Construction", CGVC), the
  default: bottom-up, one thread per leaf. A node covering keys ``[a, b]`` is a child
  of the split between ``b`` and ``b + 1`` or of the one between ``a - 1`` and ``a``,
  whichever has the larger δ; the first child to reach a parent stops, the second
  finishes it. The refit and the SAH leaf collapse happen in the same pass
  (:func:`apetrei_refit_collapse`), so no separate refit walks the tree.
- **Karras 2012** ("Maximizing Parallelism in the Construction of BVHs, Octrees, and
  k-d Trees", HPG, §3–4): each inner node ``i`` finds its own range and split
  independently:

  1. direction ``d = sign(δ(i, i+1) − δ(i, i−1))``; ``δ_min = δ(i, i−d)``;
  2. exponential then binary search for the other end ``j`` of the range;
  3. binary search for the split ``γ``; children are leaf ``γ`` / inner ``γ`` and leaf
     ``γ+1`` / inner ``γ+1``.

  Boxes then come from one bottom-up refit (:mod:`rayaccel.bvh.builders.refit`), which also
  collapses subtrees into leaves of up to ``max_leaf_size`` primitives where the SAH
  prefers a leaf (as the PLOC authors do).

On the 1.4M-triangle kitchen the Apetrei pass builds the same tree in about 0.7× the
Karras emission's time (it replaces the range searches, the separate leaf-row pass and
the refit's post-order walks). Degenerate input (all centroids equal) gives equal
keys, split by index: a balanced tree. Keys with 63 bits can nest deeper than
``MAX_DEPTH`` on very skewed scenes; the canonical conversion rebalances such
subtrees (:mod:`rayaccel.bvh.layouts.linked_tree`). Cost O(n) after an O(n) radix sort; the
fastest builder, with the lowest quality.

Given ``refs`` (:class:`~rayaccel.bvh.builders.refs.BuildRefs`, e.g. from ``+presplit``),
it builds over those boxes instead of one per triangle; leaves name mesh triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._hugepages import empty_huge, full_huge
from rayaccel._jit import atomic_exchange, cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.common import reference_boxes
from rayaccel.bvh.builders.refit import collapse_node
from rayaccel.bvh.builders.refs import BuildRefs
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import (
    LinkedTree,
    collapsed_to_canonical,
    refitted_to_canonical,
)
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.morton import count_leading_zeros, morton_codes
from rayaccel.kernels.radix_sort import radix_sort
from rayaccel.scene.mesh import TriangleMesh

#: Hierarchy emissions of :class:`LbvhOptions` (they give the same tree).
EMISSIONS = ("apetrei", "karras")


@dataclass(frozen=True, slots=True)
class LbvhOptions:
    """Options of :func:`build_lbvh`.

    Attributes
    ----------
    morton_bits : int
        30 (10 bits per axis) or 63 (21 bits per axis). 30 is the classic choice and
        sorts in half the passes; 63 separates primitives in large scenes better.
    emission : {"apetrei", "karras"}
        How the hierarchy is found; both give the same tree. ``"apetrei"`` (Apetrei
        2014) finds it bottom-up in the same pass as the refit and the SAH collapse;
        ``"karras"`` (Karras 2012) searches each inner node's range, then refits.
    max_leaf_size : int
        Largest leaf the SAH collapse may form (1..64).
    traversal_cost, intersection_cost : float
        SAH constants of the leaf collapse (Karras & Aila 2013 use 1.2 and 1).
    """

    morton_bits: int = 30
    emission: str = "apetrei"
    max_leaf_size: int = 8
    traversal_cost: float = 1.2
    intersection_cost: float = 1.0

    def __post_init__(self) -> None:
        if self.morton_bits not in (30, 63):
            raise InvalidInputError(f"morton_bits: expected 30 or 63, got {self.morton_bits}")
        if self.emission not in EMISSIONS:
            raise InvalidInputError(f"emission: expected one of {EMISSIONS}, got {self.emission!r}")
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


@cpu_inline
def _leaf_row(k, order, prim_lo, prim_hi, left, right, lo, hi, first, count, n_inner):
    """Fill leaf ``k``'s row (node ``n_inner + k``, reference ``order[k]``); return its id."""
    node = n_inner + k
    p = order[k]
    for a in range(3):
        lo[node, a] = prim_lo[p, a]
        hi[node, a] = prim_hi[p, a]
    left[node] = -1
    right[node] = -1
    first[node] = k
    count[node] = 1
    return node


@cpu_kernel(parallel=True)
def _leaf_rows(order, prim_lo, prim_hi, left, right, lo, hi, first, count, n_inner):
    """Fill the leaf rows (one primitive each, in sorted order) of the linked arrays."""
    for k in prange(order.shape[0]):
        _leaf_row(k, order, prim_lo, prim_hi, left, right, lo, hi, first, count, n_inner)


@cpu_kernel(parallel=True)
def apetrei_refit_collapse(
    codes, order, prim_lo, prim_hi, left, right, lo, hi, first, count, max_leaf, c_inner, c_prim
):  # fmt: skip
    """Find the LBVH hierarchy bottom-up, refitting and collapsing on the way (Apetrei 2014).

    One thread per leaf, in parallel, climbs from its leaf while it is the second child
    of a node to finish. A node covering the key range ``[a, b]`` is the left child of
    the node split between keys ``b`` and ``b + 1``, or the right child of the one split
    between ``a - 1`` and ``a``: whichever split is lower in the radix tree, i.e. whose
    neighbouring keys share the longer prefix (Karras' δ, index bits breaking ties, so
    the tree is exactly the Karras emission's; inner node ``i`` is the split between
    keys ``i`` and ``i + 1``). The child writes its link in that parent and exchanges
    its far range end with the parent's slot (an atomic exchange): the first child
    to arrive stops; the second gets its sibling's end, so it knows the parent's
    range, and finishes the parent with :func:`rayaccel.bvh.builders.refit.collapse_node`
    (box, SAH cost, collapse decision), whose inputs its sibling's thread wrote before
    its exchange. Every node gets the arithmetic of a serial post-order walk, so the
    result is the same for any thread count.

    Writes every row of the linked arrays (leaf ``k`` is node ``n - 1 + k``, holding
    reference ``order[k]``). Returns ``(root, as_leaf, height, n_eff, n_prim)`` as
    :func:`rayaccel.bvh.builders.refit.refit_collapse` does (``n >= 2``).
    """
    n = codes.shape[0]
    n_inner = n - 1
    n_nodes = 2 * n - 1
    as_leaf = empty_huge(n_nodes, np.uint8)
    height = empty_huge(n_nodes, np.int32)
    n_eff = empty_huge(n_nodes, np.int32)
    n_prim = empty_huge(n_nodes, np.int32)
    cost = empty_huge(n_nodes, np.float64)
    # The range end left by the first child to finish each inner node (-1: none yet).
    other_end = full_huge(n_inner, -1, np.int32)
    root = np.empty(1, dtype=np.int32)
    for k in prange(n):
        # The leaf row, then its cost and collapse data.
        leaf = _leaf_row(k, order, prim_lo, prim_hi, left, right, lo, hi, first, count, n_inner)
        height[leaf] = 0
        collapse_node(
            leaf, left, right, lo, hi, count, max_leaf, c_inner, c_prim, True,
            as_leaf, height, n_eff, n_prim, cost,
        )  # fmt: skip
        # Climb while this thread finishes the parent.
        # (a signed copy of the loop index: prange's may be unsigned, and numba makes
        # ``uint64 - int64`` a float)
        node = np.int64(leaf)
        a = np.int64(k)
        b = np.int64(k)
        while a > 0 or b < n_inner:
            if a == 0 or (b < n_inner and _delta(codes, b, b + 1) > _delta(codes, a - 1, a)):
                parent = b
                left[parent] = node
                sibling_end = atomic_exchange(other_end, parent, np.int32(a))
                if sibling_end < 0:
                    break
                b = sibling_end
            else:
                parent = a - 1
                right[parent] = node
                sibling_end = atomic_exchange(other_end, parent, np.int32(b))
                if sibling_end < 0:
                    break
                a = sibling_end
            collapse_node(
                parent, left, right, lo, hi, count, max_leaf, c_inner, c_prim, True,
                as_leaf, height, n_eff, n_prim, cost,
            )  # fmt: skip
            node = parent
        if a == 0 and b == n_inner:
            root[0] = node
    return root[0], as_leaf, height, n_eff, n_prim


def sorted_codes(
    prim_lo: np.ndarray, prim_hi: np.ndarray, morton_bits: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return the references' Morton codes, sorted, and the sorting permutation."""
    n = prim_lo.shape[0]
    bits_per_axis = 10 if morton_bits == 30 else 21
    codes = morton_codes(prim_lo, prim_hi, bits_per_axis)
    return radix_sort(codes, np.arange(n, dtype=np.int32), 3 * bits_per_axis)


def empty_linked_tree(order: np.ndarray, prim_id: np.ndarray) -> LinkedTree:
    """Return the uninitialised linked tree of ``n - 1`` inner slots and ``n`` leaves.

    Inner slots get ids ``0..n-2`` and leaf ``k`` (the ``k``-th reference in code order)
    id ``n - 1 + k``; ``prim_index`` names each leaf's primitive (``prim_id`` of the
    reference). Every row is left for the builder's kernels to write.
    """
    n_nodes = 2 * order.shape[0] - 1
    return LinkedTree(
        left=np.empty(n_nodes, dtype=np.int32),
        right=np.empty(n_nodes, dtype=np.int32),
        lo=np.empty((n_nodes, 3), dtype=np.float32),
        hi=np.empty((n_nodes, 3), dtype=np.float32),
        first=np.empty(n_nodes, dtype=np.int32),
        count=np.empty(n_nodes, dtype=np.int32),
        prim_index=np.ascontiguousarray(prim_id[order], dtype=np.int32),
    )


def sorted_leaf_tree(
    prim_lo: np.ndarray, prim_hi: np.ndarray, prim_id: np.ndarray, morton_bits: int
) -> tuple[np.ndarray, LinkedTree]:
    """Sort references by Morton code; return the sorted codes and an empty linked tree.

    The tree is :func:`empty_linked_tree`'s with its leaf rows filled. The inner slots
    are left uninitialised: the caller's hierarchy (Karras emission, PLOC merges)
    writes every one of their children and the refit their boxes.
    """
    codes, order = sorted_codes(prim_lo, prim_hi, morton_bits)
    tree = empty_linked_tree(order, prim_id)
    _leaf_rows(
        order, prim_lo, prim_hi, tree.left, tree.right, tree.lo, tree.hi, tree.first,
        tree.count, order.shape[0] - 1,
    )  # fmt: skip
    return codes, tree


def build_lbvh_refs(
    prim_lo: np.ndarray, prim_hi: np.ndarray, prim_id: np.ndarray, n_prims: int, opt: LbvhOptions
) -> Bvh2:
    """Build an LBVH over reference boxes (``prim_id`` maps references to primitives)."""
    n = prim_lo.shape[0]
    if opt.emission == "karras" or n == 1:
        codes, tree = sorted_leaf_tree(prim_lo, prim_hi, prim_id, opt.morton_bits)
        if n > 1:
            _karras_kernel(codes, tree.left, tree.right)
        return collapsed_to_canonical(tree, 0, n_prims, opt)
    codes, order = sorted_codes(prim_lo, prim_hi, opt.morton_bits)
    tree = empty_linked_tree(order, prim_id)
    root, as_leaf, height, n_eff, n_prim = apetrei_refit_collapse(
        codes, order, prim_lo, prim_hi, tree.left, tree.right, tree.lo, tree.hi, tree.first,
        tree.count, np.int32(opt.max_leaf_size), np.float64(opt.traversal_cost),
        np.float64(opt.intersection_cost),
    )  # fmt: skip
    return refitted_to_canonical(tree, int(root), n_prims, as_leaf, height, n_eff, n_prim)


@register("builder", "bvh2.lbvh")
def build_lbvh(
    mesh: TriangleMesh, options: LbvhOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Linear BVH: Morton codes, radix sort, Apetrei or Karras emission, SAH collapse.

    Build a linear BVH (see the module docstring).

    The tree's depth is at most ``MAX_DEPTH``.

    References
    ----------
    Apetrei 2014, Fast and Simple Agglomerative LBVH Construction;
    Karras 2012, Maximizing Parallelism in the Construction of BVHs, Octrees, and k-d Trees;
    Lauterbach et al. 2009.
    """
    opt = options or LbvhOptions()
    prim_lo, prim_hi, ids = reference_boxes(mesh, refs, "bvh2.lbvh")
    return build_lbvh_refs(prim_lo, prim_hi, ids, mesh.n_triangles, opt)
