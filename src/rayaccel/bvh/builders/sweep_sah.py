"""Full-sweep SAH BVH construction (Wald, Boulos, Shirley 2007, "Ray Tracing Deformable
Scenes using Dynamic Bounding Volume Hierarchies", §4).

At every node all ``N-1`` "first i | rest" splits of the primitives sorted by
centroid are evaluated on all three axes: a suffix pass records the area of the
right part, a prefix pass adds the left part and keeps the cheapest
``C_trav + C_prim·(A_L·N_L + A_R·N_R)/A`` (MacDonald & Booth 1990). This is the
reference-quality top-down greedy SAH build (binned SAH approximates it).

The three orders are sorted once; a split marks the primitives that go left and
stably partitions each order within the node's range, so every node costs O(N) and
the build O(N log N) (no per-node sorting). Degenerate nodes (a split no better than
a leaf but too many primitives for one, or a depth that must stay bounded) are cut
at the median of the longest axis's order, so the depth stays below ``MAX_DEPTH``.
Serial; use ``bvh2.binned_sah`` for speed.

Given ``refs`` (:class:`~rayaccel.bvh.builders.refs.BuildRefs`, e.g. from ``+presplit``),
it builds over those boxes instead of one per triangle; leaves name mesh triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.common import compact_to_canonical, depth_forces_median, primitive_bounds
from rayaccel.bvh.builders.refs import BuildRefs, check_refs
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2
from rayaccel.dtypes import IntArray
from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class SweepSahOptions:
    """Options of :func:`build_sweep_sah`.

    Attributes
    ----------
    max_leaf_size : int
        Nodes with more primitives are always split (1..64).
    traversal_cost : float
        SAH cost of one inner node, relative to one triangle test.
    intersection_cost : float
        SAH cost of one triangle test.
    """

    max_leaf_size: int = 8
    traversal_cost: float = 1.0
    intersection_cost: float = 1.0

    def __post_init__(self) -> None:
        if not 1 <= self.max_leaf_size <= 64:
            raise InvalidInputError(f"max_leaf_size: expected 1..64, got {self.max_leaf_size}")
        if not (self.traversal_cost >= 0 and self.intersection_cost > 0):
            raise InvalidInputError("traversal_cost must be >= 0 and intersection_cost > 0")


@cpu_kernel()
def _sweep_build(
    order, prim_lo, prim_hi, max_leaf, trav_cost, isect_cost, t_lo, t_hi, t_first, t_count
):
    """Build over ``order (3, n)`` (ids sorted by centroid per axis); return the node count."""
    n = order.shape[1]
    right_area = np.empty(n + 1, dtype=np.float64)
    goes_left = np.zeros(prim_lo.shape[0], dtype=np.uint8)
    scratch = np.empty(n, dtype=np.int32)
    stack = np.empty((2 * MAX_DEPTH + 4, 3), dtype=np.int32)  # node, begin, end
    depth_of = np.empty(2 * MAX_DEPTH + 4, dtype=np.int32)
    # Root box.
    for k in range(3):
        t_lo[0, k] = np.inf
        t_hi[0, k] = -np.inf
    for p in range(prim_lo.shape[0]):
        for k in range(3):
            t_lo[0, k] = min(t_lo[0, k], prim_lo[p, k])
            t_hi[0, k] = max(t_hi[0, k], prim_hi[p, k])
    stack[0, 0] = 0
    stack[0, 1] = 0
    stack[0, 2] = n
    depth_of[0] = 0
    sp = 1
    next_node = 1
    while sp > 0:
        sp -= 1
        node = stack[sp, 0]
        begin = stack[sp, 1]
        end = stack[sp, 2]
        depth = depth_of[sp]
        count = end - begin
        ex = np.float64(t_hi[node, 0]) - t_lo[node, 0]
        ey = np.float64(t_hi[node, 1]) - t_lo[node, 1]
        ez = np.float64(t_hi[node, 2]) - t_lo[node, 2]
        node_area = ex * ey + ey * ez + ez * ex
        inv_area = 1.0 / node_area if node_area > 0 else 0.0
        best_cost = np.inf
        best_axis = -1
        best_i = -1
        if count > 1 and not depth_forces_median(depth, count, max_leaf):
            for a in range(3):
                # Suffix pass: area of primitives i..end-1 in this axis's order.
                lo0 = np.inf
                lo1 = np.inf
                lo2 = np.inf
                hi0 = -np.inf
                hi1 = -np.inf
                hi2 = -np.inf
                for i in range(end - 1, begin, -1):
                    p = order[a, i]
                    lo0 = min(lo0, prim_lo[p, 0])
                    lo1 = min(lo1, prim_lo[p, 1])
                    lo2 = min(lo2, prim_lo[p, 2])
                    hi0 = max(hi0, prim_hi[p, 0])
                    hi1 = max(hi1, prim_hi[p, 1])
                    hi2 = max(hi2, prim_hi[p, 2])
                    e0 = np.float64(hi0) - lo0
                    e1 = np.float64(hi1) - lo1
                    e2 = np.float64(hi2) - lo2
                    right_area[i - begin] = e0 * e1 + e1 * e2 + e2 * e0
                # Prefix pass: evaluate "begin..i-1 | i..end-1".
                lo0 = np.inf
                lo1 = np.inf
                lo2 = np.inf
                hi0 = -np.inf
                hi1 = -np.inf
                hi2 = -np.inf
                for i in range(begin + 1, end):
                    p = order[a, i - 1]
                    lo0 = min(lo0, prim_lo[p, 0])
                    lo1 = min(lo1, prim_lo[p, 1])
                    lo2 = min(lo2, prim_lo[p, 2])
                    hi0 = max(hi0, prim_hi[p, 0])
                    hi1 = max(hi1, prim_hi[p, 1])
                    hi2 = max(hi2, prim_hi[p, 2])
                    e0 = np.float64(hi0) - lo0
                    e1 = np.float64(hi1) - lo1
                    e2 = np.float64(hi2) - lo2
                    n_left = i - begin
                    cost = trav_cost + isect_cost * inv_area * (
                        (e0 * e1 + e1 * e2 + e2 * e0) * n_left + right_area[i - begin] * (end - i)
                    )
                    if cost < best_cost:
                        best_cost = cost
                        best_axis = a
                        best_i = i
        leaf_cost = isect_cost * count
        if count <= max_leaf and (best_axis < 0 or best_cost >= leaf_cost):
            t_first[node] = begin
            t_count[node] = count
            continue
        if best_axis < 0 or best_cost >= leaf_cost:
            # Degenerate or depth-bounded node: median of the longest axis's order.
            best_axis = 0
            if ey > ex and ey >= ez:
                best_axis = 1
            elif ez > ex and ez > ey:
                best_axis = 2
            best_i = begin + count // 2
        # Mark the left side, then stably partition every axis's order.
        for i in range(begin, end):
            goes_left[order[best_axis, i]] = 1 if i < best_i else 0
        for a in range(3):
            if a == best_axis:
                continue
            n_l = 0
            n_r = 0
            for i in range(begin, end):
                p = order[a, i]
                if goes_left[p]:
                    order[a, begin + n_l] = p
                    n_l += 1
                else:
                    scratch[n_r] = p
                    n_r += 1
            for j in range(n_r):
                order[a, begin + n_l + j] = scratch[j]
        left = next_node
        next_node += 2
        t_first[node] = left
        t_count[node] = 0
        # Child boxes from the split axis's order.
        for c in range(2):
            c_begin = begin if c == 0 else best_i
            c_end = best_i if c == 0 else end
            for k in range(3):
                t_lo[left + c, k] = np.inf
                t_hi[left + c, k] = -np.inf
            for i in range(c_begin, c_end):
                p = order[best_axis, i]
                for k in range(3):
                    t_lo[left + c, k] = min(t_lo[left + c, k], prim_lo[p, k])
                    t_hi[left + c, k] = max(t_hi[left + c, k], prim_hi[p, k])
        # Larger child pushed first.
        first_c = 0 if (best_i - begin) >= (end - best_i) else 1
        for c in (first_c, 1 - first_c):
            stack[sp, 0] = left + c
            stack[sp, 1] = begin if c == 0 else best_i
            stack[sp, 2] = best_i if c == 0 else end
            depth_of[sp] = depth + 1
            sp += 1
    return next_node


@register(
    "builder",
    "bvh2.sweep_sah",
    options=SweepSahOptions,
    summary="top-down full-sweep SAH over presorted centroid orders (reference quality)",
    reference="Wald, Boulos, Shirley 2007, Ray Tracing Deformable Scenes using Dynamic BVHs",
)
def build_sweep_sah(
    mesh: TriangleMesh, options: SweepSahOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Build a binary BVH evaluating every split of the sorted centroids.

    Parameters
    ----------
    mesh : TriangleMesh
    options : SweepSahOptions, optional
    refs : BuildRefs, optional
        References to build over (e.g. pre-split triangle parts); default one per triangle.

    Returns
    -------
    Bvh2
    """
    opt = options or SweepSahOptions()
    ref_prim: IntArray | None = None
    if refs is None:
        prim_lo, prim_hi, centroid = primitive_bounds(mesh.triangles())
    else:
        refs = check_refs(refs, mesh, "bvh2.sweep_sah")
        prim_lo, prim_hi, ref_prim = refs
        centroid = np.float32(0.5) * prim_lo + np.float32(0.5) * prim_hi
    n = prim_lo.shape[0]
    order = np.empty((3, n), dtype=np.int32)
    for a in range(3):
        # Ties broken by primitive id, so the build is deterministic.
        order[a] = np.lexsort((np.arange(n), centroid[:, a])).astype(np.int32)
    capacity = max(2 * n - 1, 1)
    t_lo = np.empty((capacity, 3), dtype=np.float32)
    t_hi = np.empty((capacity, 3), dtype=np.float32)
    t_first = np.zeros(capacity, dtype=np.int32)
    t_count = np.zeros(capacity, dtype=np.int32)
    n_used = _sweep_build(
        order,
        prim_lo,
        prim_hi,
        int(opt.max_leaf_size),
        float(opt.traversal_cost),
        float(opt.intersection_cost),
        t_lo,
        t_hi,
        t_first,
        t_count,
    )
    prim_index = order[0] if ref_prim is None else ref_prim[order[0]]
    return compact_to_canonical(
        t_lo, t_hi, t_first, t_count, prim_index.copy(), mesh.n_triangles, int(n_used)
    )
