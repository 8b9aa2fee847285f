"""Insertion-based BVH optimization (Bittner, Hapala, Havran 2013), as a step (``+reinsert``).

Bittner, Hapala, Havran 2013, "Fast Insertion-Based Optimization of Bounding Volume
Hierarchies" (CGF 32(1)). Leaves are fixed, so the SAH cost changes only through the
areas of inner nodes. Each iteration:

1. ranks inner nodes (not the root) by inefficiency, the product of
   ``A(N)/mean(A(L), A(R))``, ``A(N)/min(A(L), A(R))`` and ``A(N)``, and takes the
   worst ``batch_fraction`` of them;
2. for each, removes the node N and its parent P: N's sibling takes P's place and the
   ancestors are refitted; N's children become two orphan subtrees;
3. reinserts each orphan (larger first) where the cost increase is smallest, found by
   branch and bound from the root with a priority queue on the *induced* cost
   ``C_I(child) = C_I(X) + A(X ∪ L) − A(X)``; inserting as sibling of X costs
   ``C_I(X) + A(X ∪ L)``, and X's subtree is pruned when ``C_I(X) + A(L) >= best``.
   The freed N and P become the orphans' new parents; ancestors are refitted.

Iterations stop after ``patience`` iterations without a relative gain of ``tolerance``
or after ``max_iterations``; the best tree seen is returned (an iteration may raise
the cost, since orphans need not find their old places). Serial and deterministic.
Reported: up to
27% lower SAH than a SAH build, up to 88% lower than a spatial-median build; it
helps LBVH most (Devillers thesis, §5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.refit import refit_up
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import linked_to_canonical, to_linked
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.sah import node_half_area, union_half_area
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class ReinsertOptions:
    """Options of the ``+reinsert`` step.

    Attributes
    ----------
    batch_fraction : float
        Share of inner nodes removed and reinserted per iteration (Bittner et al.
        use about 1%).
    max_iterations : int
        Upper bound on iterations.
    tolerance : float
        An iteration counts as progress when it lowers the best SAH cost by this fraction.
    patience : int
        Stop after this many iterations without progress.
    """

    batch_fraction: float = 0.01
    max_iterations: int = 100
    tolerance: float = 1e-3
    patience: int = 3

    def __post_init__(self) -> None:
        if not 0 < self.batch_fraction <= 1:
            raise InvalidInputError(f"batch_fraction: expected (0, 1], got {self.batch_fraction}")
        if self.max_iterations < 0:
            raise InvalidInputError(f"max_iterations: expected >= 0, got {self.max_iterations}")
        if self.patience < 1:
            raise InvalidInputError(f"patience: expected >= 1, got {self.patience}")
        if not self.tolerance >= 0:
            raise InvalidInputError(f"tolerance: expected >= 0, got {self.tolerance}")


@cpu_kernel(parallel=True)
def _inefficiency(left, right, parent, lo, hi):
    """Return Bittner's node score (−1 for leaves and the root)."""
    n = left.shape[0]
    score = np.empty(n, dtype=np.float64)
    for i in prange(n):
        if left[i] < 0 or parent[i] < 0:
            score[i] = -1.0
            continue
        area = node_half_area(lo, hi, i)
        a_l = node_half_area(lo, hi, left[i])
        a_r = node_half_area(lo, hi, right[i])
        m_sum = area / max(0.5 * (a_l + a_r), 1e-300)
        m_min = area / max(min(a_l, a_r), 1e-300)
        score[i] = m_sum * m_min * area
    return score


@cpu_inline
def _heap_push(h_cost, h_node, size, cost, node):
    i = size
    h_cost[i] = cost
    h_node[i] = node
    while i > 0:
        p = (i - 1) // 2
        if h_cost[p] < h_cost[i] or (h_cost[p] == h_cost[i] and h_node[p] <= h_node[i]):
            break
        h_cost[p], h_cost[i] = h_cost[i], h_cost[p]
        h_node[p], h_node[i] = h_node[i], h_node[p]
        i = p
    return size + 1


@cpu_inline
def _heap_pop(h_cost, h_node, size):
    size -= 1
    h_cost[0] = h_cost[size]
    h_node[0] = h_node[size]
    i = 0
    while True:
        a = 2 * i + 1
        if a >= size:
            break
        b = a + 1
        c = a
        if b < size and (
            h_cost[b] < h_cost[a] or (h_cost[b] == h_cost[a] and h_node[b] < h_node[a])
        ):
            c = b
        if h_cost[i] < h_cost[c] or (h_cost[i] == h_cost[c] and h_node[i] <= h_node[c]):
            break
        h_cost[c], h_cost[i] = h_cost[i], h_cost[c]
        h_node[c], h_node[i] = h_node[i], h_node[c]
        i = c
    return size


@cpu_inline
def find_best_sibling(root, orphan, left, right, lo, hi, h_cost, h_node, max_visits):
    """Branch and bound for the node X minimising ``C_I(X) + A(X ∪ orphan)``.

    At most ``max_visits`` nodes are evaluated (the best one so far is returned when
    the budget runs out); the heap ``h_cost``/``h_node`` needs one slot per node.
    """
    orphan_area = node_half_area(lo, hi, orphan)
    best = np.inf
    best_node = root
    size = _heap_push(h_cost, h_node, 0, 0.0, root)
    visits = 0
    while size > 0 and visits < max_visits:
        induced = h_cost[0]
        x = h_node[0]
        size = _heap_pop(h_cost, h_node, size)
        if induced + orphan_area >= best:
            break
        visits += 1
        merged = union_half_area(lo, hi, x, orphan)
        cost = induced + merged
        if cost < best:
            best = cost
            best_node = x
        # Children inherit the growth of X; prune when they cannot beat the best.
        if left[x] >= 0:
            child_induced = induced + merged - node_half_area(lo, hi, x)
            if child_induced + orphan_area < best and size + 2 <= h_cost.shape[0]:
                size = _heap_push(h_cost, h_node, size, child_induced, left[x])
                size = _heap_push(h_cost, h_node, size, child_induced, right[x])
    return best_node


@cpu_inline
def _replace_child(parent, left, right, p, old, new):
    """Make ``new`` the child of ``p`` in place of ``old`` (``p`` may be −1: root)."""
    if p >= 0:
        if left[p] == old:
            left[p] = new
        else:
            right[p] = new
    parent[new] = p


@cpu_inline
def attach_sibling(root, fresh, x, orphan, parent, left, right, lo, hi):
    """Splice the free node ``fresh`` above ``x`` as the parent of ``x`` and ``orphan``.

    ``fresh`` takes ``x``'s place under ``x``'s parent, gets ``x`` (left) and
    ``orphan`` (right) as children and their union as its box; the ancestors are
    refitted. Returns the (possibly new) root.
    """
    gx = parent[x]
    _replace_child(parent, left, right, gx, x, fresh)
    if gx < 0:
        root = fresh
    left[fresh] = x
    right[fresh] = orphan
    parent[x] = fresh
    parent[orphan] = fresh
    for a in range(3):
        lo[fresh, a] = min(lo[x, a], lo[orphan, a])
        hi[fresh, a] = max(hi[x, a], hi[orphan, a])
    refit_up(fresh, parent, left, right, lo, hi)
    return root


@cpu_kernel()
def _reinsert_batch(root, batch, left, right, parent, lo, hi):
    """Remove and reinsert every node of ``batch`` in order; return the new root."""
    n = left.shape[0]
    h_cost = np.empty(2 * n + 2, dtype=np.float64)
    h_node = np.empty(2 * n + 2, dtype=np.int32)
    for t in range(batch.shape[0]):
        node = batch[t]
        p = parent[node]
        if p < 0 or left[node] < 0:
            continue
        # Detach N and P: N's sibling takes P's place, then refit above it.
        sibling = right[p] if left[p] == node else left[p]
        g = parent[p]
        _replace_child(parent, left, right, g, p, sibling)
        if g < 0:
            root = sibling
        else:
            refit_up(sibling, parent, left, right, lo, hi)
        orphan_a = left[node]
        orphan_b = right[node]
        if node_half_area(lo, hi, orphan_b) > node_half_area(lo, hi, orphan_a):
            orphan_a, orphan_b = orphan_b, orphan_a
        # Reinsert both orphans, larger first, reusing N and P as their new parents.
        for k in range(2):
            orphan = orphan_a if k == 0 else orphan_b
            fresh = node if k == 0 else p
            x = find_best_sibling(root, orphan, left, right, lo, hi, h_cost, h_node, n)
            root = attach_sibling(root, fresh, x, orphan, parent, left, right, lo, hi)
    return root


@cpu_kernel()
def _inner_area(left, lo, hi):
    total = 0.0
    for i in range(left.shape[0]):
        if left[i] >= 0:
            total += node_half_area(lo, hi, i)
    return total


@register("step", "bvh2+reinsert")
def reinsert(bvh: Bvh2, mesh: TriangleMesh, options: ReinsertOptions | None = None) -> Bvh2:
    """Remove inefficient nodes and reinsert their subtrees where the SAH grows least.

    Return ``bvh`` optimized by insertion-based reinsertion (see the module docstring).

    References
    ----------
    Bittner, Hapala, Havran 2013, Fast Insertion-Based Optimization of BVHs.
    """
    opt = options or ReinsertOptions()
    if bvh.n_nodes < 5:
        return bvh
    tree, parent = to_linked(bvh)
    n_inner = bvh.n_nodes - bvh.n_leaves
    batch_size = max(1, round(opt.batch_fraction * n_inner))
    root = np.int32(0)
    before = _inner_area(tree.left, tree.lo, tree.hi)
    # An iteration may raise the cost (orphans need not find their old places): keep the best.
    best = (root, tree.left.copy(), tree.right.copy(), parent.copy(), tree.lo.copy(),
            tree.hi.copy())  # fmt: skip
    best_cost = before
    stale = 0
    for _ in range(opt.max_iterations):
        score = _inefficiency(tree.left, tree.right, parent, tree.lo, tree.hi)
        k = min(batch_size, int(np.count_nonzero(score > 0)))
        if k == 0:
            break
        top = np.argpartition(-score, k - 1)[:k]
        # Worst first; ties by node id so the order is deterministic.
        batch = top[np.lexsort((top, -score[top]))].astype(np.int32)
        root = np.int32(
            _reinsert_batch(root, batch, tree.left, tree.right, parent, tree.lo, tree.hi)
        )
        after = _inner_area(tree.left, tree.lo, tree.hi)
        if after < best_cost:
            best = (root, tree.left.copy(), tree.right.copy(), parent.copy(), tree.lo.copy(),
                    tree.hi.copy())  # fmt: skip
        # Stop after `patience` iterations without a relative gain of `tolerance`.
        if after < (1.0 - opt.tolerance) * best_cost:
            stale = 0
        else:
            stale += 1
            if stale >= opt.patience:
                break
        best_cost = min(best_cost, after)
    root, left, right, _, lo, hi = best
    tree = tree._replace(left=left, right=right, lo=lo, hi=hi)
    return linked_to_canonical(tree, int(root), bvh.n_prims, collapse=False)
