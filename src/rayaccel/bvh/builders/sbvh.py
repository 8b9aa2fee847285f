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
   to float32), intersected with the reference's current box
   (:func:`~rayaccel.kernels.clip.split_triangle_bounds`).

The split function is :mod:`rayaccel.bvh.builders.split_spatial`, run by the
top-down scheduler (:mod:`rayaccel.bvh.builders.topdown`).

Duplication is bounded: references live in one array of ``(1 + duplication_budget)·n``
slots (``n`` initial references: one per triangle, or the parts a pre-split step
made), each node owning a contiguous capacity that is shared between its children
in proportion to their counts; a spatial split that does not fit is not taken.
Spatial splits are also skipped below depth ``spatial_depth_limit`` (NVIDIA's code
uses 48) and when the depth bound forces median splits. Leaves reference whole
triangles (each fragment is tested whole), so a triangle may sit in several leaves.

Parallelism: large nodes are split serially; subtrees below ``parallel_threshold``
references are built concurrently (:func:`~rayaccel.bvh.builders.topdown.build_top_down`),
each into node and reference blocks reserved up front, so the result does not depend
on the thread count. Reported:
lowest SAH and fastest traversal of the BVH builders, builds about 4–8× slower than
binned SAH (Devillers thesis, Table 5.4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.common import ref_range_bounds, ref_rows, triangle_ref_rows
from rayaccel.bvh.builders.refs import BuildRefs, check_refs
from rayaccel.bvh.builders.split_binned import MAX_BINS
from rayaccel.bvh.builders.split_spatial import SpatialParams
from rayaccel.bvh.builders.topdown import SPATIAL, build_top_down, check_split_options, new_pool
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
        check_split_options(
            self.max_leaf_size, self.traversal_cost, self.intersection_cost, self.parallel_threshold
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


@register("builder", "bvh2.sbvh")
def build_sbvh(
    mesh: TriangleMesh, options: SbvhOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """SAH BVH with spatial splits: chopped binning, exact clipping, unsplitting.

    Build a spatial-split BVH (see the module docstring).

    Spatial splits clip a reference's triangle and intersect with its current box, so
    parts of ``refs`` are split further correctly. The tree has ``n_refs <= (1 +
    duplication_budget) · m`` references for ``m`` initial ones (``n_prims`` without
    ``refs``); its depth is at most ``MAX_DEPTH``.

    References
    ----------
    Stich, Friedrich, Dietrich 2009, Spatial Splits in Bounding Volume Hierarchies.
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
    box = np.empty(12, dtype=np.float32)
    ref_range_bounds(rows, 0, n, box)
    ext = (box[3:6] - box[0:3]).astype(np.float64)
    root_area = float(ext[0] * ext[1] + ext[1] * ext[2] + ext[2] * ext[0])
    params = SpatialParams(
        root_area,
        float(opt.alpha),
        int(opt.n_bins),
        int(opt.n_spatial_bins),
        int(opt.spatial_depth_limit),
        int(opt.max_leaf_size),
        float(opt.traversal_cost),
        float(opt.intersection_cost),
    )
    # Top phase serial, subtrees below the threshold in parallel. Fewer, larger subtrees
    # when threads are few: the top phase is serial (kitchen, 2 threads, timed
    # alternately in one process: median 2.63 -> 2.48 s, same tree).
    stop = max(int(opt.parallel_threshold), n // (4 * numba.get_num_threads()))
    no_box = np.zeros(6, dtype=np.float32)
    next_node, pool = build_top_down(
        SPATIAL, rows, (tri,), params, n, capacity, no_box, stop, new_pool(2 * capacity + 1)
    )
    t_first = pool.first[:next_node]
    t_count = pool.ref_count[:next_node]
    left_of = np.where(t_count == 0, t_first, -1).astype(np.int32)
    right_of = np.where(t_count == 0, t_first + 1, -1).astype(np.int32)
    lo = np.zeros((next_node, 3), dtype=np.float32)
    hi = np.zeros((next_node, 3), dtype=np.float32)
    _leaf_boxes(rows, left_of, t_first, t_count, lo, hi, next_node)
    ids = np.ascontiguousarray(rows.view(np.int32)[:, 3])
    count = np.maximum(t_count, 0).astype(np.int32)
    tree = LinkedTree(left_of, right_of, lo, hi, np.ascontiguousarray(t_first), count, ids)
    return linked_to_canonical(tree, 0, mesh.n_triangles, collapse=False)
