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
lowest bit (``P = (P − 1) & rest``), 2^(|S|−1) − 1 of them. The optimum is rebuilt
top-down reusing the treelet's n − 1 inner slots (R keeps its id and box).

Nodes are processed bottom-up, so every treelet is optimized after its subtrees:
level by level from the lowest (a node's level is its height), in parallel over the
nodes of a level, which root disjoint subtrees, so the result does not depend on the
thread count. Nodes with fewer than γ references are skipped; the pass is repeated
for a few rounds with γ doubled each round (3 rounds, γ = 7: the authors' recollection
of the paper's schedule, unconfirmed). A final pass collapses subtrees into leaves of
up to ``max_leaf_size`` references where the SAH prefers a leaf
(:func:`rayaccel.bvh.linked.linked_to_canonical`).

Multi-reference input leaves. The paper starts from one-primitive leaves. Here every
input leaf of at most ``max_leaf_size`` references is first split into one-reference
leaves (a balanced subtree; each reference's box is its triangle's box clipped to the
leaf's box, which stays valid for spatial-split input), so the DP may regroup
primitives; the DP's leaf term is allowed for ``N(S) <= max_leaf_size`` and matches
the final collapse, so an input leaf can always be re-formed and the SAH (same
constants) never rises. Larger input leaves stay whole. Constants C_i = 1.2,
C_t = 1.0. Cost per treelet O(3^n); reported: over 20 scenes, more than 90% of the
ray-tracing performance of SBVH from an LBVH input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh._build_common import primitive_bounds
from rayaccel.bvh.build_lbvh import check_leaf_costs
from rayaccel.bvh.layout import Bvh2
from rayaccel.bvh.linked import LinkedTree, linked_to_canonical
from rayaccel.bvh.refit import half_area
from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh

#: Largest treelet: the DP tables hold 2^n entries and the partitions cost O(3^n).
MAX_TREELET = 8
#: Treelet roots per parallel work item.
_CHUNK = 64


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
        doubled every round (the authors' recollection: γ = 7, unconfirmed).
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
        Inner boxes are filled in later by :func:`_subtree_costs`.
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
def _subtree_costs(root, left, right, lo, hi, count, max_leaf, c_inner, c_prim):
    """Refit inner boxes; return every node's SAH cost (with collapsing) and references.

    The cost of an inner node is ``min(C_i·A + cost(l) + cost(r), C_t·A·N)``, the
    leaf term only when ``N <= max_leaf`` (the final collapse's rule); a leaf costs
    ``C_t·A·N``. Areas are half areas (the SAH is a ratio). Post-order with an
    explicit stack, so any node numbering and depth is fine.

    Returns
    -------
    cost : (n,) float64
    n_prim : (n,) int32
    """
    n = left.shape[0]
    cost = np.zeros(n, dtype=np.float64)
    n_prim = np.zeros(n, dtype=np.int32)
    stack = np.empty(n + 2, dtype=np.int32)
    expanded = np.zeros(n, dtype=np.uint8)
    stack[0] = root
    sp = 1
    while sp > 0:
        node = stack[sp - 1]
        a = left[node]
        if a >= 0 and not expanded[node]:
            # First visit of an inner node: children first.
            expanded[node] = 1
            stack[sp] = right[node]
            stack[sp + 1] = a
            sp += 2
            continue
        sp -= 1
        if a < 0:
            n_prim[node] = count[node]
            cost[node] = c_prim * half_area(lo, hi, node) * count[node]
            continue
        b = right[node]
        for k in range(3):
            lo[node, k] = min(lo[a, k], lo[b, k])
            hi[node, k] = max(hi[a, k], hi[b, k])
        area = half_area(lo, hi, node)
        n_prim[node] = n_prim[a] + n_prim[b]
        c = c_inner * area + cost[a] + cost[b]
        if n_prim[node] <= max_leaf:
            c = min(c, c_prim * area * n_prim[node])
        cost[node] = c
    return cost, n_prim


@cpu_kernel()
def _levels(root, left, right, n_prim, gamma):
    """Group the treelet roots of one round by height (lowest first).

    A root is an inner node with at least ``gamma`` references and a grandchild
    (height >= 2; below that a treelet has two leaves and nothing to change).

    Returns
    -------
    level_start : (n_levels + 1,) int32
    level_nodes : (n_roots,) int32
        Roots of level ``h`` are ``level_nodes[level_start[h]:level_start[h + 1]]``,
        in post-order.
    """
    n = left.shape[0]
    height = np.zeros(n, dtype=np.int32)
    order = np.empty(n, dtype=np.int32)
    stack = np.empty(n + 2, dtype=np.int32)
    expanded = np.zeros(n, dtype=np.uint8)
    stack[0] = root
    sp = 1
    m = 0
    # Post-order: heights, and the eligible roots in visiting order.
    while sp > 0:
        node = stack[sp - 1]
        a = left[node]
        if a >= 0 and not expanded[node]:
            expanded[node] = 1
            stack[sp] = right[node]
            stack[sp + 1] = a
            sp += 2
            continue
        sp -= 1
        if a < 0:
            continue
        height[node] = 1 + max(height[a], height[right[node]])
        if height[node] >= 2 and n_prim[node] >= gamma:
            order[m] = node
            m += 1
    # Stable counting sort of the roots by height.
    top = height[root] + 1
    level_start = np.zeros(max(top, 2) + 1, dtype=np.int32)
    for t in range(m):
        level_start[height[order[t]] + 1] += 1
    for h in range(level_start.shape[0] - 1):
        level_start[h + 1] += level_start[h]
    fill = level_start.copy()
    level_nodes = np.empty(m, dtype=np.int32)
    for t in range(m):
        h = height[order[t]]
        level_nodes[fill[h]] = order[t]
        fill[h] += 1
    return level_start, level_nodes


def _restructure_py(
    root, left, right, lo, hi, cost, n_prim, size, max_leaf, c_inner, c_prim,
    leaves, inner, box_lo, box_hi, s_cost, s_prim, s_part, s_set, s_node,
):  # fmt: skip
    """Replace the treelet of ``root`` by its SAH-optimal restructuring (module docstring).

    Scratch: ``leaves (8,)``, ``inner (8,)``, ``box_lo``/``box_hi (256, 3)`` float32,
    ``s_cost (256,)`` float64, ``s_prim``/``s_part (256,)`` and ``s_set``/``s_node (8,)``
    int32. The new costs, reference counts and boxes of the treelet's inner nodes are
    written back, so ancestors see a consistent tree.
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
                a = half_area(lo, hi, x)
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
        area = half_area(box_lo, box_hi, s)
        # Each unordered partition once: P ranges over non-empty subsets of `rest`.
        best_split = np.inf
        best_part = rest
        p = rest
        while p > 0:
            c = s_cost[p] + s_cost[s ^ p]
            if c < best_split:
                best_split = c
                best_part = p
            p = (p - 1) & rest
        c = c_inner * area + best_split
        # The leaf term, under the same rule as the final collapse.
        if s_prim[s] <= max_leaf:
            c = min(c, c_prim * area * s_prim[s])
        s_cost[s] = c
        s_part[s] = best_part
    # Rebuild top-down from the full set, reusing the treelet's inner slots.
    s_set[0] = full
    s_node[0] = root
    sp = 1
    next_slot = 0
    while sp > 0:
        sp -= 1
        s = s_set[sp]
        node = s_node[sp]
        p = s_part[s]
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


@cpu_kernel(parallel=True)
def _treelet_round(
    left, right, lo, hi, cost, n_prim, level_start, level_nodes, size, max_leaf, c_inner, c_prim
):
    """Restructure the treelets of every root, level by level (see :func:`_levels`).

    Roots of one level root disjoint subtrees whose descendants are all done, so they
    run in parallel (chunks of ``_CHUNK`` roots, each with its own scratch) and the
    result does not depend on the thread count.
    """
    n_levels = level_start.shape[0] - 1
    for h in range(n_levels):
        begin = level_start[h]
        m = level_start[h + 1] - begin
        n_chunks = (m + _CHUNK - 1) // _CHUNK
        for ch in prange(n_chunks):
            leaves = np.empty(MAX_TREELET, dtype=np.int32)
            inner = np.empty(MAX_TREELET, dtype=np.int32)
            box_lo = np.empty((1 << MAX_TREELET, 3), dtype=np.float32)
            box_hi = np.empty((1 << MAX_TREELET, 3), dtype=np.float32)
            s_cost = np.empty(1 << MAX_TREELET, dtype=np.float64)
            s_prim = np.empty(1 << MAX_TREELET, dtype=np.int32)
            s_part = np.empty(1 << MAX_TREELET, dtype=np.int32)
            s_set = np.empty(MAX_TREELET, dtype=np.int32)
            s_node = np.empty(MAX_TREELET, dtype=np.int32)
            end = min(m, (ch + 1) * _CHUNK)
            for t in range(ch * _CHUNK, end):
                _restructure(
                    level_nodes[begin + t], left, right, lo, hi, cost, n_prim, size, max_leaf,
                    c_inner, c_prim, leaves, inner, box_lo, box_hi, s_cost, s_prim, s_part,
                    s_set, s_node,
                )  # fmt: skip


def split_leaves_linked(
    bvh: Bvh2, mesh: TriangleMesh, max_leaf_size: int, split: bool
) -> LinkedTree:
    """Return the linked form of ``bvh`` with leaves of 2..``max_leaf_size`` references split.

    Node ids of ``bvh`` keep their meaning (a split leaf becomes the root of its
    subtree); with ``split=False`` this is :func:`rayaccel.bvh.linked.to_linked`.
    """
    count = bvh.node_count
    if split:
        marked = (count > 1) & (count <= max_leaf_size)
        extra = np.where(marked, 2 * count - 2, 0)
        tri_lo, tri_hi, _ = primitive_bounds(mesh.triangles())
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


@register(
    "step",
    "bvh2+treelet",
    options=TreeletOptions,
    summary="restructure 7-leaf treelets bottom-up into their SAH-optimal form (DP)",
    reference="Karras & Aila 2013, Fast Parallel Construction of High-Quality BVHs",
)
def treelet(bvh: Bvh2, mesh: TriangleMesh, options: TreeletOptions | None = None) -> Bvh2:
    """Return ``bvh`` after treelet restructuring and SAH leaf collapsing (module docstring).

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
    """
    opt = options or TreeletOptions()
    max_leaf = np.int32(opt.max_leaf_size)
    c_inner = np.float64(opt.traversal_cost)
    c_prim = np.float64(opt.intersection_cost)
    tree = split_leaves_linked(bvh, mesh, opt.max_leaf_size, opt.split_leaves)
    root = np.int32(0)
    cost, n_prim = _subtree_costs(
        root, tree.left, tree.right, tree.lo, tree.hi, tree.count, max_leaf, c_inner, c_prim
    )
    for r in range(opt.rounds):
        gamma = np.int32(min(opt.min_subtree << r, np.iinfo(np.int32).max))
        level_start, level_nodes = _levels(root, tree.left, tree.right, n_prim, gamma)
        if level_nodes.shape[0] == 0:
            break
        _treelet_round(
            tree.left, tree.right, tree.lo, tree.hi, cost, n_prim, level_start, level_nodes,
            np.int32(opt.treelet_size), max_leaf, c_inner, c_prim,
        )  # fmt: skip
    return linked_to_canonical(
        tree,
        0,
        bvh.n_prims,
        collapse=True,
        max_leaf_size=opt.max_leaf_size,
        inner_cost=opt.traversal_cost,
        prim_cost=opt.intersection_cost,
    )
