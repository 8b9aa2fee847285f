"""Spatial-split BVH (SBVH), Stich, Friedrich, Dietrich 2009.

Stich, Friedrich, Dietrich 2009, "Spatial Splits in Bounding Volume Hierarchies"
(HPG). A top-down SAH build over *references* (a primitive id and a box that may be
a clipped part of the triangle), which may split a reference in two where that
lowers the SAH, so that large or long triangles no longer inflate whole subtrees:

1. object split: binned SAH over reference centroids (as ``bvh2.binned_sah``),
   giving cost ``C_o`` and child boxes B1, B2;
2. only if ``A(B1 ∩ B2) / A(root) > alpha`` are spatial splits considered (alpha
   decides *consideration*, the SAH decides the split; default 1e-5);
3. spatial split: ``n_spatial_bins`` equal bins per axis over the node box (fewer
   in small nodes, as for object bins); each
   reference is chopped at the bin planes it crosses, each piece growing its bin's
   box ("chopped binning"); it counts once in its entry bin and once in its exit bin;
   a sweep evaluates every plane;
4. partition with reference unsplitting: a straddling reference goes wholly to one
   side when that is cheaper than duplicating it (Stich et al. §4.3);
5. a split reference's pieces are the boxes of the triangle clipped exactly against
   the plane (vertices on each side plus edge–plane intersections, rounded outward
   to float32), intersected with the reference's current box.

Duplication is bounded: references live in one array of ``(1 + duplication_budget)·n``
slots (``n`` initial references: one per triangle, or the parts a pre-split step
made), each node owning a contiguous capacity that is shared between its children
in proportion to their counts; a spatial split that does not fit is not taken.
Spatial splits are also skipped below depth ``spatial_depth_limit`` (NVIDIA's code
uses 48) and when the depth bound forces median splits. Leaves reference whole
triangles (each fragment is tested whole), so a triangle may sit in several leaves.

Parallelism: large nodes are split serially; subtrees below ``parallel_threshold``
references are built concurrently (``prange``), each into node and reference blocks
reserved up front, so the result does not depend on the thread count. Reported:
lowest SAH and fastest traversal of the BVH builders, builds about 4–8× slower than
binned SAH (Devillers thesis, Table 5.4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.builders.binned_sah import (
    MAX_BINS,
    _bin_scales,
    _partition,
    _ref_range_bounds,
    binned_split,
    node_bin_count,
    ref_rows,
)
from rayaccel.bvh.builders.common import depth_forces_median, triangle_ref_rows
from rayaccel.bvh.builders.refs import BuildRefs, check_refs
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import LinkedTree, linked_to_canonical
from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class SbvhOptions:
    """Options of :func:`build_sbvh`.

    Attributes
    ----------
    alpha : float
        Spatial splits are considered when the object split's child boxes overlap by
        more than this fraction of the root's area (Stich et al.: 1e-5).
    duplication_budget : float
        Extra references allowed, as a fraction of the triangle count (0..4):
        ``n_refs <= (1 + duplication_budget) · n``.
    n_bins : int
        Object-split bins per axis of large nodes (2..256; small nodes use fewer, as in
        ``bvh2.binned_sah``).
    n_spatial_bins : int
        Spatial-split bins per axis of large nodes (2..256; NVIDIA's code uses 128);
        small nodes use ``min(n_spatial_bins, 4 + n // 20)`` like the object bins (on
        the kitchen: build 3.1–3.8 s → 2.8–2.9 s, SAH 37.94 → 37.99).
    spatial_depth_limit : int
        No spatial splits at or below this depth.
    max_leaf_size : int
        Nodes with more references are always split (1..64).
    traversal_cost, intersection_cost : float
        SAH constants.
    parallel_threshold : int
        Subtrees with fewer references are built one per thread; the build raises it to
        ``n // (4 · threads)`` for ``n`` references when that is larger, since the nodes
        above it are split serially (about six subtrees per thread keep the threads
        balanced). Any value gives the same tree.
    """

    alpha: float = 1e-5
    duplication_budget: float = 1.0
    n_bins: int = 32
    n_spatial_bins: int = 32
    spatial_depth_limit: int = 48
    max_leaf_size: int = 8
    traversal_cost: float = 1.0
    intersection_cost: float = 1.0
    parallel_threshold: int = 32768

    def __post_init__(self) -> None:
        if not 0 <= self.alpha <= 1:
            raise InvalidInputError(f"alpha: expected 0..1, got {self.alpha}")
        if not 0 <= self.duplication_budget <= 4:
            raise InvalidInputError(
                f"duplication_budget: expected 0..4, got {self.duplication_budget}"
            )
        for name in ("n_bins", "n_spatial_bins"):
            value = getattr(self, name)
            if not 2 <= value <= MAX_BINS:
                raise InvalidInputError(f"{name}: expected 2..{MAX_BINS}, got {value}")
        if not 0 <= self.spatial_depth_limit <= 64:
            raise InvalidInputError(
                f"spatial_depth_limit: expected 0..64, got {self.spatial_depth_limit}"
            )
        if not 1 <= self.max_leaf_size <= 64:
            raise InvalidInputError(f"max_leaf_size: expected 1..64, got {self.max_leaf_size}")
        if not (self.traversal_cost >= 0 and self.intersection_cost > 0):
            raise InvalidInputError("traversal_cost must be >= 0 and intersection_cost > 0")
        if self.parallel_threshold < 2:
            raise InvalidInputError("parallel_threshold: expected >= 2")


@cpu_inline
def _grow_point(box, x, y, z):
    """Grow ``box[0:6]`` by a float64 point, rounding outward to float32."""
    for a in range(3):
        v = x if a == 0 else (y if a == 1 else z)
        pad = abs(v) * 2.4e-7
        box[a] = min(box[a], np.float32(v - pad))
        box[3 + a] = max(box[3 + a], np.float32(v + pad))


@cpu_inline
def _split_reference(tri, prim, ref_box, axis, pos, left_box, right_box):
    """Clip triangle ``prim`` at ``x[axis] = pos``; write both sides' boxes ∩ ``ref_box``."""
    for k in range(3):
        left_box[k] = np.inf
        left_box[3 + k] = -np.inf
        right_box[k] = np.inf
        right_box[3 + k] = -np.inf
    for e in range(3):
        f = (e + 1) % 3
        p0 = np.float64(tri[prim, e, axis])
        p1 = np.float64(tri[prim, f, axis])
        # The vertex itself goes to its side(s).
        if p0 <= pos:
            for k in range(3):
                left_box[k] = min(left_box[k], tri[prim, e, k])
                left_box[3 + k] = max(left_box[3 + k], tri[prim, e, k])
        if p0 >= pos:
            for k in range(3):
                right_box[k] = min(right_box[k], tri[prim, e, k])
                right_box[3 + k] = max(right_box[3 + k], tri[prim, e, k])
        # An edge crossing the plane adds its intersection point to both sides.
        if (p0 < pos < p1) or (p1 < pos < p0):
            t = (pos - p0) / (p1 - p0)
            x = tri[prim, e, 0] + t * (np.float64(tri[prim, f, 0]) - tri[prim, e, 0])
            y = tri[prim, e, 1] + t * (np.float64(tri[prim, f, 1]) - tri[prim, e, 1])
            z = tri[prim, e, 2] + t * (np.float64(tri[prim, f, 2]) - tri[prim, e, 2])
            _grow_point(left_box, x, y, z)
            _grow_point(right_box, x, y, z)
    # The plane bounds each side exactly; both stay inside the current reference box.
    left_box[3 + axis] = min(left_box[3 + axis], np.float32(pos))
    right_box[axis] = max(right_box[axis], np.float32(pos))
    for k in range(3):
        left_box[k] = max(left_box[k], ref_box[k])
        left_box[3 + k] = min(left_box[3 + k], ref_box[3 + k])
        right_box[k] = max(right_box[k], ref_box[k])
        right_box[3 + k] = min(right_box[3 + k], ref_box[3 + k])
        if left_box[k] > left_box[3 + k]:
            left_box[3 + k] = left_box[k]
        if right_box[k] > right_box[3 + k]:
            right_box[3 + k] = right_box[k]


@cpu_inline
def _half_area6(box):
    ex = np.float64(box[3]) - box[0]
    ey = np.float64(box[4]) - box[1]
    ez = np.float64(box[5]) - box[2]
    return ex * ey + ey * ez + ez * ex


@cpu_inline
def _spatial_bin(value, node_lo, inv_width, n_bins):
    b = int((np.float64(value) - node_lo) * inv_width)
    return min(max(b, 0), n_bins - 1)


@cpu_kernel()
def _build_sbvh_task(
    refs,
    tri,
    begin,
    end,
    cap_end,
    depth0,
    root,
    node_base,
    stop_size,
    root_area,
    alpha,
    n_bins,
    n_sbins,
    spatial_depth,
    max_leaf,
    trav_cost,
    isect_cost,
    left_of,
    right_of,
    t_first,
    t_count,
    tasks,
):
    """Build the subtree over ``refs[begin:end]`` (capacity up to ``cap_end``) serially.

    Nodes with fewer than ``stop_size`` references are not built but appended to
    ``tasks`` rows ``(node, begin, end, cap_end, depth)``. Returns ``(next node, n_tasks)``.
    """
    ids = refs.view(np.int32)
    size = 2 * 64 + 8
    s_node = np.empty(size, dtype=np.int32)
    s_begin = np.empty(size, dtype=np.int32)
    s_end = np.empty(size, dtype=np.int32)
    s_cap = np.empty(size, dtype=np.int32)
    s_depth = np.empty(size, dtype=np.int32)
    counts = np.zeros((3, n_bins), dtype=np.int32)
    bin_box = np.empty((3, n_bins, 8), dtype=np.float32)
    suffix = np.empty((max(n_bins, n_sbins), 7), dtype=np.float32)
    child_box = np.empty(12, dtype=np.float32)
    box = np.empty(12, dtype=np.float32)
    scale = np.empty(3, dtype=np.float32)
    left_cb = np.empty(6, dtype=np.float32)
    right_cb = np.empty(6, dtype=np.float32)
    s_enter = np.zeros((3, n_sbins), dtype=np.int32)
    s_exit = np.zeros((3, n_sbins), dtype=np.int32)
    s_box = np.empty((3, n_sbins, 6), dtype=np.float32)
    cur = np.empty(6, dtype=np.float32)
    piece_l = np.empty(6, dtype=np.float32)
    piece_r = np.empty(6, dtype=np.float32)
    box_l = np.empty(6, dtype=np.float32)
    box_r = np.empty(6, dtype=np.float32)
    scratch = np.empty((max(cap_end - begin, 1), 8), dtype=np.float32)
    scratch_ids = scratch.view(np.int32)
    n_tasks = 0
    next_node = node_base
    s_node[0] = root
    s_begin[0] = begin
    s_end[0] = end
    s_cap[0] = cap_end
    s_depth[0] = depth0
    sp = 1
    while sp > 0:
        sp -= 1
        node = s_node[sp]
        lo_i = s_begin[sp]
        hi_i = s_end[sp]
        cap = s_cap[sp]
        depth = s_depth[sp]
        count = hi_i - lo_i
        if count < stop_size:
            tasks[n_tasks, 0] = node
            tasks[n_tasks, 1] = lo_i
            tasks[n_tasks, 2] = hi_i
            tasks[n_tasks, 3] = cap
            tasks[n_tasks, 4] = depth
            n_tasks += 1
            continue
        if count <= 1:
            t_first[node] = lo_i
            t_count[node] = count
            continue
        _ref_range_bounds(refs, lo_i, hi_i, box)
        node_area = _half_area6(box)
        forced = depth_forces_median(depth, count, max_leaf)
        # 1. Object split on centroid bins.
        axis = -1
        split_bin = -1
        cost = np.inf
        node_bins = node_bin_count(n_bins, count)
        if not forced and _bin_scales(box, node_bins, scale):
            for a in range(3):
                box[a] = box[6 + a]
            cost, axis, split_bin = binned_split(
                refs, lo_i, hi_i, box, scale, node_bins, node_area, trav_cost, isect_cost,
                counts, bin_box, suffix, child_box,
            )  # fmt: skip
            _ref_range_bounds(refs, lo_i, hi_i, box)
        # 2. Spatial split, only where the object split's children overlap enough.
        s_axis = -1
        s_cost = np.inf
        s_split = -1
        n_l_est = 0
        n_r_est = 0
        try_spatial = not forced and depth < spatial_depth and cap > hi_i and node_area > 0
        if try_spatial and axis >= 0:
            overlap = 0.0
            ex = min(child_box[3], child_box[9]) - max(child_box[0], child_box[6])
            ey = min(child_box[4], child_box[10]) - max(child_box[1], child_box[7])
            ez = min(child_box[5], child_box[11]) - max(child_box[2], child_box[8])
            if ex > 0 and ey > 0 and ez > 0:
                overlap = np.float64(ex) * ey + np.float64(ey) * ez + np.float64(ez) * ex
            try_spatial = overlap > alpha * root_area
        # Spatial bins follow the node size as object bins do (node_bin_count).
        node_sbins = node_bin_count(n_sbins, count)
        if try_spatial:
            # 3. Chopped binning: each reference is cut at the planes it crosses.
            for a in range(3):
                for b in range(node_sbins):
                    s_enter[a, b] = 0
                    s_exit[a, b] = 0
                    for k in range(3):
                        s_box[a, b, k] = np.inf
                        s_box[a, b, 3 + k] = -np.inf
            for i in range(lo_i, hi_i):
                prim = ids[i, 3]
                for a in range(3):
                    extent = np.float64(box[3 + a]) - box[a]
                    if extent <= 0:
                        continue
                    inv_width = node_sbins / extent
                    b0 = _spatial_bin(refs[i, a], box[a], inv_width, node_sbins)
                    b1 = _spatial_bin(refs[i, 4 + a], box[a], inv_width, node_sbins)
                    s_enter[a, b0] += 1
                    s_exit[a, b1] += 1
                    for k in range(3):
                        cur[k] = refs[i, k]
                        cur[3 + k] = refs[i, 4 + k]
                    for b in range(b0, b1):
                        plane = box[a] + (b + 1) * extent / node_sbins
                        _split_reference(tri, prim, cur, a, plane, piece_l, piece_r)
                        for k in range(3):
                            s_box[a, b, k] = min(s_box[a, b, k], piece_l[k])
                            s_box[a, b, 3 + k] = max(s_box[a, b, 3 + k], piece_l[3 + k])
                        for k in range(6):
                            cur[k] = piece_r[k]
                    for k in range(3):
                        s_box[a, b1, k] = min(s_box[a, b1, k], cur[k])
                        s_box[a, b1, 3 + k] = max(s_box[a, b1, 3 + k], cur[3 + k])
            # Sweep every plane: N_L counts entries left of it, N_R exits right of it.
            inv_area = 1.0 / node_area
            for a in range(3):
                if np.float64(box[3 + a]) - box[a] <= 0:
                    continue
                n_right = 0
                for k in range(6):
                    suffix[0, k] = np.inf if k < 3 else -np.inf
                rlo0 = np.inf
                rlo1 = np.inf
                rlo2 = np.inf
                rhi0 = -np.inf
                rhi1 = -np.inf
                rhi2 = -np.inf
                for b in range(node_sbins - 1, 0, -1):
                    n_right += s_exit[a, b]
                    rlo0 = min(rlo0, s_box[a, b, 0])
                    rlo1 = min(rlo1, s_box[a, b, 1])
                    rlo2 = min(rlo2, s_box[a, b, 2])
                    rhi0 = max(rhi0, s_box[a, b, 3])
                    rhi1 = max(rhi1, s_box[a, b, 4])
                    rhi2 = max(rhi2, s_box[a, b, 5])
                    suffix[b, 0] = rlo0
                    suffix[b, 1] = rlo1
                    suffix[b, 2] = rlo2
                    suffix[b, 3] = rhi0
                    suffix[b, 4] = rhi1
                    suffix[b, 5] = rhi2
                    suffix[b, 6] = n_right
                n_left = 0
                for k in range(3):
                    cur[k] = np.inf
                    cur[3 + k] = -np.inf
                for b in range(node_sbins - 1):
                    n_left += s_enter[a, b]
                    for k in range(3):
                        cur[k] = min(cur[k], s_box[a, b, k])
                        cur[3 + k] = max(cur[3 + k], s_box[a, b, 3 + k])
                    n_r = int(suffix[b + 1, 6])
                    if n_left == 0 or n_r == 0:
                        continue
                    # Duplicates must fit in the node's capacity.
                    if lo_i + n_left + n_r > cap:
                        continue
                    area_l = _half_area6(cur)
                    area_r = _half_area6(suffix[b + 1])
                    c = trav_cost + isect_cost * (area_l * n_left + area_r * n_r) * inv_area
                    if c < s_cost:
                        s_cost = c
                        s_axis = a
                        s_split = b
                        n_l_est = n_left
                        n_r_est = n_r
        best = min(cost, s_cost)
        # Leaf when no split pays and the leaf is small enough.
        if count <= max_leaf and best >= isect_cost * count:
            t_first[node] = lo_i
            t_count[node] = count
            continue
        left = next_node
        next_node += 2
        left_of[node] = left
        right_of[node] = left + 1
        t_count[node] = 0
        if s_axis >= 0 and s_cost < cost:
            # 4. Spatial partition with unsplitting; right references go to scratch.
            a = s_axis
            extent = np.float64(box[3 + a]) - box[a]
            inv_width = node_sbins / extent
            plane = box[a] + (s_split + 1) * extent / node_sbins
            # Child boxes of the sweep, for the unsplitting costs.
            for k in range(3):
                box_l[k] = np.inf
                box_l[3 + k] = -np.inf
                box_r[k] = np.inf
                box_r[3 + k] = -np.inf
            for b in range(node_sbins):
                for k in range(3):
                    if b <= s_split:
                        box_l[k] = min(box_l[k], s_box[a, b, k])
                        box_l[3 + k] = max(box_l[3 + k], s_box[a, b, 3 + k])
                    else:
                        box_r[k] = min(box_r[k], s_box[a, b, k])
                        box_r[3 + k] = max(box_r[3 + k], s_box[a, b, 3 + k])
            n1 = n_l_est
            n2 = n_r_est
            w = lo_i
            n_scr = 0
            for i in range(lo_i, hi_i):
                b0 = _spatial_bin(refs[i, a], box[a], inv_width, node_sbins)
                b1 = _spatial_bin(refs[i, 4 + a], box[a], inv_width, node_sbins)
                side = 0
                if b1 <= s_split:
                    side = -1
                elif b0 > s_split:
                    side = 1
                else:
                    # Unsplit when keeping the reference whole on one side is cheaper.
                    for k in range(3):
                        cur[k] = min(box_l[k], refs[i, k])
                        cur[3 + k] = max(box_l[3 + k], refs[i, 4 + k])
                    a1 = _half_area6(cur)
                    for k in range(3):
                        cur[k] = min(box_r[k], refs[i, k])
                        cur[3 + k] = max(box_r[3 + k], refs[i, 4 + k])
                    a2 = _half_area6(cur)
                    c_split = _half_area6(box_l) * n1 + _half_area6(box_r) * n2
                    c1 = a1 * n1 + _half_area6(box_r) * (n2 - 1)
                    c2 = _half_area6(box_l) * (n1 - 1) + a2 * n2
                    # Never empty a side (the counts are exact: n2 - 1 >= 1 keeps one).
                    if c1 < c_split and c1 <= c2 and n2 > 1:
                        side = -1
                        n2 -= 1
                    elif c2 < c_split and n1 > 1:
                        side = 1
                        n1 -= 1
                if side < 0:
                    for k in range(8):
                        refs[w, k] = refs[i, k]
                    w += 1
                elif side > 0:
                    for k in range(8):
                        scratch[n_scr, k] = refs[i, k]
                    n_scr += 1
                else:
                    # 5. Split the reference: clipped halves on both sides.
                    prim = ids[i, 3]
                    for k in range(3):
                        cur[k] = refs[i, k]
                        cur[3 + k] = refs[i, 4 + k]
                    _split_reference(tri, prim, cur, a, plane, piece_l, piece_r)
                    for k in range(3):
                        refs[w, k] = piece_l[k]
                        refs[w, 4 + k] = piece_l[3 + k]
                        scratch[n_scr, k] = piece_r[k]
                        scratch[n_scr, 4 + k] = piece_r[3 + k]
                    ids[w, 3] = prim
                    scratch_ids[n_scr, 3] = prim
                    refs[w, 7] = 0
                    scratch[n_scr, 7] = 0
                    w += 1
                    n_scr += 1
            n_l = w - lo_i
            n_r = n_scr
            spare = cap - lo_i - n_l - n_r
            split_at = lo_i + n_l + (spare * n_l) // (n_l + n_r)
            for j in range(n_r):
                for k in range(8):
                    refs[split_at + j, k] = scratch[j, k]
            mid_end = lo_i + n_l
            right_begin = split_at
            right_end = split_at + n_r
        else:
            if axis >= 0:
                mid = _partition(
                    refs,
                    lo_i,
                    hi_i,
                    axis,
                    split_bin,
                    box[6 + axis],
                    scale[axis],
                    node_bins,
                    left_cb,
                    right_cb,
                )
            else:
                # No usable plane or the depth bound: balanced index median.
                mid = lo_i + count // 2
            n_l = mid - lo_i
            n_r = hi_i - mid
            spare = cap - hi_i
            shift = (spare * n_l) // count
            # Move the right references up to leave the left child its share of capacity.
            if shift > 0:
                for j in range(hi_i - 1, mid - 1, -1):
                    for k in range(8):
                        refs[j + shift, k] = refs[j, k]
            mid_end = mid
            right_begin = mid + shift
            right_end = hi_i + shift
            split_at = right_begin
        # Push the larger child first so the smaller is processed next.
        for c in range(2):
            first_right = (n_l >= n_r) == (c == 0)
            if first_right:
                s_node[sp] = left + 1
                s_begin[sp] = right_begin
                s_end[sp] = right_end
                s_cap[sp] = cap
            else:
                s_node[sp] = left
                s_begin[sp] = lo_i
                s_end[sp] = mid_end
                s_cap[sp] = split_at
            s_depth[sp] = depth + 1
            sp += 1
    return next_node, n_tasks


@cpu_kernel(parallel=True)
def _build_frontier(
    refs,
    tri,
    tasks,
    task_base,
    root_area,
    alpha,
    n_bins,
    n_sbins,
    spatial_depth,
    max_leaf,
    trav_cost,
    isect_cost,
    left_of,
    right_of,
    t_first,
    t_count,
    n_threads,
):
    """Build every frontier subtree concurrently into its reserved blocks.

    ``n_threads`` workers take the subtrees one at a time, in the given order, from a
    shared counter (:mod:`rayaccel._work`).
    """
    counter = new_counter()
    for _worker in prange(worker_count(tasks.shape[0], n_threads, True)):
        while True:
            i = next_item(counter, tasks.shape[0])
            if i < 0:
                break
            no_tasks = np.empty((1, 5), dtype=np.int32)
            # int64 arguments, as in the serial top-phase call: one compiled signature.
            _build_sbvh_task(
                refs,
                tri,
                np.int64(tasks[i, 1]),
                np.int64(tasks[i, 2]),
                np.int64(tasks[i, 3]),
                np.int64(tasks[i, 4]),
                np.int64(tasks[i, 0]),
                np.int64(task_base[i]),
                np.int64(0),
                root_area,
                alpha,
                n_bins,
                n_sbins,
                spatial_depth,
                max_leaf,
                trav_cost,
                isect_cost,
                left_of,
                right_of,
                t_first,
                t_count,
                no_tasks,
            )


@cpu_kernel(parallel=True)
def _leaf_boxes(refs, left_of, t_first, t_count, lo, hi, n_used):
    """Set every leaf's box to the union of its (clipped) reference boxes."""
    for node in prange(n_used):
        if left_of[node] >= 0 or t_count[node] < 0:
            continue
        for k in range(3):
            lo[node, k] = np.inf
            hi[node, k] = -np.inf
        for r in range(t_first[node], t_first[node] + t_count[node]):
            for k in range(3):
                lo[node, k] = min(lo[node, k], refs[r, k])
                hi[node, k] = max(hi[node, k], refs[r, 4 + k])


@register(
    "builder",
    "bvh2.sbvh",
    options=SbvhOptions,
    summary="SAH BVH with spatial splits: chopped binning, exact clipping, unsplitting",
    reference="Stich, Friedrich, Dietrich 2009, Spatial Splits in Bounding Volume Hierarchies",
)
def build_sbvh(
    mesh: TriangleMesh, options: SbvhOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Build a spatial-split BVH (see the module docstring).

    Parameters
    ----------
    mesh : TriangleMesh
    options : SbvhOptions, optional
    refs : BuildRefs, optional
        Initial references (e.g. pre-split triangle parts); default one per triangle.
        Spatial splits clip a reference's triangle and intersect with its current box,
        so split parts are split further correctly.

    Returns
    -------
    Bvh2
        Canonical tree; ``n_refs <= (1 + duplication_budget) · m`` for ``m`` initial
        references (``n_prims`` without ``refs``); depth at most ``MAX_DEPTH``.
    """
    opt = options or SbvhOptions()
    tri = mesh.triangles()
    if refs is None:
        initial = triangle_ref_rows(mesh.vertices, mesh.faces)
    else:
        initial = ref_rows(check_refs(refs, mesh, "bvh2.sbvh"))
    n = initial.shape[0]
    capacity = n + int(opt.duplication_budget * n)
    rows = np.zeros((capacity, 8), dtype=np.float32)
    rows[:n] = initial
    pool = 2 * capacity + 1
    left_of = np.full(pool, -1, dtype=np.int32)
    right_of = np.full(pool, -1, dtype=np.int32)
    t_first = np.zeros(pool, dtype=np.int32)
    t_count = np.full(pool, -1, dtype=np.int32)
    box = np.empty(12, dtype=np.float32)
    _ref_range_bounds(rows, 0, n, box)
    ext = (box[3:6] - box[0:3]).astype(np.float64)
    root_area = float(ext[0] * ext[1] + ext[1] * ext[2] + ext[2] * ext[0])
    args = (
        root_area,
        float(opt.alpha),
        int(opt.n_bins),
        int(opt.n_spatial_bins),
        int(opt.spatial_depth_limit),
        int(opt.max_leaf_size),
        float(opt.traversal_cost),
        float(opt.intersection_cost),
    )
    # Top phase: split large nodes serially; collect the subtrees below the threshold.
    tasks = np.empty((capacity + 1, 5), dtype=np.int32)
    # Fewer, larger subtrees when threads are few: the top phase is serial (kitchen,
    # 2 threads, timed alternately in one process: median 2.63 -> 2.48 s, same tree).
    stop = max(int(opt.parallel_threshold), n // (4 * numba.get_num_threads()))
    next_node, n_tasks = _build_sbvh_task(
        rows, tri, 0, n, capacity, 0, 0, 1, stop, *args, left_of, right_of, t_first, t_count,
        tasks,
    )  # fmt: skip
    tasks = tasks[:n_tasks]
    if n_tasks:
        # Each subtree of capacity C gets 2C node slots, in task order.
        sizes = 2 * (tasks[:, 3] - tasks[:, 1]).astype(np.int64)
        task_base = (next_node + np.concatenate(([0], np.cumsum(sizes)[:-1]))).astype(np.int32)
        top = next_node
        next_node = int(next_node + sizes.sum())
        # Grow the node pool to hold every reserved block (unused slots stay unreachable).
        left_of, right_of, t_first, t_count = (
            np.concatenate((x[:top], np.full(next_node - top, fill, dtype=np.int32)))
            for x, fill in ((left_of, -1), (right_of, -1), (t_first, 0), (t_count, -1))
        )
        order = np.argsort(-(tasks[:, 2] - tasks[:, 1]), kind="stable")
        # Largest subtrees first, one at a time, so no thread idles at the end.
        _build_frontier(
            rows, tri, np.ascontiguousarray(tasks[order]), task_base[order], *args,
            left_of, right_of, t_first, t_count, numba.get_num_threads(),
        )  # fmt: skip
    lo = np.zeros((next_node, 3), dtype=np.float32)
    hi = np.zeros((next_node, 3), dtype=np.float32)
    _leaf_boxes(rows, left_of, t_first, t_count, lo, hi, next_node)
    ids = np.ascontiguousarray(rows.view(np.int32)[:, 3])
    count = np.maximum(t_count, 0).astype(np.int32)
    tree = LinkedTree(left_of, right_of, lo, hi, t_first, count, ids)
    return linked_to_canonical(tree, 0, mesh.n_triangles, collapse=False)
