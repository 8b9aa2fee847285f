"""Binned SAH BVH construction (Wald 2007, "On fast Construction of SAH-based BVHs").

Top-down: each node's primitives are binned by centroid into equal intervals of
the node's *centroid* bounds on all three axes (``n_bins``, fewer for small nodes:
Embree's ``4 + n/20``), the surface area
heuristic is evaluated at every bin boundary with one sweep per axis, and the
primitive range is partitioned in place around the cheapest plane. The split cost
is ``C_trav + C_prim · (A_L·N_L + A_R·N_R) / A_node`` against a leaf cost of
``C_prim · N`` (MacDonald & Booth 1990). Nodes are split when the split is cheaper
or when they hold more than ``max_leaf_size`` primitives.

Degenerate input (all centroids equal, e.g. many copies of one triangle) has no
binning plane; such nodes are split at the index median, which bounds the depth by
``log2(n)``. Any node whose remaining depth could exceed ``MAX_DEPTH`` is split at
the median too, so no traversal stack can overflow.

Parallelism (STYLE §4.5): nodes above ``parallel_threshold`` primitives are binned
by all threads (per-chunk bins, min/max and integer reductions, so the result does
not depend on the thread count); the remaining subtrees are built concurrently with
``prange``, each into a node block reserved by a prefix sum. The pool is then
compacted depth-first into the canonical layout. Cost O(n log n).

Given ``refs`` (:class:`~rayaccel.bvh.builders.refs.BuildRefs`, e.g. from ``+presplit``),
it builds over those boxes instead of one per triangle; leaves name mesh triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.builders.common import (
    compact_to_canonical,
    depth_forces_median,
    triangle_ref_rows,
)
from rayaccel.bvh.builders.refs import BuildRefs, check_refs
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.box_grow import grow_bounds, grow_box_row
from rayaccel.scene.mesh import TriangleMesh

MAX_BINS = 256
#: Bins of the smallest nodes; see :func:`node_bin_count`.
MIN_BINS = 4
#: Primitives per extra bin above ``MIN_BINS`` (Embree's ``4 + 0.05·n``).
PRIMS_PER_BIN = 20


@dataclass(frozen=True, slots=True)
class BinnedSahOptions:
    """Options of :func:`build_binned_sah`.

    Attributes
    ----------
    n_bins : int
        Bins per axis of large nodes (2..256); a node of ``n`` primitives uses
        ``min(n_bins, 4 + n // 20)`` (:func:`node_bin_count`). 32 is within a few
        percent of a full sweep's SAH.
    max_leaf_size : int
        Nodes with more primitives are always split (1..64).
    traversal_cost : float
        SAH cost of one inner node (two box tests), relative to one triangle test.
    intersection_cost : float
        SAH cost of one triangle test.
    parallel_threshold : int
        Nodes with at least this many primitives are binned by all threads; smaller
        subtrees are built one per thread.
    """

    n_bins: int = 32
    max_leaf_size: int = 8
    traversal_cost: float = 1.0
    intersection_cost: float = 1.0
    parallel_threshold: int = 32768

    def __post_init__(self) -> None:
        if not 2 <= self.n_bins <= MAX_BINS:
            raise InvalidInputError(f"n_bins: expected 2..{MAX_BINS}, got {self.n_bins}")
        if not 1 <= self.max_leaf_size <= 64:
            raise InvalidInputError(f"max_leaf_size: expected 1..64, got {self.max_leaf_size}")
        if not (self.traversal_cost >= 0 and self.intersection_cost > 0):
            raise InvalidInputError("traversal_cost must be >= 0 and intersection_cost > 0")
        if self.parallel_threshold < 2:
            raise InvalidInputError("parallel_threshold: expected >= 2")


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
def _reset_bins(counts, bin_box, n_bins):
    for a in range(3):
        for b in range(n_bins):
            counts[a, b] = 0
            for k in range(4):
                bin_box[a, b, k] = np.inf
                bin_box[a, b, 4 + k] = -np.inf


@cpu_inline
def _half_area(lo0, lo1, lo2, hi0, hi1, hi2):
    ex = np.float64(hi0) - lo0
    ey = np.float64(hi1) - lo1
    ez = np.float64(hi2) - lo2
    return ex * ey + ey * ez + ez * ex


@cpu_inline
def _bin_scales(cb, n_bins, scale):
    """Per-axis scale mapping a centroid to its bin; 0 for an axis with no extent."""
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
def _best_split(
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
        # Right-to-left prefix: box and count of bins b..n_bins-1.
        lo0 = np.inf
        lo1 = np.inf
        lo2 = np.inf
        hi0 = -np.inf
        hi1 = -np.inf
        hi2 = -np.inf
        n_right = 0
        for b in range(n_bins - 1, 0, -1):
            n_right += counts[a, b]
            lo0 = min(lo0, bin_box[a, b, 0])
            lo1 = min(lo1, bin_box[a, b, 1])
            lo2 = min(lo2, bin_box[a, b, 2])
            hi0 = max(hi0, bin_box[a, b, 4])
            hi1 = max(hi1, bin_box[a, b, 5])
            hi2 = max(hi2, bin_box[a, b, 6])
            suffix[b, 0] = lo0
            suffix[b, 1] = lo1
            suffix[b, 2] = lo2
            suffix[b, 3] = hi0
            suffix[b, 4] = hi1
            suffix[b, 5] = hi2
            suffix[b, 6] = n_right
        # Left-to-right sweep evaluating the plane after bin b.
        lo0 = np.inf
        lo1 = np.inf
        lo2 = np.inf
        hi0 = -np.inf
        hi1 = -np.inf
        hi2 = -np.inf
        n_left = 0
        for b in range(n_bins - 1):
            n_left += counts[a, b]
            lo0 = min(lo0, bin_box[a, b, 0])
            lo1 = min(lo1, bin_box[a, b, 1])
            lo2 = min(lo2, bin_box[a, b, 2])
            hi0 = max(hi0, bin_box[a, b, 4])
            hi1 = max(hi1, bin_box[a, b, 5])
            hi2 = max(hi2, bin_box[a, b, 6])
            n_r = count - n_left
            if n_left == 0 or n_r == 0:
                continue
            area_left = _half_area(lo0, lo1, lo2, hi0, hi1, hi2)
            s = suffix[b + 1]
            area_right = _half_area(s[0], s[1], s[2], s[3], s[4], s[5])
            cost = trav_cost + isect_cost * (area_left * n_left + area_right * n_r) * inv_area
            if cost < best_cost:
                best_cost = cost
                best_axis = a
                best_bin = b
                child_box[0] = lo0
                child_box[1] = lo1
                child_box[2] = lo2
                child_box[3] = hi0
                child_box[4] = hi1
                child_box[5] = hi2
                for k in range(6):
                    child_box[6 + k] = s[k]
    return best_cost, best_axis, best_bin


@cpu_inline
def _pair_split(
    refs, begin, cb_lo, scale, n_bins, count, node_area, trav_cost, isect_cost, child_box
):
    """:func:`_best_split`'s result for a node of two references, without the bins.

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
        area_left = _half_area(
            child_box[0], child_box[1], child_box[2], child_box[3], child_box[4], child_box[5]
        )
        area_right = _half_area(
            child_box[6], child_box[7], child_box[8], child_box[9], child_box[10], child_box[11]
        )
        cost = trav_cost + isect_cost * (area_left * n_left + area_right * n_r) * inv_area
        return cost, a, min(b0, b1)
    return np.inf, -1, -1


@cpu_inline
def binned_split(
    refs, begin, end, cb_lo, scale, n_bins, node_area, trav_cost, isect_cost, counts, bin_box,
    suffix, child_box,
):  # fmt: skip
    """The best binned object split of ``refs[begin:end]``: ``(cost, axis, bin)``.

    Bins the references (``counts``/``bin_box`` are scratch) and sweeps the bins
    (:func:`_best_split`); a node of two references gets the same answer without bins
    (:func:`_pair_split`). Shared by binned SAH and SBVH's object splits.
    """
    count = end - begin
    if count == 2:
        return _pair_split(
            refs, begin, cb_lo, scale, n_bins, count, node_area, trav_cost, isect_cost, child_box
        )
    _reset_bins(counts, bin_box, n_bins)
    bin_prims(refs, begin, end, cb_lo, scale, n_bins, counts, bin_box)
    return _best_split(
        counts, bin_box, n_bins, scale, count, node_area, trav_cost, isect_cost, suffix, child_box
    )


@cpu_inline
def _partition(
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
def _ref_range_bounds(refs, begin, end, out):
    """Write box ``out[0:6]`` and doubled-centroid box ``out[6:12]`` of ``refs[begin:end]``."""
    for a in range(3):
        out[a] = np.inf
        out[3 + a] = -np.inf
        out[6 + a] = np.inf
        out[9 + a] = -np.inf
    for i in range(begin, end):
        for a in range(3):
            out[a] = min(out[a], refs[i, a])
            out[3 + a] = max(out[3 + a], refs[i, 4 + a])
            c = refs[i, a] + refs[i, 4 + a]
            out[6 + a] = min(out[6 + a], c)
            out[9 + a] = max(out[9 + a], c)


def ref_rows(refs: BuildRefs) -> np.ndarray:
    """Return the ``(m, 8)`` float32 reference rows of ``refs``.

    Same row layout as :func:`~rayaccel.bvh.builders.common.triangle_ref_rows`.
    """
    rows = np.zeros((refs.n_refs, 8), dtype=np.float32)
    rows[:, 0:3] = refs.lo
    rows[:, 4:7] = refs.hi
    rows.view(np.int32)[:, 3] = refs.prim
    return rows


@cpu_inline
def _set_node_box(t_lo, t_hi, node, box):
    for k in range(3):
        t_lo[node, k] = box[k]
        t_hi[node, k] = box[3 + k]


@cpu_kernel()
def _build_subtree(
    refs,
    begin,
    end,
    depth0,
    root,
    node_base,
    box0,
    n_bins,
    max_leaf,
    trav_cost,
    isect_cost,
    t_lo,
    t_hi,
    t_first,
    t_count,
):
    """Build the subtree over ``refs[begin:end]`` serially.

    ``root`` is the pool slot of the subtree root (its box already written) and
    children pairs are allocated from ``node_base``. ``box0[0:12]`` holds the root's
    box and centroid box. Returns the next free pool slot.
    """
    stack_node = np.empty(2 * MAX_DEPTH + 4, dtype=np.int32)
    stack_begin = np.empty(2 * MAX_DEPTH + 4, dtype=np.int32)
    stack_end = np.empty(2 * MAX_DEPTH + 4, dtype=np.int32)
    stack_depth = np.empty(2 * MAX_DEPTH + 4, dtype=np.int32)
    stack_cb = np.empty((2 * MAX_DEPTH + 4, 6), dtype=np.float32)
    counts = np.zeros((3, n_bins), dtype=np.int32)
    bin_box = np.empty((3, n_bins, 8), dtype=np.float32)
    suffix = np.empty((n_bins, 7), dtype=np.float32)
    child_box = np.empty(12, dtype=np.float32)
    cb = np.empty(12, dtype=np.float32)
    scale = np.empty(3, dtype=np.float32)
    left_cb = np.empty(6, dtype=np.float32)
    right_cb = np.empty(6, dtype=np.float32)
    half = np.empty(12, dtype=np.float32)
    next_node = node_base
    # The work stack holds (node, range, depth, centroid box); larger child is pushed first.
    stack_node[0] = root
    stack_begin[0] = begin
    stack_end[0] = end
    stack_depth[0] = depth0
    for k in range(6):
        stack_cb[0, k] = box0[6 + k]
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack_node[sp]
        lo_i = stack_begin[sp]
        hi_i = stack_end[sp]
        depth = stack_depth[sp]
        count = hi_i - lo_i
        for k in range(6):
            cb[6 + k] = stack_cb[sp, k]
        # Small enough to stop outright.
        if count <= 1:
            t_first[node] = lo_i
            t_count[node] = count
            continue
        node_area = _half_area(
            t_lo[node, 0], t_lo[node, 1], t_lo[node, 2], t_hi[node, 0], t_hi[node, 1], t_hi[node, 2]
        )
        forced_median = depth_forces_median(depth, count, max_leaf)
        axis = -1
        split_bin = -1
        cost = np.inf
        # Small nodes use fewer bins: the per-bin sweep would dominate their cost.
        node_bins = node_bin_count(n_bins, count)
        if not forced_median and _bin_scales(cb, node_bins, scale):
            for a in range(3):
                cb[a] = cb[6 + a]
            cost, axis, split_bin = binned_split(
                refs, lo_i, hi_i, cb, scale, node_bins, node_area, trav_cost, isect_cost,
                counts, bin_box, suffix, child_box,
            )  # fmt: skip
        # Leaf when splitting does not pay and the leaf is small enough.
        if count <= max_leaf and (axis < 0 or cost >= isect_cost * count):
            t_first[node] = lo_i
            t_count[node] = count
            continue
        left = next_node
        next_node += 2
        t_first[node] = left
        t_count[node] = 0
        if axis >= 0:
            mid = _partition(
                refs,
                lo_i,
                hi_i,
                axis,
                split_bin,
                cb[6 + axis],
                scale[axis],
                node_bins,
                left_cb,
                right_cb,
            )
            for k in range(3):
                t_lo[left, k] = child_box[k]
                t_hi[left, k] = child_box[3 + k]
                t_lo[left + 1, k] = child_box[6 + k]
                t_hi[left + 1, k] = child_box[9 + k]
        else:
            # No usable plane (equal centroids) or depth bound reached: balanced index median.
            mid = lo_i + count // 2
            _ref_range_bounds(refs, lo_i, mid, half)
            _set_node_box(t_lo, t_hi, left, half[0:6])
            for k in range(6):
                left_cb[k] = half[6 + k]
            _ref_range_bounds(refs, mid, hi_i, half)
            _set_node_box(t_lo, t_hi, left + 1, half[0:6])
            for k in range(6):
                right_cb[k] = half[6 + k]
        # Push the right child first so the left is processed next: pairs are then
        # allocated in the depth-first order compaction walks (sequential memory there).
        # The stack holds at most one pending right child per level (depth <= MAX_DEPTH).
        for c in (1, 0):
            stack_node[sp] = left + c
            stack_begin[sp] = lo_i if c == 0 else mid
            stack_end[sp] = mid if c == 0 else hi_i
            stack_depth[sp] = depth + 1
            for k in range(6):
                stack_cb[sp, k] = left_cb[k] if c == 0 else right_cb[k]
            sp += 1
    return next_node


@cpu_kernel(parallel=True)
def _bin_parallel(refs, begin, end, cb_lo, scale, n_bins, n_chunks):
    """Bin a large range with ``n_chunks`` private bin sets, then reduce them in order."""
    counts_c = np.zeros((n_chunks, 3, n_bins), dtype=np.int32)
    box_c = np.empty((n_chunks, 3, n_bins, 8), dtype=np.float32)
    size = (end - begin + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        _reset_bins(counts_c[c], box_c[c], n_bins)
        lo_i = begin + c * size
        hi_i = min(end, lo_i + size)
        bin_prims(refs, lo_i, hi_i, cb_lo, scale, n_bins, counts_c[c], box_c[c])
    counts = np.empty((3, n_bins), dtype=np.int32)
    bin_box = np.empty((3, n_bins, 8), dtype=np.float32)
    _reset_bins(counts, bin_box, n_bins)
    for c in range(n_chunks):
        for a in range(3):
            for b in range(n_bins):
                counts[a, b] += counts_c[c, a, b]
                grow_box_row(bin_box, a, b, box_c[c, a], b)
    return counts, bin_box


@cpu_kernel()
def _split_large(
    refs,
    begin,
    end,
    depth,
    node,
    left,
    cb_in,
    counts,
    bin_box,
    n_bins,
    max_leaf,
    trav_cost,
    isect_cost,
    scale,
    t_lo,
    t_hi,
    t_first,
    t_count,
    out_cb,
):
    """Split one large node with precomputed bins; return the partition point (-1: leaf)."""
    count = end - begin
    suffix = np.empty((n_bins, 7), dtype=np.float32)
    child_box = np.empty(12, dtype=np.float32)
    half = np.empty(12, dtype=np.float32)
    node_area = _half_area(
        t_lo[node, 0], t_lo[node, 1], t_lo[node, 2], t_hi[node, 0], t_hi[node, 1], t_hi[node, 2]
    )
    axis = -1
    split_bin = -1
    cost = np.inf
    if not depth_forces_median(depth, count, max_leaf) and counts.shape[1] > 0:
        cost, axis, split_bin = _best_split(
            counts,
            bin_box,
            n_bins,
            scale,
            count,
            node_area,
            trav_cost,
            isect_cost,
            suffix,
            child_box,
        )
    if count <= max_leaf and (axis < 0 or cost >= isect_cost * count):
        t_first[node] = begin
        t_count[node] = count
        return -1
    t_first[node] = left
    t_count[node] = 0
    if axis >= 0:
        mid = _partition(
            refs,
            begin,
            end,
            axis,
            split_bin,
            cb_in[axis],
            scale[axis],
            n_bins,
            out_cb[0],
            out_cb[1],
        )
        for k in range(3):
            t_lo[left, k] = child_box[k]
            t_hi[left, k] = child_box[3 + k]
            t_lo[left + 1, k] = child_box[6 + k]
            t_hi[left + 1, k] = child_box[9 + k]
    else:
        mid = begin + count // 2
        _ref_range_bounds(refs, begin, mid, half)
        _set_node_box(t_lo, t_hi, left, half[0:6])
        for k in range(6):
            out_cb[0, k] = half[6 + k]
        _ref_range_bounds(refs, mid, end, half)
        _set_node_box(t_lo, t_hi, left + 1, half[0:6])
        for k in range(6):
            out_cb[1, k] = half[6 + k]
    return mid


@cpu_kernel(parallel=True)
def _split_level(
    refs, task, left, cb_lo, counts, bin_box, usable, n_bins, max_leaf, trav_cost,
    isect_cost, scale, t_lo, t_hi, t_first, t_count, out_cb, mid, n_threads,
):  # fmt: skip
    """Split a level's large nodes concurrently (their reference ranges are disjoint).

    Node ``i`` is ``task[i] = (begin, end, depth, node)`` with bins ``counts[i]``/
    ``bin_box[i]`` (none when ``usable[i]`` is False); its children go to slots
    ``left[i]`` and ``left[i] + 1``. ``mid[i]`` gets the partition point (-1: leaf).
    ``n_threads`` workers take the nodes one at a time from a shared counter.
    """
    counter = new_counter()
    for _worker in prange(worker_count(task.shape[0], n_threads, True)):
        while True:
            i = next_item(counter, task.shape[0])
            if i < 0:
                break
            n_used_bins = n_bins if usable[i] else 0
            mid[i] = _split_large(
                refs, task[i, 0], task[i, 1], task[i, 2], task[i, 3], left[i], cb_lo[i],
                counts[i, :, :n_used_bins], bin_box[i, :, :n_used_bins], n_bins, max_leaf,
                trav_cost, isect_cost, scale[i], t_lo, t_hi, t_first, t_count, out_cb[i],
            )  # fmt: skip


@cpu_kernel(parallel=True)
def _build_frontier(
    refs,
    task_begin,
    task_end,
    task_depth,
    task_node,
    task_base,
    task_cb,
    n_bins,
    max_leaf,
    trav_cost,
    isect_cost,
    t_lo,
    t_hi,
    t_first,
    t_count,
    used,
    n_threads,
):
    """Build every frontier subtree concurrently, each into its reserved node block.

    ``n_threads`` workers take the subtrees one at a time, in the given order, from a
    shared counter (:mod:`rayaccel._work`).
    """
    counter = new_counter()
    for _worker in prange(worker_count(task_begin.shape[0], n_threads, True)):
        while True:
            i = next_item(counter, task_begin.shape[0])
            if i < 0:
                break
            box0 = np.empty(12, dtype=np.float32)
            node = task_node[i]
            for k in range(3):
                box0[k] = t_lo[node, k]
                box0[3 + k] = t_hi[node, k]
            for k in range(6):
                box0[6 + k] = task_cb[i, k]
            used[i] = _build_subtree(
                refs,
                task_begin[i],
                task_end[i],
                task_depth[i],
                node,
                task_base[i],
                box0,
                n_bins,
                max_leaf,
                trav_cost,
                isect_cost,
                t_lo,
                t_hi,
                t_first,
                t_count,
            )


@register(
    "builder",
    "bvh2.binned_sah",
    options=BinnedSahOptions,
    default=True,
    summary="top-down binned SAH on centroid bins, parallel over large nodes and subtrees",
    reference="Wald 2007, On fast Construction of SAH-based Bounding Volume Hierarchies",
)
def build_binned_sah(
    mesh: TriangleMesh, options: BinnedSahOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Build a binary BVH with the binned surface area heuristic.

    Parameters
    ----------
    mesh : TriangleMesh
    options : BinnedSahOptions, optional
    refs : BuildRefs, optional
        References to build over (e.g. pre-split triangle parts); default one per triangle.

    Returns
    -------
    Bvh2
        Canonical tree; depth at most ``MAX_DEPTH``.
    """
    opt = options or BinnedSahOptions()
    if refs is None:
        rows = triangle_ref_rows(mesh.vertices, mesh.faces)
    else:
        rows = ref_rows(check_refs(refs, mesh, "bvh2.binned_sah"))
    n = rows.shape[0]
    capacity = 2 * n - 1 if n > 0 else 1
    t_lo = np.empty((capacity, 3), dtype=np.float32)
    t_hi = np.empty((capacity, 3), dtype=np.float32)
    t_first = np.zeros(capacity, dtype=np.int32)
    t_count = np.full(capacity, -1, dtype=np.int32)
    box = np.empty(12, dtype=np.float32)
    _ref_range_bounds(rows, 0, n, box)
    t_lo[0], t_hi[0] = box[0:3], box[3:6]
    n_bins = int(opt.n_bins)
    max_leaf = int(opt.max_leaf_size)
    trav, isect = float(opt.traversal_cost), float(opt.intersection_cost)
    n_chunks = max(1, 4 * numba.get_num_threads())
    # Top phase, a level at a time: each large node is binned by all threads, then the
    # level's nodes are partitioned concurrently, one per thread; smaller nodes go to
    # the frontier. (Levels, not a work stack: the tree does not depend on the order.)
    level = [(0, n, 0, 0, box[6:12].copy())]
    frontier: list[tuple[int, int, int, int, np.ndarray]] = []
    next_node = 1
    while level:
        large = [task for task in level if task[1] - task[0] >= opt.parallel_threshold]
        frontier.extend(task for task in level if task[1] - task[0] < opt.parallel_threshold)
        if not large:
            break
        m = len(large)
        counts = np.zeros((m, 3, n_bins), dtype=np.int32)
        bin_box = np.zeros((m, 3, n_bins, 8), dtype=np.float32)
        scale = np.zeros((m, 3), dtype=np.float32)
        usable = np.zeros(m, dtype=np.bool_)
        cb_lo = np.ascontiguousarray([task[4][0:3] for task in large], dtype=np.float32)
        bins_span = np.float32(n_bins) * np.float32(0.99999)
        for i, (begin, end, _, _, cb) in enumerate(large):
            extent = cb[3:6] - cb[0:3]
            with np.errstate(divide="ignore"):
                scale[i] = np.where(extent > 0, bins_span / extent, 0)
            usable[i] = (scale[i] > 0).any()
            if usable[i]:
                counts[i], bin_box[i] = _bin_parallel(
                    rows, begin, end, cb_lo[i], scale[i], n_bins, n_chunks
                )
        # Two pool slots per node (a large node that stays a leaf wastes its two; its
        # references, at least parallel_threshold >= 2 of them, need no slots below).
        task = np.array([task[:4] for task in large], dtype=np.int32)
        left = (next_node + 2 * np.arange(m)).astype(np.int32)
        next_node += 2 * m
        mid = np.empty(m, dtype=np.int32)
        out_cb = np.empty((m, 2, 6), dtype=np.float32)
        _split_level(
            rows, task, left, cb_lo, counts, bin_box, usable, n_bins, max_leaf, trav,
            isect, scale, t_lo, t_hi, t_first, t_count, out_cb, mid, numba.get_num_threads(),
        )  # fmt: skip
        level = []
        for i, (begin, end, depth, _) in enumerate(task.tolist()):
            if mid[i] >= 0:
                level.append((begin, int(mid[i]), depth + 1, int(left[i]), out_cb[i, 0].copy()))
                level.append((int(mid[i]), end, depth + 1, int(left[i]) + 1, out_cb[i, 1].copy()))
    # Frontier phase: reserve 2m-2 pool slots per subtree of m primitives, build concurrently.
    if frontier:
        frontier.sort(key=lambda task: task[0])
        task_begin = np.array([t[0] for t in frontier], dtype=np.int32)
        task_end = np.array([t[1] for t in frontier], dtype=np.int32)
        task_depth = np.array([t[2] for t in frontier], dtype=np.int32)
        task_node = np.array([t[3] for t in frontier], dtype=np.int32)
        task_cb = np.ascontiguousarray(np.stack([t[4] for t in frontier]), dtype=np.float32)
        sizes = np.maximum(2 * (task_end - task_begin) - 2, 0)
        task_base = (next_node + np.concatenate(([0], np.cumsum(sizes)[:-1]))).astype(np.int32)
        pool_end = int(next_node + sizes.sum())
        used = np.empty(len(frontier), dtype=np.int32)
        # Largest subtrees first, handed out one at a time, so no thread idles at the end.
        order = np.argsort(-(task_end - task_begin), kind="stable")
        task_begin, task_end, task_depth = task_begin[order], task_end[order], task_depth[order]
        task_node, task_base, task_cb = task_node[order], task_base[order], task_cb[order]
        _build_frontier(
            rows,
            task_begin,
            task_end,
            task_depth,
            task_node,
            task_base,
            task_cb,
            n_bins,
            max_leaf,
            trav,
            isect,
            t_lo,
            t_hi,
            t_first,
            t_count,
            used,
            numba.get_num_threads(),
        )
        next_node = pool_end
    prim_index = np.ascontiguousarray(rows.view(np.int32)[:, 3])
    return compact_to_canonical(
        t_lo, t_hi, t_first, t_count, prim_index, mesh.n_triangles, next_node
    )
