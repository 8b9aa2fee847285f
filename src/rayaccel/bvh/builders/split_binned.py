"""Binned SAH object splits (Wald 2007, "On fast Construction of SAH-based BVHs").

The split function of ``bvh2.binned_sah`` and the object splits of ``bvh2.sbvh``,
called by the top-down scheduler (:mod:`rayaccel.bvh.builders.topdown`). A node's
references are binned by centroid into equal intervals of the node's *centroid*
bounds on all three axes (``n_bins``, fewer for small nodes: Embree's ``4 + n/20``,
:func:`node_bin_count`), the surface area heuristic is evaluated at every bin
boundary with one sweep per axis (:func:`best_bin_split`), and the reference range is
partitioned in place around the cheapest plane (:func:`partition_refs`).

References are 32-byte rows ``[lo.x, lo.y, lo.z, id, hi.x, hi.y, hi.z, -]``
(:func:`~rayaccel.bvh.builders.common.triangle_ref_rows`); the binning key is the
doubled centroid ``lo + hi`` (no multiply, same order as the centroid). A node
with no binning plane (all centroids equal) or whose depth forces it is split at
the index median instead.

- :func:`binned_try_split` / :func:`binned_apply_split`: the scheduler's interface
  (``try_split`` of madmann91/bvh's ``binned_sah_builder.h``) over
  :class:`BinnedParams` and a :class:`BinnedWorkspace` per thread.
- :func:`bin_prims`, :func:`reset_bins`, :func:`best_bin_split`,
  :func:`split_binned_node`: the steps, also used by ``bvh2.binned_sah``'s parallel
  binning of large nodes.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.bvh.builders.common import ref_range_bounds
from rayaccel.kernels.box_grow import (
    EMPTY_BOUNDS,
    grow_bounds,
    grow_box_row,
    store_bounds,
    union_bounds,
)
from rayaccel.kernels.sah import bounds_half_area, box_half_area, sah_split_cost

#: Most bins per axis (``n_bins`` options are checked against it).
MAX_BINS = 256
#: Bins of the smallest nodes; see :func:`node_bin_count`.
MIN_BINS = 4
#: Primitives per extra bin above ``MIN_BINS`` (Embree's ``4 + 0.05·n``).
PRIMS_PER_BIN = 20


class BinnedParams(NamedTuple):
    """Constants of a binned SAH build, as the kernels take them.

    Attributes
    ----------
    n_bins : int
        Bins per axis of large nodes (:func:`node_bin_count` gives a node's).
    max_leaf_size : int
        Nodes with more references are always split.
    traversal_cost, intersection_cost : float
        SAH ``C_trav`` and ``C_prim``.
    """

    n_bins: int
    max_leaf_size: int
    traversal_cost: float
    intersection_cost: float


class BinnedWorkspace(NamedTuple):
    """Scratch arrays of one thread's binned splits (:func:`binned_workspace`).

    Attributes
    ----------
    counts : (3, n_bins) int32
        References per bin and axis.
    bin_box : (3, n_bins, 8) float32
        Bin boxes, laid out like reference rows (lanes 3 and 7 unused).
    suffix : (n_bins, 7) float32
        Right-to-left box and count of the sweep.
    child_box : (12,) float32
        The best split's left (0:6) and right (6:12) boxes.
    scale : (3,) float32
        Doubled centroid to bin, per axis (0: no extent).
    half : (12,) float32
        Box and centroid box of a median half.
    """

    counts: np.ndarray
    bin_box: np.ndarray
    suffix: np.ndarray
    child_box: np.ndarray
    scale: np.ndarray
    half: np.ndarray


@cpu_inline
def binned_workspace(n_bins):
    """Return a :class:`BinnedWorkspace` for up to ``n_bins`` bins per axis."""
    return BinnedWorkspace(
        np.zeros((3, n_bins), dtype=np.int32),
        np.empty((3, n_bins, 8), dtype=np.float32),
        np.empty((n_bins, 7), dtype=np.float32),
        np.empty(12, dtype=np.float32),
        np.empty(3, dtype=np.float32),
        np.empty(12, dtype=np.float32),
    )


def _bin_prims_py(refs, begin, end, cb_lo, scale, n_bins, counts, bin_box):
    """Accumulate references ``refs[begin:end]`` into per-axis bins (counts and boxes).

    A reference row is ``[lo.x, lo.y, lo.z, id, hi.x, hi.y, hi.z, -]``; its binning key is
    the doubled centroid ``lo + hi`` (no multiply, same order as the centroid). The
    bin mapping is read into scalars once and the axes are written out: with a loop
    over the axes indexing ``cb_lo``/``scale`` (which LLVM must assume the bin stores
    may overwrite) binning took 1.4× as long (6.5 against 4.5 ns per reference,
    kitchen rows, one thread).
    """
    lo_x, lo_y, lo_z = cb_lo[0], cb_lo[1], cb_lo[2]
    s_x, s_y, s_z = scale[0], scale[1], scale[2]
    last = n_bins - 1
    for k in range(end - begin):
        # Unsigned indices: no negative-index wraparound code per access.
        i = np.uint64(begin + k)
        bx = max(0, min(int((refs[i, 0] + refs[i, 4] - lo_x) * s_x), last))
        by = max(0, min(int((refs[i, 1] + refs[i, 5] - lo_y) * s_y), last))
        bz = max(0, min(int((refs[i, 2] + refs[i, 6] - lo_z) * s_z), last))
        counts[0, np.uint64(bx)] += 1
        grow_box_row(bin_box, 0, bx, refs, i)
        counts[1, np.uint64(by)] += 1
        grow_box_row(bin_box, 1, by, refs, i)
        counts[2, np.uint64(bz)] += 1
        grow_box_row(bin_box, 2, bz, refs, i)


bin_prims = cpu_inline(_bin_prims_py)


@cpu_inline
def node_bin_count(n_bins, count):
    """Bins per axis for a node of ``count`` primitives: ``min(n_bins, 4 + count // 20)``.

    Embree's binning rule (``BinMapping``: ``min(BINS, 4 + 0.05·N)``). The sweep over
    the bins costs the same for every node while binning costs ``O(count)``, so with a
    fixed bin count the sweep dominates the many small nodes near the leaves; there
    fewer bins lose little, since a node of ``count`` primitives has at most
    ``count - 1`` distinct planes. On the kitchen (1.4M triangles) this cut the
    subtree phase by a fifth and the SAH went slightly down (44.86 to 44.79).
    """
    return min(n_bins, MIN_BINS + count // PRIMS_PER_BIN)


@cpu_inline
def reset_bins(counts, bin_box, n_bins):
    """Empty the first ``n_bins`` bins of every axis (count 0, box +inf..-inf)."""
    for a in range(3):
        for b in range(n_bins):
            counts[a, b] = 0
            for k in range(4):
                bin_box[a, b, k] = np.inf
                bin_box[a, b, 4 + k] = -np.inf


@cpu_inline
def bin_scales(cb, n_bins, scale):
    """Write the per-axis scale mapping a doubled centroid to its bin; 0 for an axis with no extent.

    ``cb[6:12]`` is the node's doubled-centroid box. Returns whether any axis has extent.
    """
    usable = False
    for a in range(3):
        extent = cb[9 + a] - cb[6 + a]
        if extent > 0:
            scale[a] = np.float32(n_bins) * np.float32(0.99999) / extent
            usable = True
        else:
            scale[a] = 0
    return usable


@cpu_inline
def suffix_bounds(counts, boxes, h, n_bins, suffix):
    """Write ``suffix[b]``: the box (0:6) and count (6) of bins ``b..n_bins-1``, for ``b >= 1``.

    The right-to-left pass of a bin sweep (object and spatial bins): bin ``b`` holds
    ``counts[b]`` references in the box ``boxes[b, 0:3]`` .. ``boxes[b, h:h + 3]``.
    """
    right = EMPTY_BOUNDS
    n_right = 0
    for b in range(n_bins - 1, 0, -1):
        n_right += counts[b]
        right = union_bounds(right, boxes, boxes, b, h)
        store_bounds(suffix[b], 0, right)
        suffix[b, 6] = n_right


@cpu_inline
def best_bin_split(
    counts, bin_box, n_bins, scale, count, node_area, trav_cost, isect_cost, suffix, child_box
):
    """Sweep each axis's bins; return ``(cost, axis, bin)`` of the best plane (axis -1 if none).

    The best plane puts bins ``<= bin`` left. ``child_box[0:6]``/``[6:12]`` receive the
    left and right boxes. ``suffix`` is scratch of shape (n_bins, 7).
    """
    best_cost = np.inf
    best_axis = -1
    best_bin = -1
    inv_area = 1.0 / node_area if node_area > 0 else 0.0
    for a in range(3):
        if scale[a] == 0:
            continue
        bins = bin_box[a]
        suffix_bounds(counts[a], bins, 4, n_bins, suffix)
        # Left-to-right sweep evaluating the plane after bin b.
        left = EMPTY_BOUNDS
        n_left = 0
        for b in range(n_bins - 1):
            n_left += counts[a, b]
            left = union_bounds(left, bins, bins, b, 4)
            n_r = count - n_left
            if n_left == 0 or n_r == 0:
                continue
            area_left = bounds_half_area(left)
            s = suffix[b + 1]
            area_right = box_half_area(s[0], s[1], s[2], s[3], s[4], s[5])
            cost = sah_split_cost(
                trav_cost, isect_cost, area_left, n_left, area_right, n_r, inv_area
            )
            if cost < best_cost:
                best_cost = cost
                best_axis = a
                best_bin = b
                store_bounds(child_box, 0, left)
                for k in range(6):
                    child_box[6 + k] = s[k]
    return best_cost, best_axis, best_bin


@cpu_inline
def _pair_split(
    refs, begin, cb_lo, scale, n_bins, count, node_area, trav_cost, isect_cost, child_box
):
    """:func:`best_bin_split`'s result for a node of two references, without the bins.

    Two references fall into two bins or one on each axis; every plane between two
    bins gives the same partition, so the sweep's answer is the first axis that
    separates them, at the lower reference's bin, with the two references' own boxes
    as child boxes. The bin indices and the cost are computed with the binning's and
    the sweep's exact expressions, so the tree is the one binning builds. On the
    kitchen (1.4M triangles) 544k of the 1.37M nodes hold two references.
    """
    inv_area = 1.0 / node_area if node_area > 0 else 0.0
    u0 = np.uint64(begin)
    u1 = np.uint64(begin + 1)
    for a in range(3):
        if scale[a] == 0:
            continue
        b0 = int((refs[u0, a] + refs[u0, 4 + a] - cb_lo[a]) * scale[a])
        b1 = int((refs[u1, a] + refs[u1, 4 + a] - cb_lo[a]) * scale[a])
        b0 = max(0, min(b0, n_bins - 1))
        b1 = max(0, min(b1, n_bins - 1))
        if b0 == b1:
            continue
        left = u0 if b0 < b1 else u1
        right = u1 if b0 < b1 else u0
        for k in range(3):
            child_box[k] = refs[left, k]
            child_box[3 + k] = refs[left, 4 + k]
            child_box[6 + k] = refs[right, k]
            child_box[9 + k] = refs[right, 4 + k]
        n_left = np.int32(1)
        n_r = count - n_left
        area_left = box_half_area(
            child_box[0], child_box[1], child_box[2], child_box[3], child_box[4], child_box[5]
        )
        area_right = box_half_area(
            child_box[6], child_box[7], child_box[8], child_box[9], child_box[10], child_box[11]
        )
        cost = sah_split_cost(trav_cost, isect_cost, area_left, n_left, area_right, n_r, inv_area)
        return cost, a, min(b0, b1)
    return np.inf, -1, -1


@cpu_inline
def binned_split(
    refs, begin, end, cb_lo, scale, n_bins, node_area, trav_cost, isect_cost, counts, bin_box,
    suffix, child_box,
):  # fmt: skip
    """Return the best binned object split of ``refs[begin:end]``: ``(cost, axis, bin)``.

    Bins the references (``counts``/``bin_box`` are scratch) and sweeps the bins
    (:func:`best_bin_split`); a node of two references gets the same answer without bins
    (:func:`_pair_split`). Shared by binned SAH and SBVH's object splits.
    """
    count = end - begin
    if count == 2:
        return _pair_split(
            refs, begin, cb_lo, scale, n_bins, count, node_area, trav_cost, isect_cost, child_box
        )
    reset_bins(counts, bin_box, n_bins)
    bin_prims(refs, begin, end, cb_lo, scale, n_bins, counts, bin_box)
    return best_bin_split(
        counts, bin_box, n_bins, scale, count, node_area, trav_cost, isect_cost, suffix, child_box
    )


@cpu_inline
def partition_refs(
    refs, begin, end, axis, split_bin, cb_lo_axis, scale_axis, n_bins, left_cb, right_cb
):
    """Partition ``refs[begin:end]`` so bins ``<= split_bin`` come first; return the middle.

    Rows are swapped whole (32 bytes), so later passes read memory sequentially. Also
    writes both sides' doubled-centroid bounds into ``left_cb``/``right_cb`` (lo 0:3, hi 3:6),
    kept in scalars during the loop (array elements would be reloaded and stored
    around every row swap, which LLVM must assume may overwrite them).
    """
    inf = np.float32(np.inf)
    left = (inf, inf, inf, -inf, -inf, -inf)
    right = left
    i = begin
    j = end - 1
    while i <= j:
        ui = np.uint64(i)
        b = int((refs[ui, axis] + refs[ui, 4 + axis] - cb_lo_axis) * scale_axis)
        if b > n_bins - 1:
            b = n_bins - 1
        if b < 0:
            b = 0
        cx = refs[ui, 0] + refs[ui, 4]
        cy = refs[ui, 1] + refs[ui, 5]
        cz = refs[ui, 2] + refs[ui, 6]
        if b <= split_bin:
            left = grow_bounds(left, cx, cy, cz)
            i += 1
        else:
            right = grow_bounds(right, cx, cy, cz)
            uj = np.uint64(j)
            for k in range(8):
                tmp = refs[ui, k]
                refs[ui, k] = refs[uj, k]
                refs[uj, k] = tmp
            j -= 1
    for k in range(6):
        left_cb[k] = left[k]
        right_cb[k] = right[k]
    return i


@cpu_inline
def _set_node_box(t_lo, t_hi, node, box):
    for k in range(3):
        t_lo[node, k] = box[k]
        t_hi[node, k] = box[3 + k]


@cpu_inline
def split_binned_node(
    refs, begin, end, axis, split_bin, cb_lo_axis, scale, n_bins, child_box, half, left, t_lo,
    t_hi, left_cb, right_cb,
):  # fmt: skip
    """Split ``refs[begin:end]`` at a binned plane (``axis >= 0``) or the index median.

    The children are pool slots ``left`` and ``left + 1``: their boxes go to
    ``t_lo``/``t_hi`` (from ``child_box``, or computed for a median split, using
    ``half`` as scratch) and their doubled-centroid boxes to ``left_cb``/``right_cb``.
    ``cb_lo_axis`` is the node's doubled-centroid low bound on ``axis`` and ``scale``
    the per-axis bin scales. Returns the first reference of the right child.
    """
    if axis >= 0:
        mid = partition_refs(
            refs, begin, end, axis, split_bin, cb_lo_axis, scale[axis], n_bins, left_cb, right_cb
        )
        for k in range(3):
            t_lo[left, k] = child_box[k]
            t_hi[left, k] = child_box[3 + k]
            t_lo[left + 1, k] = child_box[6 + k]
            t_hi[left + 1, k] = child_box[9 + k]
    else:
        # No usable plane (equal centroids) or depth bound reached: balanced index median.
        mid = begin + (end - begin) // 2
        ref_range_bounds(refs, begin, mid, half)
        _set_node_box(t_lo, t_hi, left, half[0:6])
        for k in range(6):
            left_cb[k] = half[6 + k]
        ref_range_bounds(refs, mid, end, half)
        _set_node_box(t_lo, t_hi, left + 1, half[0:6])
        for k in range(6):
            right_cb[k] = half[6 + k]
    return mid


@cpu_inline
def binned_try_split(
    refs, aux, params, ws, node, begin, end, cap, depth, forced, box, t_lo, t_hi
):
    """Find the best binned split of node ``node`` over ``refs[begin:end]``: ``(cost, axis, bin)``.

    The scheduler's ``try_split`` for :data:`~rayaccel.bvh.builders.topdown.BINNED`.
    ``box[6:12]`` holds the node's doubled-centroid box (its work item's box) and
    ``t_lo``/``t_hi`` its box. ``axis`` is -1 when no plane exists or ``forced`` (the
    depth bound) asks for a median split; the cost is then ``inf``. ``aux``, ``cap``
    and ``depth`` are unused (every split kind has the same signature).
    """
    count = end - begin
    node_area = box_half_area(
        t_lo[node, 0], t_lo[node, 1], t_lo[node, 2], t_hi[node, 0], t_hi[node, 1], t_hi[node, 2]
    )
    # Small nodes use fewer bins: the per-bin sweep would dominate their cost.
    node_bins = node_bin_count(params.n_bins, count)
    if not forced and bin_scales(box, node_bins, ws.scale):
        for a in range(3):
            box[a] = box[6 + a]
        return binned_split(
            refs, begin, end, box, ws.scale, node_bins, node_area, params.traversal_cost,
            params.intersection_cost, ws.counts, ws.bin_box, ws.suffix, ws.child_box,
        )  # fmt: skip
    return np.inf, -1, -1


@cpu_inline
def binned_apply_split(
    refs, aux, params, ws, node, left, begin, end, cap, cost, axis, pos, box, child_item, t_lo,
    t_hi,
):  # fmt: skip
    """Apply :func:`binned_try_split`'s split; return the children's ranges.

    The scheduler's split step for :data:`~rayaccel.bvh.builders.topdown.BINNED`. The
    references are partitioned in place, so the children are ``[begin, mid)`` and
    ``[mid, end)``, returned as ``(left_end, right_begin, right_end, left_cap)`` =
    ``(mid, mid, end, mid)``; their boxes go to pool slots ``left``/``left + 1`` and
    their doubled-centroid boxes to ``child_item[0]``/``child_item[1]``.
    """
    node_bins = node_bin_count(params.n_bins, end - begin)
    cb_lo_axis = box[6 + axis] if axis >= 0 else box[6]
    mid = split_binned_node(
        refs, begin, end, axis, pos, cb_lo_axis, ws.scale, node_bins, ws.child_box, ws.half,
        left, t_lo, t_hi, child_item[0], child_item[1],
    )  # fmt: skip
    return mid, mid, end, mid
