"""Treelet restructuring (Karras & Aila 2013), as a build step (``+treelet``).

Karras & Aila 2013, "Fast Parallel Construction of High-Quality Bounding Volume
Hierarchies" (HPG 2013, §4). A *treelet* of a node R is R plus a few of its
descendants: start with R's two children as treelet leaves and repeatedly replace
the leaf of largest surface area by its two children, until ``n`` leaves (7 in the
paper; any subtree may be a treelet leaf). Every binary tree over those leaves is a
valid replacement for the treelet, and the SAH-optimal one is found exactly by
dynamic programming over the ``2^n`` subsets S of leaves (bitmasks), in increasing
numeric order so that every proper subset comes first:

    C(S) = min( C_i·A(S) + min over partitions {P, S∖P} of C(P) + C(S∖P),
                C_t·A(S)·N(S) )                  (the second term: S as one leaf)

where A is the surface area of the union box (precomputed for all subsets), N the
number of references and a singleton costs its subtree's current SAH cost. Each
unordered partition is enumerated once, as the non-empty subsets P of S without its
lowest bit (``P = (P - 1) & rest``), 2^(|S|−1) − 1 of them. The optimum is rebuilt
top-down reusing the treelet's n − 1 inner slots (R keeps its id and box).

Nodes are processed bottom-up, so every treelet is optimized after its subtrees: in
post-order, where maximal subtrees of about 1/1024 of the references run in parallel
(they are disjoint) and the few nodes above them follow serially; a treelet touches
only its root's subtree, so every such order, hence every thread count, gives the
same tree. (The paper's GPU version climbs from the leaves with an atomic counter
per node; one parallel region per round avoids a barrier per tree level.) Nodes
with fewer than γ references are not treelet roots; the pass is repeated for a few
rounds with γ doubled each round (3 rounds from γ = 7: our recollection of the
paper's schedule, not confirmed against its text). A final pass collapses subtrees into leaves of
up to ``max_leaf_size`` references where the SAH prefers a leaf
(:func:`rayaccel.bvh.layouts.linked_tree.linked_to_canonical`).

Multi-reference input leaves. The paper starts from one-primitive leaves. Here every
input leaf of at most ``max_leaf_size`` references is first split into one-reference
leaves (a balanced subtree; each reference's box is its triangle's box clipped to the
leaf's box, which stays valid for spatial-split input), so the DP may regroup
primitives; the DP's leaf term is allowed for ``N(S) <= max_leaf_size`` and matches
the final collapse, so an input leaf can always be re-formed and the SAH (same
constants) never rises, unless the conversion's depth guard has to rebalance a
subtree deeper than ``MAX_DEPTH``. Larger input leaves stay whole. Constants C_i = 1.2,
C_t = 1.0. Cost per treelet O(3^n); reported: over 20 scenes, more than 90% of the
ray-tracing performance of SBVH from an LBVH input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.common import triangle_bounds
from rayaccel.bvh.builders.lbvh import check_leaf_costs
from rayaccel.bvh.builders.refit import refit_collapse
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import LinkedTree, collapsed_to_canonical
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.sah import node_half_area
from rayaccel.scene.mesh import TriangleMesh

#: Largest treelet: the DP tables hold 2^n entries and the partitions cost O(3^n).
MAX_TREELET = 8
#: Smallest subtree (references) handed to a thread as one task.
_MIN_GRAIN = 256


@dataclass(frozen=True, slots=True)
class TreeletOptions:
    """Options of the ``+treelet`` step.

    Attributes
    ----------
    treelet_size : int
        Leaves per treelet, n (3..8; the paper uses 7). The DP tables hold 2^n
        entries and the partition loop costs about 3^n / 2 steps per treelet.
    rounds : int
        Bottom-up passes over the tree (0..32; 0 only splits and re-collapses leaves).
    min_subtree : int
        γ: nodes with fewer references are not treelet roots in the first round;
        doubled every round (γ = 7 and the doubling are our recollection of the
        paper, unconfirmed).
    traversal_cost, intersection_cost : float
        SAH constants C_i and C_t of the DP and of the final collapse (1.2 and 1).
    max_leaf_size : int
        Largest leaf the DP and the final collapse may form (1..64).
    split_leaves : bool
        Split input leaves of at most ``max_leaf_size`` references into one-reference
        leaves first, so the DP can regroup primitives (see the module docstring).
    """

    treelet_size: int = 7
    rounds: int = 3
    min_subtree: int = 7
    traversal_cost: float = 1.2
    intersection_cost: float = 1.0
    max_leaf_size: int = 8
    split_leaves: bool = True

    def __post_init__(self) -> None:
        if not 3 <= self.treelet_size <= MAX_TREELET:
            raise InvalidInputError(
                f"treelet_size: expected 3..{MAX_TREELET}, got {self.treelet_size}"
            )
        if not 0 <= self.rounds <= 32:
            raise InvalidInputError(f"rounds: expected 0..32, got {self.rounds}")
        if not self.min_subtree >= 1:
            raise InvalidInputError(f"min_subtree: expected >= 1, got {self.min_subtree}")
        check_leaf_costs(self.max_leaf_size, self.traversal_cost, self.intersection_cost)


@cpu_kernel(parallel=True)
def _split_leaves(node_lo, node_hi, node_first, node_count, tri_lo, tri_hi, prim_index, offset):
    """Return the linked form of a canonical tree with marked leaves split (see module doc).

    Parameters
    ----------
    node_lo, node_hi, node_first, node_count : canonical Bvh2 arrays
    tri_lo, tri_hi : (F, 3) float32
        Triangle boxes (unused where nothing is split).
    prim_index : (n_refs,) int32
    offset : (n_nodes + 1,) int32
        Exclusive prefix sum of the new nodes each leaf adds (``2·count − 2`` for a
        split leaf, else 0). Node ids ``0..n_nodes-1`` keep their meaning; a split
        leaf becomes the root of a complete binary tree (heap numbering, heap node
        ``j >= 1`` at ``n_nodes + offset[i] + j − 1``) whose heap leaves take the
        leaf's references in order.

    Returns
    -------
    left, right, first, count : (n_out,) int32
    lo, hi : (n_out, 3) float32
        Inner boxes are filled in later by :func:`~rayaccel.bvh.builders.refit.refit_collapse`.
    """
    n = node_count.shape[0]
    n_out = n + offset[n]
    left = np.full(n_out, -1, dtype=np.int32)
    right = np.full(n_out, -1, dtype=np.int32)
    first = np.zeros(n_out, dtype=np.int32)
    count = np.zeros(n_out, dtype=np.int32)
    lo = np.empty((n_out, 3), dtype=np.float32)
    hi = np.empty((n_out, 3), dtype=np.float32)
    for i in prange(n):
        c = node_count[i]
        for k in range(3):
            lo[i, k] = node_lo[i, k]
            hi[i, k] = node_hi[i, k]
        if c == 0:
            # Inner node: siblings are adjacent in the canonical layout.
            left[i] = node_first[i]
            right[i] = node_first[i] + 1
            continue
        if offset[i + 1] == offset[i]:
            # A leaf kept whole.
            first[i] = node_first[i]
            count[i] = c
            continue
        # Heap node j: id i for j = 0, else base + j - 1; heap leaves are j >= c - 1.
        base = np.int64(n + offset[i] - 1)
        for j in range(2 * c - 1):
            node = np.int64(i) if j == 0 else base + j
            if j < c - 1:
                left[node] = base + 2 * j + 1
                right[node] = base + 2 * j + 2
                continue
            ref = node_first[i] + j - (c - 1)
            first[node] = ref
            count[node] = 1
            # The reference's box: its triangle's box clipped to the leaf's box.
            p = prim_index[ref]
            for k in range(3):
                a = max(tri_lo[p, k], node_lo[i, k])
                b = min(tri_hi[p, k], node_hi[i, k])
                if a > b:
                    a = node_lo[i, k]
                    b = node_hi[i, k]
                lo[node, k] = a
                hi[node, k] = b
    return left, right, first, count, lo, hi


@cpu_kernel()
def _schedule(root, left, right, n_prim, gamma, grain):
    """List one round's treelet roots in a valid bottom-up order, grouped into tasks.

    A root is an inner node with at least ``gamma`` references and a grandchild
    (below that a treelet has two leaves and nothing to change). The walk is a
    post-order, so every root follows its descendants. Maximal subtrees of at most
    ``grain`` references are *tasks*: their roots are independent of other tasks'.
    The remaining roots (the *top*, ancestors of tasks) come last.

    Returns
    -------
    task_start : (n_tasks + 2,) int32
        Task ``t`` owns ``order[task_start[t]:task_start[t + 1]]``; the last range is
        the top.
    order : (n_roots,) int32
        Roots, post-order within each range.
    """
    n = left.shape[0]
    task = np.full(n, -1, dtype=np.int32)
    post = np.empty(n, dtype=np.int32)
    stack = np.empty(n + 2, dtype=np.int32)
    expanded = np.zeros(n, dtype=np.uint8)
    has_grandchild = np.zeros(n, dtype=np.uint8)
    n_tasks = 0
    if n_prim[root] <= grain:
        task[root] = 0
        n_tasks = 1
    stack[0] = root
    sp = 1
    m = 0
    while sp > 0:
        node = stack[sp - 1]
        a = left[node]
        if a >= 0 and not expanded[node]:
            # First visit: children inherit the task, or start one when small enough.
            expanded[node] = 1
            b = right[node]
            for c in (b, a):
                if task[node] >= 0:
                    task[c] = task[node]
                elif n_prim[c] <= grain:
                    task[c] = n_tasks
                    n_tasks += 1
            stack[sp] = b
            stack[sp + 1] = a
            sp += 2
            continue
        sp -= 1
        if a < 0:
            continue
        if left[a] >= 0 or left[right[node]] >= 0:
            has_grandchild[node] = 1
        if has_grandchild[node] and n_prim[node] >= gamma:
            post[m] = node
            m += 1
    # Stable counting sort by task; the top (task -1) goes last.
    task_start = np.zeros(n_tasks + 2, dtype=np.int32)
    for t in range(m):
        g = task[post[t]]
        task_start[(g if g >= 0 else n_tasks) + 1] += 1
    for g in range(n_tasks + 1):
        task_start[g + 1] += task_start[g]
    fill = task_start.copy()
    order = np.empty(m, dtype=np.int32)
    for t in range(m):
        g = task[post[t]]
        g = g if g >= 0 else n_tasks
        order[fill[g]] = post[t]
        fill[g] += 1
    return task_start, order


def _restructure_py(
    root, left, right, lo, hi, cost, n_prim, size, max_leaf, c_inner, c_prim,
    leaves, inner, box_lo, box_hi, s_cost, s_prim, s_split, s_set, s_node,
):  # fmt: skip
    """Replace the treelet of ``root`` by its SAH-optimal restructuring (module docstring).

    Scratch: ``leaves (8,)``, ``inner (8,)``, ``box_lo``/``box_hi (256, 3)`` float32,
    ``s_cost``/``s_split (256,)`` float64 (cost; best split without the node's own
    term), ``s_prim (256,)`` and ``s_set``/``s_node (8,)`` int32. The new costs,
    reference counts and boxes of the treelet's inner nodes are written back, so
    ancestors see a consistent tree.
    """
    # Form the treelet: expand the treelet leaf of largest area until `size` leaves.
    leaves[0] = left[root]
    leaves[1] = right[root]
    k = 2
    n_inner = 0
    while k < size:
        best = -1
        best_area = -1.0
        for j in range(k):
            x = leaves[j]
            if left[x] >= 0:
                a = node_half_area(lo, hi, x)
                if a > best_area:
                    best_area = a
                    best = j
        if best < 0:
            break
        x = leaves[best]
        inner[n_inner] = x
        n_inner += 1
        # Its children take its place, in order, so leaf order stays left to right.
        for j in range(k, best + 1, -1):
            leaves[j] = leaves[j - 1]
        leaves[best] = left[x]
        leaves[best + 1] = right[x]
        k += 1
    if k < 3:
        return
    # Singletons: the current subtrees.
    for j in range(k):
        s = 1 << j
        x = leaves[j]
        for a in range(3):
            box_lo[s, a] = lo[x, a]
            box_hi[s, a] = hi[x, a]
        s_cost[s] = cost[x]
        s_prim[s] = n_prim[x]
    # Larger subsets in increasing order: every proper subset comes first.
    full = (1 << k) - 1
    for s in range(3, full + 1):
        low = s & -s
        rest = s ^ low
        if rest == 0:
            continue
        for a in range(3):
            box_lo[s, a] = min(box_lo[rest, a], box_lo[low, a])
            box_hi[s, a] = max(box_hi[rest, a], box_hi[low, a])
        s_prim[s] = s_prim[rest] + s_prim[low]
        area = node_half_area(box_lo, box_hi, s)
        # Each unordered partition once: P ranges over non-empty subsets of `rest`. Only
        # the minimum is kept (a branch-free loop); the rebuild finds the argmin again.
        best_split = np.inf
        p = rest
        while p > 0:
            best_split = min(best_split, s_cost[p] + s_cost[s ^ p])
            p = (p - 1) & rest
        c = c_inner * area + best_split
        # The leaf term, under the same rule as the final collapse.
        if s_prim[s] <= max_leaf:
            c = min(c, c_prim * area * s_prim[s])
        s_cost[s] = c
        s_split[s] = best_split
    # Rebuild top-down from the full set, reusing the treelet's inner slots.
    s_set[0] = full
    s_node[0] = root
    sp = 1
    next_slot = 0
    while sp > 0:
        sp -= 1
        s = s_set[sp]
        node = s_node[sp]
        # The first partition in enumeration order that reaches the minimum.
        rest = s ^ (s & -s)
        p = rest
        while p > 0 and s_cost[p] + s_cost[s ^ p] != s_split[s]:
            p = (p - 1) & rest
        if p == 0:
            p = rest
        for side in range(2):
            # The part holding the lowest leaf goes left.
            part = s ^ p if side == 0 else p
            if part & (part - 1) == 0:
                j = 0
                while (part >> j) != 1:
                    j += 1
                child = leaves[j]
            else:
                child = inner[next_slot]
                next_slot += 1
                s_set[sp] = part
                s_node[sp] = child
                sp += 1
            if side == 0:
                left[node] = child
            else:
                right[node] = child
        for a in range(3):
            lo[node, a] = box_lo[s, a]
            hi[node, a] = box_hi[s, a]
        cost[node] = s_cost[s]
        n_prim[node] = s_prim[s]


_restructure = cpu_inline(_restructure_py)


@cpu_inline
def _restructure_range(
    order, begin, end, left, right, lo, hi, cost, n_prim, size, max_leaf, c_inner, c_prim
):
    """Restructure the treelets of ``order[begin:end]`` in order, with fresh scratch."""
    leaves = np.empty(MAX_TREELET, dtype=np.int32)
    inner = np.empty(MAX_TREELET, dtype=np.int32)
    box_lo = np.empty((1 << MAX_TREELET, 3), dtype=np.float32)
    box_hi = np.empty((1 << MAX_TREELET, 3), dtype=np.float32)
    s_cost = np.empty(1 << MAX_TREELET, dtype=np.float64)
    s_split = np.empty(1 << MAX_TREELET, dtype=np.float64)
    s_prim = np.empty(1 << MAX_TREELET, dtype=np.int32)
    s_set = np.empty(MAX_TREELET, dtype=np.int32)
    s_node = np.empty(MAX_TREELET, dtype=np.int32)
    for t in range(begin, end):
        _restructure(
            order[t], left, right, lo, hi, cost, n_prim, size, max_leaf, c_inner, c_prim,
            leaves, inner, box_lo, box_hi, s_cost, s_prim, s_split, s_set, s_node,
        )  # fmt: skip


@cpu_kernel(parallel=True)
def _treelet_round(
    left, right, lo, hi, cost, n_prim, task_start, order, size, max_leaf, c_inner, c_prim
):
    """Restructure the treelets of every root listed by :func:`_schedule`.

    Tasks own disjoint subtrees, so they run in parallel, each bottom-up in its own
    order; the top roots follow serially. Any such order gives the same tree (a
    treelet reads and writes only its root's subtree), so the result does not depend
    on the thread count.
    """
    n_tasks = task_start.shape[0] - 2
    for g in prange(n_tasks):
        _restructure_range(
            order, task_start[g], task_start[g + 1], left, right, lo, hi, cost, n_prim, size,
            max_leaf, c_inner, c_prim,
        )  # fmt: skip
    _restructure_range(
        order, task_start[n_tasks], task_start[n_tasks + 1], left, right, lo, hi, cost, n_prim,
        size, max_leaf, c_inner, c_prim,
    )  # fmt: skip


def split_leaves_linked(
    bvh: Bvh2, mesh: TriangleMesh, max_leaf_size: int, split: bool
) -> LinkedTree:
    """Return the linked form of ``bvh`` with leaves of 2..``max_leaf_size`` references split.

    Node ids of ``bvh`` keep their meaning (a split leaf becomes the root of its
    subtree); with ``split=False`` this is :func:`rayaccel.bvh.layouts.linked_tree.to_linked`.
    """
    count = bvh.node_count
    if split:
        marked = (count > 1) & (count <= max_leaf_size)
        extra = np.where(marked, 2 * count - 2, 0)
        tri_lo, tri_hi = triangle_bounds(mesh.vertices, mesh.faces)
    else:
        extra = np.zeros_like(count)
        tri_lo = tri_hi = np.zeros((0, 3), dtype=np.float32)
    offset = np.zeros(bvh.n_nodes + 1, dtype=np.int32)
    np.cumsum(extra, out=offset[1:])
    left, right, first, cnt, lo, hi = _split_leaves(
        bvh.node_lo, bvh.node_hi, bvh.node_first, bvh.node_count, tri_lo, tri_hi,
        bvh.prim_index, offset,
    )  # fmt: skip
    return LinkedTree(left, right, lo, hi, first, cnt, bvh.prim_index)


@register("step", "bvh2+treelet")
def treelet(bvh: Bvh2, mesh: TriangleMesh, options: TreeletOptions | None = None) -> Bvh2:
    """Restructure 7-leaf treelets bottom-up into their SAH-optimal form (DP).

    Return ``bvh`` after treelet restructuring and SAH leaf collapsing (module docstring).

    Parameters
    ----------
    bvh : Bvh2
    mesh : TriangleMesh
        The mesh ``bvh`` was built over (triangle boxes of split leaves).
    options : TreeletOptions, optional

    Returns
    -------
    Bvh2
        Same references; SAH cost (same constants) no higher than ``bvh``'s.

    References
    ----------
    Karras & Aila 2013, Fast Parallel Construction of High-Quality BVHs.
    """
    opt = options or TreeletOptions()
    max_leaf = np.int32(opt.max_leaf_size)
    c_inner = np.float64(opt.traversal_cost)
    c_prim = np.float64(opt.intersection_cost)
    tree = split_leaves_linked(bvh, mesh, opt.max_leaf_size, opt.split_leaves)
    root = np.int32(0)
    # Parallel tasks: subtrees of about 1/1024 of the references (at least _MIN_GRAIN).
    grain = np.int32(max(_MIN_GRAIN, bvh.n_refs // 1024))
    # Inner boxes, subtree costs (with the collapse rule) and reference counts.
    _, _, _, n_prim, cost = refit_collapse(
        root, tree.left, tree.right, tree.lo, tree.hi, tree.count, max_leaf, c_inner, c_prim,
        True,
    )  # fmt: skip
    for r in range(opt.rounds):
        gamma = np.int32(min(opt.min_subtree << r, np.iinfo(np.int32).max))
        task_start, order = _schedule(root, tree.left, tree.right, n_prim, gamma, grain)
        if order.shape[0] == 0:
            break
        _treelet_round(
            tree.left, tree.right, tree.lo, tree.hi, cost, n_prim, task_start, order,
            np.int32(opt.treelet_size), max_leaf, c_inner, c_prim,
        )  # fmt: skip
    return collapsed_to_canonical(tree, 0, bvh.n_prims, opt)
