"""Binned SAH BVH construction (Wald 2007, "On fast Construction of SAH-based BVHs").

Top-down: each node's primitives are binned by centroid into equal intervals of
the node's *centroid* bounds on all three axes (``n_bins``, fewer for small nodes:
Embree's ``4 + n/20``), the surface area heuristic is evaluated at every bin
boundary with one sweep per axis, and the primitive range is partitioned in place
around the cheapest plane (:mod:`rayaccel.bvh.builders.split_binned`). The split
cost is ``C_trav + C_prim · (A_L·N_L + A_R·N_R) / A_node`` against a leaf cost of
``C_prim · N`` (MacDonald & Booth 1990). Nodes are split when the split is cheaper
or when they hold more than ``max_leaf_size`` primitives.

Degenerate input (all centroids equal, e.g. many copies of one triangle) has no
binning plane; such nodes are split at the index median, which bounds the depth by
``log2(n)``. Any node whose remaining depth could exceed ``MAX_DEPTH`` is split at
the median too, so no traversal stack can overflow.

Parallelism (STYLE §4.5): nodes above ``parallel_threshold`` primitives are binned
by all threads (per-chunk bins, min/max and integer reductions, so the result does
not depend on the thread count), a level at a time; the remaining subtrees are built
concurrently by the top-down scheduler (:func:`~rayaccel.bvh.builders.topdown.build_frontier`),
each into a node block reserved by a prefix sum. The pool is then compacted
depth-first into the canonical layout. Cost O(n log n).

Given ``refs`` (:class:`~rayaccel.bvh.builders.refs.BuildRefs`, e.g. from ``+presplit``),
it builds over those boxes instead of one per triangle; leaves name mesh triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel._variant import register
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.builders.common import (
    compact_to_canonical,
    depth_forces_median,
    ref_range_bounds,
    ref_rows,
    triangle_ref_rows,
)
from rayaccel.bvh.builders.refs import BuildRefs, check_refs
from rayaccel.bvh.builders.split_binned import (
    MAX_BINS,
    BinnedParams,
    best_bin_split,
    bin_prims,
    reset_bins,
    split_binned_node,
)
from rayaccel.bvh.builders.topdown import BINNED, build_frontier, check_split_options, new_pool
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.box_grow import grow_box_row
from rayaccel.kernels.sah import box_half_area
from rayaccel.scene.mesh import TriangleMesh


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
        check_split_options(
            self.max_leaf_size, self.traversal_cost, self.intersection_cost, self.parallel_threshold
        )



@cpu_kernel(parallel=True)
def _bin_parallel(refs, begin, end, cb_lo, scale, n_bins, n_chunks):
    """Bin a large range with ``n_chunks`` private bin sets, then reduce them in order."""
    counts_c = np.zeros((n_chunks, 3, n_bins), dtype=np.int32)
    box_c = np.empty((n_chunks, 3, n_bins, 8), dtype=np.float32)
    size = (end - begin + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        reset_bins(counts_c[c], box_c[c], n_bins)
        lo_i = begin + c * size
        hi_i = min(end, lo_i + size)
        bin_prims(refs, lo_i, hi_i, cb_lo, scale, n_bins, counts_c[c], box_c[c])
    counts = np.empty((3, n_bins), dtype=np.int32)
    bin_box = np.empty((3, n_bins, 8), dtype=np.float32)
    reset_bins(counts, bin_box, n_bins)
    for c in range(n_chunks):
        for a in range(3):
            for b in range(n_bins):
                counts[a, b] += counts_c[c, a, b]
                grow_box_row(bin_box, a, b, box_c[c, a], b)
    return counts, bin_box


@cpu_kernel()
def _split_large(
    refs, begin, end, depth, node, left, cb_in, counts, bin_box, params, scale, t_lo, t_hi,
    t_first, t_count, out_cb,
):  # fmt: skip
    """Split one large node with precomputed bins; return the partition point (-1: leaf)."""
    count = end - begin
    n_bins = params.n_bins
    suffix = np.empty((n_bins, 7), dtype=np.float32)
    child_box = np.empty(12, dtype=np.float32)
    half = np.empty(12, dtype=np.float32)
    node_area = box_half_area(
        t_lo[node, 0], t_lo[node, 1], t_lo[node, 2], t_hi[node, 0], t_hi[node, 1], t_hi[node, 2]
    )
    axis = -1
    split_bin = -1
    cost = np.inf
    if not depth_forces_median(depth, count, params.max_leaf_size) and counts.shape[1] > 0:
        cost, axis, split_bin = best_bin_split(
            counts, bin_box, n_bins, scale, count, node_area, params.traversal_cost,
            params.intersection_cost, suffix, child_box,
        )  # fmt: skip
    if count <= params.max_leaf_size and (axis < 0 or cost >= params.intersection_cost * count):
        t_first[node] = begin
        t_count[node] = count
        return -1
    t_first[node] = left
    t_count[node] = 0
    cb_lo_axis = cb_in[axis] if axis >= 0 else cb_in[0]
    return split_binned_node(
        refs, begin, end, axis, split_bin, cb_lo_axis, scale, n_bins, child_box, half, left,
        t_lo, t_hi, out_cb[0], out_cb[1],
    )  # fmt: skip


@cpu_kernel(parallel=True)
def _split_level(
    refs, task, left, cb_lo, counts, bin_box, usable, params, scale, t_lo, t_hi, t_first,
    t_count, out_cb, mid, n_threads,
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
            n_used_bins = params.n_bins if usable[i] else 0
            mid[i] = _split_large(
                refs, task[i, 0], task[i, 1], task[i, 2], task[i, 3], left[i], cb_lo[i],
                counts[i, :, :n_used_bins], bin_box[i, :, :n_used_bins], params, scale[i],
                t_lo, t_hi, t_first, t_count, out_cb[i],
            )  # fmt: skip


@register("builder", "bvh2.binned_sah", default=True)
def build_binned_sah(
    mesh: TriangleMesh, options: BinnedSahOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Top-down binned SAH on centroid bins, parallel over large nodes and subtrees.

    Build a binary BVH with the binned surface area heuristic.

    The tree's depth is at most ``MAX_DEPTH``.

    References
    ----------
    Wald 2007, On fast Construction of SAH-based Bounding Volume Hierarchies.
    """
    opt = options or BinnedSahOptions()
    if refs is None:
        rows = triangle_ref_rows(mesh.vertices, mesh.faces)
    else:
        rows = ref_rows(check_refs(refs, mesh, "bvh2.binned_sah"))
    n = rows.shape[0]
    pool = new_pool(2 * n - 1)
    t_lo, t_hi, t_first, t_count = pool
    box = np.empty(12, dtype=np.float32)
    ref_range_bounds(rows, 0, n, box)
    t_lo[0], t_hi[0] = box[0:3], box[3:6]
    n_bins = int(opt.n_bins)
    params = BinnedParams(
        n_bins, int(opt.max_leaf_size), float(opt.traversal_cost), float(opt.intersection_cost)
    )
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
            rows, task, left, cb_lo, counts, bin_box, usable, params, scale, t_lo, t_hi,
            t_first, t_count, out_cb, mid, numba.get_num_threads(),
        )  # fmt: skip
        level = []
        for i, (begin, end, depth, _) in enumerate(task.tolist()):
            if mid[i] >= 0:
                level.append((begin, int(mid[i]), depth + 1, int(left[i]), out_cb[i, 0].copy()))
                level.append((int(mid[i]), end, depth + 1, int(left[i]) + 1, out_cb[i, 1].copy()))
    # Frontier phase: the scheduler builds the remaining subtrees concurrently.
    tasks = np.array([(t[3], t[0], t[1], t[1], t[2]) for t in frontier], dtype=np.int32)
    task_box = np.array([t[4] for t in frontier], dtype=np.float32).reshape(-1, 6)
    next_node, pool = build_frontier(
        BINNED, rows, (), params, tasks.reshape(-1, 5), task_box, next_node, pool
    )
    prim_index = np.ascontiguousarray(rows.view(np.int32)[:, 3])
    return compact_to_canonical(*pool, prim_index, mesh.n_triangles, next_node)
