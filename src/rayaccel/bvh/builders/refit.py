"""Bottom-up refitting of BVH boxes, and the SAH subtree costs computed on the way up.

A refit recomputes every inner box as the union of its children's boxes, leaves
first. Bottom-up builders (LBVH, Karras 2012 §4; PLOC) emit topology first and boxes
afterwards, and every tree optimizer refits the path above a changed node.

- :func:`refit_collapse`: one post-order pass over a linked tree (any node order)
  that refits, computes the SAH cost of every subtree and decides SAH leaf
  collapsing (Meister & Bittner 2018 §4.4). Cost O(n), parallel over the subtrees
  below :func:`top_frontier`; each is walked depth-first with an explicit, growable
  stack, so arbitrarily deep trees are fine.
- :func:`refit_up`: refit the ancestors of one node through parent links, stopping
  as soon as a box no longer changes (used by the optimizers).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._hugepages import zeros_huge
from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.kernels.sah import node_half_area

#: Subtrees handed to threads by the parallel passes (independent of the thread count,
#: so results never depend on it).
FRONTIER_SIZE = 128


@cpu_kernel()
def top_frontier(root, left, right, target):
    """Cut a linked tree below its top levels into about ``target`` independent subtrees.

    The tree is expanded level by level from ``root`` until the current level holds at
    least ``target`` nodes or only leaves. Returns ``(frontier, top)``: the roots of
    the subtrees (the last level, left to right) and the expanded inner nodes above
    them, parents before children. A chain-like tree still works: its frontier is
    leaves and one deep subtree.
    """
    level = np.empty(1, dtype=np.int32)
    level[0] = root
    top = np.empty(4 * target + 4, dtype=np.int32)
    n_top = 0
    while level.shape[0] < target:
        n_inner = 0
        for x in level:
            if left[x] >= 0:
                n_inner += 1
        if n_inner == 0:
            break
        nxt = np.empty(level.shape[0] + n_inner, dtype=np.int32)
        m = 0
        for x in level:
            if left[x] >= 0:
                if n_top == top.shape[0]:
                    grown = np.empty(2 * top.shape[0], dtype=np.int32)
                    grown[:n_top] = top[:n_top]
                    top = grown
                top[n_top] = x
                n_top += 1
                nxt[m] = left[x]
                nxt[m + 1] = right[x]
                m += 2
            else:
                nxt[m] = x
                m += 1
        level = nxt
    return level, top[:n_top].copy()


def _push_py(stack, sp, value):
    """Push ``value`` on a growable int32 stack; return the (possibly new) stack.

    The entries are copied by an explicit loop. Inlined twice into a ``prange`` body
    (pushes at ``sp`` and ``sp + 1``: :func:`refit_collapse`, the emission of
    :mod:`rayaccel.bvh.layouts.linked_tree`), a slice copy ``grown[:sp] = stack[:sp]``
    was lowered wrongly by numba 0.68's parfor passes when the push at ``sp`` grew
    the stack: nothing was copied, or a size check failed (``SystemError ...
    refit_collapse returned a result with an exception set``), so subtrees deeper
    than the initial stack were lost from the refit (the insertion build of a
    20k-triangle fan crashed).
    """
    if sp == stack.shape[0]:
        grown = np.empty(2 * stack.shape[0], dtype=np.int32)
        for i in range(sp):
            grown[i] = stack[i]
        stack = grown
    stack[sp] = value
    return stack


push = cpu_inline(_push_py)


def _collapse_node_py(
    node, left, right, lo, hi, count, max_leaf, c_inner, c_prim, collapse,
    as_leaf, height, n_eff, n_prim, cost,
):  # fmt: skip
    """Finish one node whose children are done: refit, cost, collapse decision.

    Node ids are non-negative: they index as unsigned integers, which spares numba's
    negative-index wraparound code on every access.
    """
    u = np.uint64(node)
    a = left[u]
    if a < 0:
        # An original leaf.
        as_leaf[u] = 1
        n_eff[u] = 1
        n_prim[u] = count[u]
        cost[u] = c_prim * node_half_area(lo, hi, node) * count[u]
        return
    b = np.uint64(right[u])
    a = np.uint64(a)
    # Refit the box, then compare the split cost with a leaf's.
    for k in range(3):
        lo[u, k] = min(lo[a, k], lo[b, k])
        hi[u, k] = max(hi[a, k], hi[b, k])
    area = node_half_area(lo, hi, node)
    n_prim[u] = n_prim[a] + n_prim[b]
    split_cost = c_inner * area + cost[a] + cost[b]
    leaf_cost = c_prim * area * n_prim[u]
    if collapse and n_prim[u] <= max_leaf and leaf_cost <= split_cost:
        as_leaf[u] = 1
        n_eff[u] = 1
        height[u] = 0
        cost[u] = leaf_cost
    else:
        as_leaf[u] = 0
        n_eff[u] = n_eff[a] + n_eff[b]
        height[u] = 1 + max(height[a], height[b])
        cost[u] = split_cost


collapse_node = cpu_inline(_collapse_node_py)


@cpu_kernel(parallel=True)
def refit_collapse(root, left, right, lo, hi, count, max_leaf, c_inner, c_prim, collapse):
    """Refit a linked tree bottom-up; return collapse decisions, subtree sizes and costs.

    The subtrees below :func:`top_frontier` are processed in parallel, each with a
    post-order walk on an explicit stack (arbitrarily deep trees are fine), then the
    top nodes serially, children first. Every node gets the same arithmetic as in a
    serial walk, so the result is bit-identical for any thread count.

    Parameters
    ----------
    root : int32
    left, right : (n,) int32
        Children (``-1`` for leaves).
    lo, hi : (n, 3) float32
        Boxes; inner boxes are overwritten with the union of their children.
    count : (n,) int32
        References of each leaf.
    max_leaf : int32
    c_inner, c_prim : float64
        SAH constants.
    collapse : bool
        Whether subtrees may be collapsed into leaves.

    Returns
    -------
    as_leaf : (n,) uint8
        1 for nodes emitted as leaves (original leaves and collapsed subtrees).
    height : (n,) int32
        Height of each subtree after collapsing (0 for an emitted leaf).
    n_eff : (n,) int32
        Emitted leaves in each subtree.
    n_prim : (n,) int32
        References in each subtree.
    cost : (n,) float64
        SAH cost of each subtree after collapsing, in half areas (not divided by the
        root's area).
    """
    n = left.shape[0]
    as_leaf = zeros_huge(n, np.uint8)
    height = zeros_huge(n, np.int32)
    n_eff = zeros_huge(n, np.int32)
    n_prim = zeros_huge(n, np.int32)
    cost = zeros_huge(n, np.float64)
    expanded = zeros_huge(n, np.uint8)
    frontier, top = top_frontier(root, left, right, FRONTIER_SIZE)
    # Frontier subtrees in parallel: post-order walks (a node is finished on its second visit).
    for f in prange(frontier.shape[0]):
        stack = np.empty(2 * MAX_DEPTH + 64, dtype=np.int32)
        stack[0] = frontier[f]
        sp = 1
        while sp > 0:
            node = stack[sp - 1]
            u = np.uint64(node)
            a = left[u]
            if a >= 0 and not expanded[u]:
                expanded[u] = 1
                stack = push(stack, sp, right[u])
                stack = push(stack, sp + 1, a)
                sp += 2
                continue
            sp -= 1
            collapse_node(
                node, left, right, lo, hi, count, max_leaf, c_inner, c_prim, collapse,
                as_leaf, height, n_eff, n_prim, cost,
            )  # fmt: skip
    # The top levels, children before parents.
    for i in range(top.shape[0] - 1, -1, -1):
        collapse_node(
            top[i], left, right, lo, hi, count, max_leaf, c_inner, c_prim, collapse,
            as_leaf, height, n_eff, n_prim, cost,
        )  # fmt: skip
    return as_leaf, height, n_eff, n_prim, cost


def _refit_up_py(node, parent, left, right, lo, hi):
    """Refit the ancestors of ``node`` (exclusive) until a box stops changing."""
    p = parent[node]
    while p >= 0:
        a = left[p]
        b = right[p]
        changed = False
        for k in range(3):
            new_lo = min(lo[a, k], lo[b, k])
            new_hi = max(hi[a, k], hi[b, k])
            if new_lo != lo[p, k] or new_hi != hi[p, k]:
                changed = True
            lo[p, k] = new_lo
            hi[p, k] = new_hi
        if not changed:
            break
        p = parent[p]


refit_up = cpu_inline(_refit_up_py)
