"""The linked working form of a binary BVH, and its conversion to the canonical layout.

Bottom-up builders (LBVH, PLOC, insertion) and tree optimizers (reinsertion,
rotations, treelets) edit a tree whose nodes name their children explicitly:
``left[i]``/``right[i]`` (``-1`` for a leaf), ``lo``/``hi`` boxes and, for leaves,
a range ``first:first + count`` into a reference array. Node ids carry no order.

:func:`linked_to_canonical` turns such a tree into a canonical
:class:`~rayaccel.bvh.layouts.bvh2.Bvh2` in three passes:

1. A post-order refit (:func:`rayaccel.bvh.builders.refit.refit_collapse`) computes every
   inner box as the union of its children, the subtree SAH cost and, optionally,
   the SAH-based leaf collapsing of Meister & Bittner 2018 §4.4: a subtree of at
   most ``max_leaf_size`` primitives becomes one leaf when
   ``C_prim·A·N <= C_inner·A + cost(left) + cost(right)``.
2. A depth-first emission numbers nodes root 0, siblings adjacent, and copies the
   references of each leaf so that leaves tile ``prim_index`` in order.
3. The depth guard: a subtree that would end deeper than ``MAX_DEPTH`` is re-emitted
   as a balanced tree over its leaves, in their left-to-right order (which for a
   Morton-ordered build keeps spatial coherence). It fires at the first node on the
   path where ``depth + ceil(log2(leaves)) >= MAX_DEPTH - 1``, so the balanced
   subtree always fits; ordinary trees are never touched.

Passes 1 and 2 run in parallel over the subtrees below a top frontier
(:func:`rayaccel.bvh.builders.refit.top_frontier`); since a node's descendants take one
contiguous block of ids and references in the depth-first numbering, the serial walk
over the top levels reserves each subtree's block and the output is exactly the
serial one, whatever the thread count.

A tree with more references than primitives (spatial splits, pre-split input) may
collapse two pieces of one triangle into one leaf; the copies are then dropped
(:func:`rayaccel.bvh.builders.refs.remove_leaf_duplicates`, Karras & Aila 2013 §5.9).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numba
import numpy as np
from numba import prange

from rayaccel._hugepages import empty_huge, zeros_huge
from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.builders.common import canonical_bvh2, ceil_log2
from rayaccel.bvh.builders.refit import FRONTIER_SIZE, push, refit_collapse, top_frontier
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2
from rayaccel.dtypes import INDEX, FloatArray, IntArray


class LinkedTree(NamedTuple):
    """A binary tree with explicit child links (see the module docstring).

    Attributes
    ----------
    left, right : (n,) int32
        Children of an inner node; ``-1`` marks a leaf.
    lo, hi : (n, 3) float32
        Node boxes (inner boxes are recomputed by the conversion).
    first, count : (n,) int32
        Leaf reference range in ``prim_index``; ignored for inner nodes.
    prim_index : (n_refs,) int32
        Primitive id of each reference.
    """

    left: IntArray
    right: IntArray
    lo: FloatArray
    hi: FloatArray
    first: IntArray
    # Shadows tuple.count, which nothing calls on this record (builders read ``tree.count``).
    count: IntArray  # type: ignore[assignment]
    prim_index: IntArray


def to_linked(bvh: Bvh2) -> tuple[LinkedTree, IntArray]:
    """Return the linked form of a canonical tree (same node ids) and its parent array.

    The root is node 0 and its parent is ``-1``.
    """
    inner = bvh.node_count == 0
    left = np.where(inner, bvh.node_first, -1).astype(INDEX)
    right = np.where(inner, bvh.node_first + 1, -1).astype(INDEX)
    parent = np.full(bvh.n_nodes, -1, dtype=INDEX)
    ids = np.flatnonzero(inner).astype(INDEX)
    parent[left[ids]] = ids
    parent[right[ids]] = ids
    tree = LinkedTree(
        left,
        right,
        bvh.node_lo.copy(),
        bvh.node_hi.copy(),
        bvh.node_first.copy(),
        bvh.node_count.copy(),
        bvh.prim_index,
    )
    return tree, parent


def _emit_walk_py(
    start, start_slot, start_depth, next_id, next_ref, stop, is_frontier,
    left, right, lo, hi, first, count, prim_index, as_leaf, height, n_eff, n_prim,
    out_lo, out_hi, out_first, out_count, out_prim,
    task_node, task_slot, task_depth, task_id, task_ref, inner_slots,
):  # fmt: skip
    """Emit the subtree of ``start`` depth-first into slot ``start_slot`` and onwards.

    Children pairs are numbered from ``next_id``, references copied from ``next_ref``.
    With ``stop``, a frontier node is not descended into: it becomes a task (its
    descendants' ids and references are reserved, as the serial walk would number
    them) and every inner slot written is listed in ``inner_slots``. Returns
    ``(next_id, next_ref, n_tasks, n_inner_slots)``.
    """
    size = 2 * MAX_DEPTH + 8
    s_node = np.empty(size, dtype=np.int32)
    s_slot = np.empty(size, dtype=np.int32)
    s_depth = np.empty(size, dtype=np.int32)
    s_a = np.empty(size, dtype=np.int32)
    s_b = np.empty(size, dtype=np.int32)
    # Scratch for walking (possibly very deep) subtrees and for rebalanced leaf lists.
    g_stack = np.empty(2 * MAX_DEPTH + 64, dtype=np.int32)
    gather = np.empty(n_eff[start], dtype=np.int32)
    n_tasks = 0
    n_inner = 0
    s_node[0] = start
    s_slot[0] = start_slot
    s_depth[0] = start_depth
    sp = 1
    while sp > 0:
        sp -= 1
        node = s_node[sp]
        slot = s_slot[sp]
        depth = s_depth[sp]
        a = s_a[sp]
        b = s_b[sp]
        # A range task of a rebalanced subtree: one leaf, or split the leaf list in half.
        if node < 0:
            if b - a > 1:
                mid = (a + b) // 2
                out_first[slot] = next_id
                out_count[slot] = 0
                if stop:
                    inner_slots[n_inner] = slot
                    n_inner += 1
                for c in range(2):
                    s_node[sp] = -1
                    s_slot[sp] = next_id + 1 - c
                    s_depth[sp] = depth + 1
                    s_a[sp] = mid if c == 0 else a
                    s_b[sp] = b if c == 0 else mid
                    sp += 1
                next_id += 2
                continue
            node = gather[a]
        # Ids, slots and reference positions are non-negative: indexing with unsigned
        # integers spares numba's negative-index wraparound code on every access.
        u = np.uint64(node)
        us = np.uint64(slot)
        if as_leaf[u]:
            # Emit a leaf: copy the references of every original leaf below, left first.
            for k in range(3):
                out_lo[us, k] = lo[u, k]
                out_hi[us, k] = hi[u, k]
            out_first[us] = next_ref
            out_count[us] = n_prim[u]
            gp = 1
            g_stack[0] = node
            while gp > 0:
                gp -= 1
                x = np.uint64(g_stack[gp])
                if left[x] < 0:
                    for r in range(first[x], first[x] + count[x]):
                        out_prim[np.uint64(next_ref)] = prim_index[np.uint64(r)]
                        next_ref += 1
                else:
                    g_stack = push(g_stack, gp, right[x])
                    g_stack = push(g_stack, gp + 1, left[x])
                    gp += 2
            continue
        if stop and is_frontier[u]:
            # Another thread emits this subtree into the ids and references reserved here.
            task_node[n_tasks] = node
            task_slot[n_tasks] = slot
            task_depth[n_tasks] = depth
            task_id[n_tasks] = next_id
            task_ref[n_tasks] = next_ref
            n_tasks += 1
            next_id += 2 * n_eff[node] - 2
            next_ref += n_prim[node]
            continue
        if depth + height[u] > MAX_DEPTH and depth + ceil_log2(n_eff[u]) >= MAX_DEPTH - 1:
            # Too deep: collect the subtree's leaves in order, re-emit them balanced.
            m = 0
            gp = 1
            g_stack[0] = node
            while gp > 0:
                gp -= 1
                x = g_stack[gp]
                if as_leaf[x]:
                    gather[m] = x
                    m += 1
                else:
                    g_stack = push(g_stack, gp, right[x])
                    g_stack = push(g_stack, gp + 1, left[x])
                    gp += 2
            s_node[sp] = -1
            s_slot[sp] = slot
            s_depth[sp] = depth
            s_a[sp] = 0
            s_b[sp] = m
            sp += 1
            continue
        # Inner node: allocate the sibling pair, push right then left (left emitted first).
        out_first[us] = next_id
        out_count[us] = 0
        if stop:
            inner_slots[n_inner] = slot
            n_inner += 1
        s_node[sp] = right[u]
        s_slot[sp] = next_id + 1
        s_depth[sp] = depth + 1
        s_node[sp + 1] = left[u]
        s_slot[sp + 1] = next_id
        s_depth[sp + 1] = depth + 1
        sp += 2
        next_id += 2
    return next_id, next_ref, n_tasks, n_inner


_emit_walk = cpu_inline(_emit_walk_py)


def _inner_box_py(out_lo, out_hi, out_first, out_count, i):
    """Set inner slot ``i``'s box to the union of its children's (no-op for a leaf)."""
    u = np.uint64(i)
    if out_count[u] == 0:
        c = np.uint64(out_first[u])
        d = np.uint64(out_first[u] + 1)
        for k in range(3):
            out_lo[u, k] = min(out_lo[c, k], out_lo[d, k])
            out_hi[u, k] = max(out_hi[c, k], out_hi[d, k])


_inner_box = cpu_inline(_inner_box_py)


@cpu_kernel(parallel=True)
def _emit_kernel(
    root, left, right, lo, hi, first, count, prim_index, as_leaf, height, n_eff, n_prim,
    n_threads,
):  # fmt: skip
    """Emit the canonical arrays depth-first (see the module docstring).

    The top levels are emitted serially down to the :func:`top_frontier` subtrees,
    whose id and reference ranges are reserved exactly where a serial walk would put
    them; the subtrees are then emitted in parallel, ``n_threads`` workers taking them
    one at a time from a shared counter. The output is the serial one.
    """
    n = left.shape[0]
    n_out = 2 * n_eff[root] - 1
    out_lo = empty_huge((n_out, 3), np.float32)
    out_hi = empty_huge((n_out, 3), np.float32)
    out_first = empty_huge(n_out, np.int32)
    out_count = empty_huge(n_out, np.int32)
    out_prim = empty_huge(n_prim[root], np.int32)
    frontier, _ = top_frontier(root, left, right, FRONTIER_SIZE)
    is_frontier = zeros_huge(n, np.uint8)
    for f in frontier:
        is_frontier[f] = 1
    m = frontier.shape[0]
    task_node = np.empty(m, dtype=np.int32)
    task_slot = np.empty(m, dtype=np.int32)
    task_depth = np.empty(m, dtype=np.int32)
    task_id = np.empty(m, dtype=np.int32)
    task_ref = np.empty(m, dtype=np.int32)
    inner_slots = empty_huge(n_out, np.int32)
    # Top levels, serially; frontier subtrees become tasks.
    _, _, n_tasks, n_inner = _emit_walk(
        root, 0, 0, 1, 0, True, is_frontier,
        left, right, lo, hi, first, count, prim_index, as_leaf, height, n_eff, n_prim,
        out_lo, out_hi, out_first, out_count, out_prim,
        task_node, task_slot, task_depth, task_id, task_ref, inner_slots,
    )  # fmt: skip
    # Each subtree, then its inner boxes (children always follow their parent).
    counter = new_counter()
    for _worker in prange(worker_count(n_tasks, n_threads, True)):
        while True:
            t = next_item(counter, n_tasks)
            if t < 0:
                break
            _emit_walk(
                task_node[t], task_slot[t], task_depth[t], task_id[t], task_ref[t], False,
                is_frontier, left, right, lo, hi, first, count, prim_index, as_leaf, height,
                n_eff, n_prim, out_lo, out_hi, out_first, out_count, out_prim,
                task_node, task_slot, task_depth, task_id, task_ref, inner_slots,
            )  # fmt: skip
            base = task_id[t]
            for i in range(base + 2 * n_eff[task_node[t]] - 3, base - 1, -1):
                _inner_box(out_lo, out_hi, out_first, out_count, i)
            _inner_box(out_lo, out_hi, out_first, out_count, task_slot[t])
    # Inner boxes of the top levels, deepest ids first.
    top_slots = np.sort(inner_slots[:n_inner])
    for i in range(n_inner - 1, -1, -1):
        _inner_box(out_lo, out_hi, out_first, out_count, top_slots[i])
    return out_lo, out_hi, out_first, out_count, out_prim


def linked_to_canonical(
    tree: LinkedTree,
    root: int,
    n_prims: int,
    *,
    collapse: bool = False,
    max_leaf_size: int = 8,
    inner_cost: float = 1.2,
    prim_cost: float = 1.0,
) -> Bvh2:
    """Return the canonical :class:`Bvh2` of a linked tree (refit, collapse, depth guard).

    Parameters
    ----------
    tree : LinkedTree
        Leaf boxes must bound their references; inner boxes are recomputed (in place).
    root : int
        Id of the root node.
    n_prims : int
        Number of primitives of the mesh.
    collapse : bool
        Merge subtrees of at most ``max_leaf_size`` references into one leaf when the
        SAH says a leaf is no more expensive.
    max_leaf_size : int
        Largest subtree, in references, that ``collapse`` may merge into one leaf.
    inner_cost, prim_cost : float
        SAH constants of the collapse decision.
    """
    as_leaf, height, n_eff, n_prim, _ = refit_collapse(
        np.int32(root),
        tree.left,
        tree.right,
        tree.lo,
        tree.hi,
        tree.count,
        np.int32(max_leaf_size),
        np.float64(inner_cost),
        np.float64(prim_cost),
        bool(collapse),
    )
    return refitted_to_canonical(tree, root, n_prims, as_leaf, height, n_eff, n_prim)


def refitted_to_canonical(
    tree: LinkedTree,
    root: int,
    n_prims: int,
    as_leaf: np.ndarray,
    height: IntArray,
    n_eff: IntArray,
    n_prim: IntArray,
) -> Bvh2:
    """Emit the canonical :class:`Bvh2` of a refitted linked tree (passes 2 and 3).

    The arrays are :func:`rayaccel.bvh.builders.refit.refit_collapse`'s, or those of a builder
    that refits and collapses on its own (the Apetrei emission of ``bvh2.lbvh``).
    """
    lo, hi, first, count, prim = _emit_kernel(
        np.int32(root),
        tree.left,
        tree.right,
        tree.lo,
        tree.hi,
        tree.first,
        tree.count,
        tree.prim_index,
        as_leaf,
        height,
        n_eff,
        n_prim,
        numba.get_num_threads(),
    )
    return canonical_bvh2(lo, hi, first, count, prim, n_prims)


def collapsed_to_canonical(tree: LinkedTree, root: int, n_prims: int, options: Any) -> Bvh2:
    """:func:`linked_to_canonical` with SAH leaf collapsing, constants taken from ``options``.

    ``options`` is any builder or step options object with ``max_leaf_size``,
    ``traversal_cost`` and ``intersection_cost`` (LBVH, PLOC, insertion, treelets,
    ``+collapse``).
    """
    return linked_to_canonical(
        tree,
        root,
        n_prims,
        collapse=True,
        max_leaf_size=options.max_leaf_size,
        inner_cost=options.traversal_cost,
        prim_cost=options.intersection_cost,
    )
