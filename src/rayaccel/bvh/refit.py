"""Bottom-up refitting of BVH boxes, and the SAH subtree costs computed on the way up.

A refit recomputes every inner box as the union of its children's boxes, leaves
first. Bottom-up builders (LBVH, Karras 2012 §4; PLOC) emit topology first and boxes
afterwards, and every tree optimizer refits the path above a changed node.

- :func:`refit_collapse`: one post-order pass over a linked tree (any node order)
  that refits, computes the SAH cost of every subtree and decides SAH leaf
  collapsing (Meister & Bittner 2018 §4.4). Cost O(n), serial; the traversal order
  is a depth-first walk with an explicit stack, so arbitrarily deep trees are fine.
- :func:`refit_up`: refit the ancestors of one node through parent links, stopping
  as soon as a box no longer changes (used by the optimizers).
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import cpu_inline, cpu_kernel


def _half_area_py(lo, hi, i):
    """Half surface area of box ``i`` of ``lo``/``hi`` in float64."""
    ex = np.float64(hi[i, 0]) - lo[i, 0]
    ey = np.float64(hi[i, 1]) - lo[i, 1]
    ez = np.float64(hi[i, 2]) - lo[i, 2]
    return ex * ey + ey * ez + ez * ex


half_area = cpu_inline(_half_area_py)


@cpu_kernel()
def refit_collapse(root, left, right, lo, hi, count, max_leaf, c_inner, c_prim, collapse):
    """Refit a linked tree bottom-up; return collapse decisions, subtree sizes and costs.

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
    as_leaf = np.zeros(n, dtype=np.uint8)
    height = np.zeros(n, dtype=np.int32)
    n_eff = np.zeros(n, dtype=np.int32)
    n_prim = np.zeros(n, dtype=np.int32)
    cost = np.zeros(n, dtype=np.float64)
    stack = np.empty(n + 2, dtype=np.int32)
    expanded = np.zeros(n, dtype=np.uint8)
    stack[0] = root
    sp = 1
    while sp > 0:
        node = stack[sp - 1]
        a = left[node]
        if a >= 0 and not expanded[node]:
            # First visit of an inner node: visit the children before it.
            expanded[node] = 1
            stack[sp] = right[node]
            stack[sp + 1] = a
            sp += 2
            continue
        sp -= 1
        if a < 0:
            # An original leaf.
            as_leaf[node] = 1
            n_eff[node] = 1
            n_prim[node] = count[node]
            cost[node] = c_prim * half_area(lo, hi, node) * count[node]
            continue
        b = right[node]
        # Refit the box, then compare the split cost with a leaf's.
        for k in range(3):
            lo[node, k] = min(lo[a, k], lo[b, k])
            hi[node, k] = max(hi[a, k], hi[b, k])
        area = half_area(lo, hi, node)
        n_prim[node] = n_prim[a] + n_prim[b]
        split_cost = c_inner * area + cost[a] + cost[b]
        leaf_cost = c_prim * area * n_prim[node]
        if collapse and n_prim[node] <= max_leaf and leaf_cost <= split_cost:
            as_leaf[node] = 1
            n_eff[node] = 1
            cost[node] = leaf_cost
        else:
            n_eff[node] = n_eff[a] + n_eff[b]
            height[node] = 1 + max(height[a], height[b])
            cost[node] = split_cost
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
