"""Static quality metrics of a binary BVH: SAH, EPO and LCV (Aila, Karras, Laine 2013).

Aila, Karras, Laine 2013, "On Quality Metrics of Bounding Volume Hierarchies" (HPG).

- **SAH** (:meth:`Bvh2.sah_cost`): ``(C_inner·Σ_inner A(n) + C_prim·Σ_leaf A(l)·N(l)) / A(root)``,
  the expected cost of a random ray that hits the root box.
- **EPO** (:func:`epo`), end-point overlap: the expected extra cost of rays whose end
  point (the hit) lies on geometry *outside* a node's subtree but inside its box,
  ``Σ_n C(n)·A((S ∖ Q(n)) ∩ box(n)) / A(S)``, with ``S`` the scene surface, ``Q(n)`` the
  surface in n's subtree and ``C(n)`` = ``C_inner`` or ``C_prim·N(n)``. Computed per
  triangle in parallel: walk the nodes whose box overlaps it and, where the triangle
  is not in the node's subtree, add the area of the triangle clipped to the box
  (Sutherland–Hodgman against six planes, float64:
  :func:`~rayaccel.kernels.clip.clip_triangle_box`). A triangle of a spatial-split
  BVH counts as in ``Q(n)`` when any of its references is in n's subtree.
  Spatial-split structures therefore have a lower EPO by construction.
- **LCV** (:func:`lcv`), leaf count variability: the standard deviation over rays of
  the number of leaves a ray intersects. We count the leaves whose box the segment
  ``[tmin, t_hit]`` crosses (the leaves any closest-hit traversal must consider),
  which does not depend on the traversal order.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2
from rayaccel.dtypes import REAL
from rayaccel.kernels.clip import clip_triangle_box, polygon_area


@cpu_kernel()
def _subtree_ref_ranges(node_first, node_count):
    """Return ``(begin, end)`` of every subtree's slots in ``prim_index``."""
    n = node_count.shape[0]
    begin = np.empty(n, dtype=np.int32)
    end = np.empty(n, dtype=np.int32)
    for i in range(n - 1, -1, -1):
        if node_count[i] > 0:
            begin[i] = node_first[i]
            end[i] = node_first[i] + node_count[i]
        else:
            c = node_first[i]
            begin[i] = min(begin[c], begin[c + 1])
            end[i] = max(end[c], end[c + 1])
    return begin, end


@cpu_inline
def _clipped_area(tri, prim, lo, hi, node, poly_a, poly_b):
    """Area of triangle ``prim`` inside box ``node`` (float64; 0 when less than a polygon)."""
    m = clip_triangle_box(tri, prim, lo[node], hi[node], poly_a, poly_b, 3)
    if m < 3:
        return 0.0
    return polygon_area(poly_a, m)


@cpu_kernel(parallel=True)
def _epo_kernel(bvh, tri, slot_begin, slots, sub_begin, sub_end, c_inner, c_prim):
    """Return the per-triangle EPO contributions (unnormalised) and triangle areas."""
    n_tri = tri.shape[0]
    contrib = np.zeros(n_tri, dtype=np.float64)
    areas = np.zeros(n_tri, dtype=np.float64)
    for t in prange(n_tri):
        # Convex clipping adds one vertex per plane; rounding may add more: room for 32.
        poly_a = np.empty((32, 3), dtype=np.float64)
        poly_b = np.empty((32, 3), dtype=np.float64)
        stack = np.empty(MAX_DEPTH + 2, dtype=np.int32)
        t_lo = np.empty(3, dtype=np.float32)
        t_hi = np.empty(3, dtype=np.float32)
        for k in range(3):
            t_lo[k] = min(tri[t, 0, k], min(tri[t, 1, k], tri[t, 2, k]))
            t_hi[k] = max(tri[t, 0, k], max(tri[t, 1, k], tri[t, 2, k]))
        full = _clipped_area(tri, t, bvh.node_lo, bvh.node_hi, 0, poly_a, poly_b)
        areas[t] = full
        if full <= 0:
            continue
        total = 0.0
        stack[0] = 0
        sp = 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            overlap = True
            for k in range(3):
                if t_hi[k] < bvh.node_lo[node, k] or t_lo[k] > bvh.node_hi[node, k]:
                    overlap = False
            if not overlap:
                continue
            # Is the triangle referenced in this subtree?
            inside = False
            for s in range(slot_begin[t], slot_begin[t + 1]):
                if sub_begin[node] <= slots[s] < sub_end[node]:
                    inside = True
                    break
            count = bvh.node_count[node]
            if not inside:
                cost = c_inner if count == 0 else c_prim * count
                contained = True
                for k in range(3):
                    if t_lo[k] < bvh.node_lo[node, k] or t_hi[k] > bvh.node_hi[node, k]:
                        contained = False
                if contained:
                    total += cost * full
                else:
                    total += cost * _clipped_area(
                        tri, t, bvh.node_lo, bvh.node_hi, node, poly_a, poly_b
                    )
            if count == 0:
                stack[sp] = bvh.node_first[node]
                stack[sp + 1] = bvh.node_first[node] + 1
                sp += 2
        contrib[t] = total
    return contrib, areas


def epo(bvh: Bvh2, triangles: np.ndarray, inner_cost: float = 1.2, prim_cost: float = 1.0) -> float:
    """Return the end-point overlap of ``bvh`` (Aila et al. 2013; see the module docstring).

    Parameters
    ----------
    bvh : Bvh2
    triangles : (F, 3, 3) float32
        The mesh triangles the tree was built over.
    inner_cost, prim_cost : float
        ``C_inner`` and ``C_prim``.

    Notes
    -----
    Cost O(F · nodes overlapping each triangle), parallel over triangles; a minute or
    less for the 1.4M-triangle kitchen on two cores.
    """
    tri = np.ascontiguousarray(triangles, dtype=REAL)
    sub_begin, sub_end = _subtree_ref_ranges(bvh.node_first, bvh.node_count)
    # Slots of each triangle's references, grouped by triangle (CSR).
    order = np.argsort(bvh.prim_index, kind="stable").astype(np.int32)
    counts = np.bincount(bvh.prim_index, minlength=tri.shape[0])
    slot_begin = np.concatenate(([0], np.cumsum(counts))).astype(np.int32)
    contrib, areas = _epo_kernel(
        bvh.arrays(), tri, slot_begin, order, sub_begin, sub_end, float(inner_cost),
        float(prim_cost),
    )  # fmt: skip
    surface = float(np.sum(areas))
    return float(np.sum(contrib) / surface) if surface > 0 else 0.0


@cpu_kernel(parallel=True)
def _leaf_counts_kernel(bvh, origin, direction, tmin, tmax):
    """Count, per ray, the leaves whose box the segment ``[tmin, tmax]`` crosses."""
    n = origin.shape[0]
    out = np.zeros(n, dtype=np.int32)
    for r in prange(n):
        stack = np.empty(MAX_DEPTH + 2, dtype=np.int32)
        inv = np.empty(3, dtype=np.float64)
        for k in range(3):
            inv[k] = 1.0 / np.float64(direction[r, k])
        stack[0] = 0
        sp = 1
        leaves = 0
        while sp > 0:
            sp -= 1
            node = stack[sp]
            t0 = np.float64(tmin[r])
            t1 = np.float64(tmax[r])
            for k in range(3):
                a = (np.float64(bvh.node_lo[node, k]) - origin[r, k]) * inv[k]
                b = (np.float64(bvh.node_hi[node, k]) - origin[r, k]) * inv[k]
                if a > b:
                    a, b = b, a
                # 0 * inf = NaN for an axis-parallel ray on a slab plane: no constraint.
                if a == a:
                    t0 = max(t0, a)
                if b == b:
                    t1 = min(t1, b)
            if t0 > t1:
                continue
            if bvh.node_count[node] > 0:
                leaves += 1
            else:
                stack[sp] = bvh.node_first[node]
                stack[sp + 1] = bvh.node_first[node] + 1
                sp += 2
        out[r] = leaves
    return out


def leaf_counts(
    bvh: Bvh2, origin: np.ndarray, direction: np.ndarray, tmin: np.ndarray, t_hit: np.ndarray
) -> np.ndarray:
    """Return the ``(n,)`` int32 number of leaves each ray segment ``[tmin, t_hit]`` crosses.

    ``t_hit`` is the closest hit distance (``tmax`` or inf for a miss).
    """
    counts: np.ndarray = _leaf_counts_kernel(
        bvh.arrays(),
        np.ascontiguousarray(origin, dtype=REAL),
        np.ascontiguousarray(direction, dtype=REAL),
        np.ascontiguousarray(tmin, dtype=REAL),
        np.ascontiguousarray(t_hit, dtype=REAL),
    )
    return counts


def lcv(counts: np.ndarray) -> float:
    """Return the leaf count variability ``sqrt(E[N²] − E[N]²)`` of per-ray leaf counts."""
    values = np.asarray(counts, dtype=np.float64)
    return float(values.std()) if values.size else 0.0
