"""Spatial splits with reference unsplitting (Stich, Friedrich, Dietrich 2009).

Stich, Friedrich, Dietrich 2009, "Spatial Splits in Bounding Volume Hierarchies"
(HPG). The split function of ``bvh2.sbvh``, called by the top-down scheduler
(:mod:`rayaccel.bvh.builders.topdown`). References are rows of a primitive id and a
box that may be a clipped part of the triangle; a node owns the row slots
``[begin, cap)``, of which ``[begin, end)`` are used, so a split may duplicate
references into its spare slots.

1. object split: binned SAH over reference centroids
   (:func:`~rayaccel.bvh.builders.split_binned.binned_split`), giving cost ``C_o``
   and child boxes B1, B2;
2. only if ``A(B1 ∩ B2) / A(root) > alpha`` are spatial splits considered;
3. spatial split: equal bins per axis over the node box (fewer in small nodes, as
   for object bins); each reference is chopped at the bin planes it crosses
   (:func:`~rayaccel.kernels.clip.split_triangle_bounds`: the triangle clipped at the
   plane, within the reference's box), each piece growing its bin's box ("chopped binning");
   it counts once in its entry bin and once in its exit bin; a sweep evaluates every
   plane, skipping those whose duplicates would not fit in ``cap``;
4. partition with reference unsplitting: a straddling reference goes wholly to one
   side when that is cheaper than duplicating it (Stich et al. §4.3);
5. the children share the node's spare slots in proportion to their counts.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.bvh.builders.common import ref_range_bounds
from rayaccel.bvh.builders.split_binned import (
    bin_scales,
    binned_split,
    node_bin_count,
    partition_refs,
    suffix_bounds,
)
from rayaccel.kernels.box_grow import EMPTY_BOUNDS, union_bounds
from rayaccel.kernels.clip import split_triangle_bounds
from rayaccel.kernels.sah import bounds_half_area, box_half_area, sah_split_cost


class SpatialParams(NamedTuple):
    """Constants of a spatial-split build, as the kernels take them.

    Attributes
    ----------
    root_area : float
        Half area of the root box (the ``alpha`` test's denominator).
    alpha : float
        Spatial splits are tried when the object children overlap by more than
        ``alpha · root_area``.
    n_bins, n_spatial_bins : int
        Object and spatial bins per axis of large nodes.
    spatial_depth_limit : int
        No spatial splits at or below this depth.
    max_leaf_size : int
    traversal_cost, intersection_cost : float
    """

    root_area: float
    alpha: float
    n_bins: int
    n_spatial_bins: int
    spatial_depth_limit: int
    max_leaf_size: int
    traversal_cost: float
    intersection_cost: float


class SpatialWorkspace(NamedTuple):
    """Scratch arrays of one thread's spatial-split build (:func:`spatial_workspace`).

    ``counts``, ``bin_box``, ``suffix``, ``child_box`` and ``scale`` serve the object
    split (:class:`~rayaccel.bvh.builders.split_binned.BinnedWorkspace`); ``s_enter``,
    ``s_exit`` (3, n_spatial_bins) and ``s_box`` (3, n_spatial_bins, 6) are the spatial
    bins; ``cur``, ``piece_l``, ``piece_r``, ``box_l``, ``box_r`` are 6-float boxes;
    ``scratch`` (capacity, 8) receives the right references of a spatial partition;
    ``est`` (2,) carries the chosen spatial split's left and right counts from the
    search to the partition.
    """

    counts: np.ndarray
    bin_box: np.ndarray
    suffix: np.ndarray
    child_box: np.ndarray
    scale: np.ndarray
    s_enter: np.ndarray
    s_exit: np.ndarray
    s_box: np.ndarray
    cur: np.ndarray
    piece_l: np.ndarray
    piece_r: np.ndarray
    box_l: np.ndarray
    box_r: np.ndarray
    scratch: np.ndarray
    est: np.ndarray


@cpu_inline
def spatial_workspace(params, capacity):
    """Return a :class:`SpatialWorkspace` for a subtree owning ``capacity`` reference slots."""
    n_bins = params.n_bins
    n_sbins = params.n_spatial_bins
    return SpatialWorkspace(
        np.zeros((3, n_bins), dtype=np.int32),
        np.empty((3, n_bins, 8), dtype=np.float32),
        np.empty((max(n_bins, n_sbins), 7), dtype=np.float32),
        np.empty(12, dtype=np.float32),
        np.empty(3, dtype=np.float32),
        np.zeros((3, n_sbins), dtype=np.int32),
        np.zeros((3, n_sbins), dtype=np.int32),
        np.empty((3, n_sbins, 6), dtype=np.float32),
        np.empty(6, dtype=np.float32),
        np.empty(6, dtype=np.float32),
        np.empty(6, dtype=np.float32),
        np.empty(6, dtype=np.float32),
        np.empty(6, dtype=np.float32),
        np.empty((max(capacity, 1), 8), dtype=np.float32),
        np.zeros(2, dtype=np.int64),
    )


@cpu_inline
def _spatial_bin(value, node_lo, inv_width, n_bins):
    """Spatial bin of coordinate ``value`` in bins of ``1 / inv_width`` from ``node_lo``."""
    b = int((np.float64(value) - node_lo) * inv_width)
    return min(max(b, 0), n_bins - 1)


@cpu_inline
def _chopped_binning(refs, tri, ws, begin, end, box, node_sbins):
    """Bin ``refs[begin:end]`` into ``node_sbins`` spatial bins per axis of the node box.

    Each reference is cut at the bin planes it crosses; every piece grows its bin's
    box, and the reference counts in its entry bin (``s_enter``) and its exit bin
    (``s_exit``).
    """
    ids = refs.view(np.int32)
    s_enter = ws.s_enter
    s_exit = ws.s_exit
    s_box = ws.s_box
    cur = ws.cur
    piece_l = ws.piece_l
    piece_r = ws.piece_r
    for a in range(3):
        for b in range(node_sbins):
            s_enter[a, b] = 0
            s_exit[a, b] = 0
            for k in range(3):
                s_box[a, b, k] = np.inf
                s_box[a, b, 3 + k] = -np.inf
    for i in range(begin, end):
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
                split_triangle_bounds(tri, prim, cur, a, plane, piece_l, piece_r)
                for k in range(3):
                    s_box[a, b, k] = min(s_box[a, b, k], piece_l[k])
                    s_box[a, b, 3 + k] = max(s_box[a, b, 3 + k], piece_l[3 + k])
                for k in range(6):
                    cur[k] = piece_r[k]
            for k in range(3):
                s_box[a, b1, k] = min(s_box[a, b1, k], cur[k])
                s_box[a, b1, 3 + k] = max(s_box[a, b1, 3 + k], cur[3 + k])


@cpu_inline
def spatial_try_split(
    refs, aux, params, ws, node, begin, end, cap, depth, forced, box, t_lo, t_hi
):
    """Find the best object or spatial split of ``refs[begin:end]``: ``(cost, axis, pos)``.

    The scheduler's ``try_split`` for :data:`~rayaccel.bvh.builders.topdown.SPATIAL`;
    ``aux = (tri,)``, the mesh's ``(F, 3, 3)`` corners. Returns the cheaper of the
    two: an object split as ``(cost, axis, bin)``, a spatial split as
    ``(cost, 3 + axis, plane index)`` (its estimated child counts go to ``ws.est``),
    or ``(inf, -1, -1)`` (no split, or ``forced`` by the depth bound). Leaves the
    node's box and doubled-centroid box in ``box[0:12]``; ``t_lo``/``t_hi`` are unused
    (leaf boxes are computed after the build).
    """
    tri = aux[0]
    count = end - begin
    suffix = ws.suffix
    child_box = ws.child_box
    s_exit = ws.s_exit
    s_enter = ws.s_enter
    s_box = ws.s_box
    ref_range_bounds(refs, begin, end, box)
    node_area = box_half_area(box[0], box[1], box[2], box[3], box[4], box[5])
    # 1. Object split on centroid bins.
    axis = -1
    split_bin = -1
    cost = np.inf
    node_bins = node_bin_count(params.n_bins, count)
    if not forced and bin_scales(box, node_bins, ws.scale):
        for a in range(3):
            box[a] = box[6 + a]
        cost, axis, split_bin = binned_split(
            refs, begin, end, box, ws.scale, node_bins, node_area, params.traversal_cost,
            params.intersection_cost, ws.counts, ws.bin_box, suffix, child_box,
        )  # fmt: skip
        ref_range_bounds(refs, begin, end, box)
    # 2. Spatial split, only where the object split's children overlap enough.
    s_axis = -1
    s_cost = np.inf
    s_split = -1
    try_spatial = (
        not forced and depth < params.spatial_depth_limit and cap > end and node_area > 0
    )
    if try_spatial and axis >= 0:
        overlap = 0.0
        ex = min(child_box[3], child_box[9]) - max(child_box[0], child_box[6])
        ey = min(child_box[4], child_box[10]) - max(child_box[1], child_box[7])
        ez = min(child_box[5], child_box[11]) - max(child_box[2], child_box[8])
        if ex > 0 and ey > 0 and ez > 0:
            overlap = np.float64(ex) * ey + np.float64(ey) * ez + np.float64(ez) * ex
        try_spatial = overlap > params.alpha * params.root_area
    if try_spatial:
        # 3. Chopped binning, then a sweep over every plane: N_L counts entries left of
        # it, N_R exits right of it.
        node_sbins = node_bin_count(params.n_spatial_bins, count)
        _chopped_binning(refs, tri, ws, begin, end, box, node_sbins)
        inv_area = 1.0 / node_area
        for a in range(3):
            if np.float64(box[3 + a]) - box[a] <= 0:
                continue
            for k in range(6):
                suffix[0, k] = np.inf if k < 3 else -np.inf
            bins = s_box[a]
            suffix_bounds(s_exit[a], bins, 3, node_sbins, suffix)
            n_left = 0
            left = EMPTY_BOUNDS
            for b in range(node_sbins - 1):
                n_left += s_enter[a, b]
                left = union_bounds(left, bins, bins, b, 3)
                n_r = int(suffix[b + 1, 6])
                if n_left == 0 or n_r == 0:
                    continue
                # Duplicates must fit in the node's capacity.
                if begin + n_left + n_r > cap:
                    continue
                area_l = bounds_half_area(left)
                s = suffix[b + 1]
                area_r = box_half_area(s[0], s[1], s[2], s[3], s[4], s[5])
                c = sah_split_cost(
                    params.traversal_cost, params.intersection_cost, area_l, n_left, area_r,
                    n_r, inv_area,
                )  # fmt: skip
                if c < s_cost:
                    s_cost = c
                    s_axis = a
                    s_split = b
                    ws.est[0] = n_left
                    ws.est[1] = n_r
    best = min(cost, s_cost)
    if s_axis >= 0 and s_cost < cost:
        return best, 3 + s_axis, s_split
    return best, axis, split_bin


@cpu_inline
def spatial_apply_split(
    refs, aux, params, ws, node, left, begin, end, cap, cost, axis, pos, box, child_item, t_lo,
    t_hi,
):  # fmt: skip
    """Apply :func:`spatial_try_split`'s split; return the children's ranges.

    The scheduler's split step for :data:`~rayaccel.bvh.builders.topdown.SPATIAL`.
    Returns ``(left_end, right_begin, right_end, left_cap)``: the left child keeps
    ``[begin, left_end)`` with capacity up to ``left_cap``, the right child
    ``[right_begin, right_end)`` with capacity up to ``cap``; the node's spare slots
    are shared in proportion to the children's counts. ``child_item`` receives
    unused centroid boxes; ``t_lo``/``t_hi`` are unused.
    """
    tri = aux[0]
    ids = refs.view(np.int32)
    count = end - begin
    cur = ws.cur
    piece_l = ws.piece_l
    piece_r = ws.piece_r
    box_l = ws.box_l
    box_r = ws.box_r
    s_box = ws.s_box
    scratch = ws.scratch
    scratch_ids = scratch.view(np.int32)
    if axis >= 3:
        # 4. Spatial partition with unsplitting; right references go to scratch.
        a = axis - 3
        s_split = pos
        node_sbins = node_bin_count(params.n_spatial_bins, count)
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
        area_box_l = box_half_area(box_l[0], box_l[1], box_l[2], box_l[3], box_l[4], box_l[5])
        area_box_r = box_half_area(box_r[0], box_r[1], box_r[2], box_r[3], box_r[4], box_r[5])
        n1 = ws.est[0]
        n2 = ws.est[1]
        w = begin
        n_scr = 0
        for i in range(begin, end):
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
                a1 = box_half_area(cur[0], cur[1], cur[2], cur[3], cur[4], cur[5])
                for k in range(3):
                    cur[k] = min(box_r[k], refs[i, k])
                    cur[3 + k] = max(box_r[3 + k], refs[i, 4 + k])
                a2 = box_half_area(cur[0], cur[1], cur[2], cur[3], cur[4], cur[5])
                c_split = area_box_l * n1 + area_box_r * n2
                c1 = a1 * n1 + area_box_r * (n2 - 1)
                c2 = area_box_l * (n1 - 1) + a2 * n2
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
                split_triangle_bounds(tri, prim, cur, a, plane, piece_l, piece_r)
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
        n_l = w - begin
        n_r = n_scr
        spare = cap - begin - n_l - n_r
        split_at = begin + n_l + (spare * n_l) // (n_l + n_r)
        for j in range(n_r):
            for k in range(8):
                refs[split_at + j, k] = scratch[j, k]
        return begin + n_l, split_at, split_at + n_r, split_at
    if axis >= 0:
        mid = partition_refs(
            refs, begin, end, axis, pos, box[6 + axis], ws.scale[axis],
            node_bin_count(params.n_bins, count), child_item[0], child_item[1],
        )  # fmt: skip
    else:
        # No usable plane or the depth bound: balanced index median.
        mid = begin + count // 2
    n_l = mid - begin
    spare = cap - end
    shift = (spare * n_l) // count
    # Move the right references up to leave the left child its share of capacity.
    if shift > 0:
        for j in range(end - 1, mid - 1, -1):
            for k in range(8):
                refs[j + shift, k] = refs[j, k]
    return mid, mid + shift, end + shift, mid + shift
