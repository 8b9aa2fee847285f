"""Parallel Locally-Ordered Clustering (PLOC), Meister & Bittner 2018.

Meister & Bittner 2018, "Parallel Locally-Ordered Clustering for Bounding Volume
Hierarchy Construction" (IEEE TVCG 24(3)). Agglomerative clustering in the spirit of
Walter et al. 2008, made parallel by searching neighbours only in a window of the
Morton order:

1. sort the primitives by Morton code; each is a cluster;
2. every cluster ``i`` finds its nearest neighbour among clusters ``i−r..i+r`` of the
   current list, the distance being the surface area of the merged box (ties go to
   the partner ``i xor 1``, then the nearest index, so equal boxes merge pairwise;
   an iteration without a mutual pair merges the first two clusters);
3. mutual nearest neighbours merge into a new inner node placed at the lower index;
4. the list is compacted by a prefix sum, keeping Morton order; repeat until one
   cluster remains.

Steps 2 and 3 run in ``prange`` over clusters; node ids come from prefix sums, so the
tree does not depend on the thread count. The merged tree has one primitive per
leaf; the final conversion collapses leaves by the SAH (the authors' adaptive leaf
collapsing, max leaf size 8). Defaults follow the authors' code: ``r = 25``, 60-bit
(here 63-bit) Morton codes. Reported quality is close to a binned SAH build
(Devillers thesis: 26.8 vs 26.4 primary Mrays/s). Cost O(n·r) per iteration, with
the cluster count shrinking geometrically.

Given ``refs`` (:class:`~rayaccel.bvh.builders.refs.BuildRefs`, e.g. from ``+presplit``),
it builds over those boxes instead of one per triangle; leaves name mesh triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import prange

from rayaccel._hugepages import empty_huge
from rayaccel._jit import cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.common import reference_boxes
from rayaccel.bvh.builders.lbvh import check_leaf_costs, sorted_leaf_tree
from rayaccel.bvh.builders.refs import BuildRefs
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import collapsed_to_canonical
from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh

#: Packed candidate value larger than any real one (see the neighbour search).
NO_CANDIDATE = np.int64(0x7FFFFFFFFFFFFFFF)


@dataclass(frozen=True, slots=True)
class PlocOptions:
    """Options of :func:`build_ploc`.

    Attributes
    ----------
    radius : int
        Search radius ``r`` in the Morton-ordered cluster list (1..256; authors: 25).
        Larger is closer to exact agglomerative clustering and slower (O(n·r)).
    morton_bits : int
        30 or 63.
    max_leaf_size : int
        Largest leaf the final SAH collapse may form (1..64).
    traversal_cost, intersection_cost : float
        SAH constants of the leaf collapse.
    """

    radius: int = 25
    morton_bits: int = 63
    max_leaf_size: int = 8
    traversal_cost: float = 1.2
    intersection_cost: float = 1.0

    def __post_init__(self) -> None:
        if not 1 <= self.radius <= 256:
            raise InvalidInputError(f"radius: expected 1..256, got {self.radius}")
        if self.morton_bits not in (30, 63):
            raise InvalidInputError(f"morton_bits: expected 30 or 63, got {self.morton_bits}")
        check_leaf_costs(self.max_leaf_size, self.traversal_cost, self.intersection_cost)


#: An iteration that merges fewer than one cluster in this many pairs up its clusters
#: by Morton order instead (see :func:`_ploc_kernel`); on real scenes PLOC merges
#: about a third of its clusters per iteration, so this never triggers there.
MIN_MERGE_SHARE = 64


@cpu_kernel(parallel=True)
def _ploc_kernel(n_leaves, radius, left, right, lo, hi, max_chunks):
    """Cluster leaves ``n−1 .. 2n−2`` (Morton order); fill inner nodes; return the root."""
    n = n_leaves
    clusters = empty_huge(n, np.int32)
    for i in range(n):
        clusters[i] = n - 1 + i
    box = empty_huge((6, n), np.float32)
    best = empty_huge(n, np.int64)
    nn = empty_huge(n, np.int32)
    rank = empty_huge(n + 1, np.int32)
    keep = empty_huge(n + 1, np.int32)
    swap = empty_huge(n, np.int32)
    c = n
    next_inner = 0
    while c > 1:
        # Structure-of-arrays copy of the cluster boxes for the window scans.
        for i in prange(c):
            node = clusters[i]
            for k in range(3):
                box[k, i] = lo[node, k]
                box[3 + k, i] = hi[node, k]
            best[i] = NO_CANDIDATE
        # Nearest neighbour in the window by merged-box area. A candidate is packed as
        # (area bits << 32 | key): areas are >= 0, so their float bits order like the
        # areas, and the smallest packed value is the (area, key)-smallest candidate,
        # found branch-free. Ties prefer the partner i xor 1 (key 0), then the nearest
        # index (key 2·|i−j|, +1 when j > i): equal boxes (copies of one triangle) merge
        # pairwise and halve per iteration. Each pair (i, j > i) is measured once and
        # offered to both ends; a chunk owns its clusters and also scans the r clusters
        # before it. The order is strict, so the chunking cannot change the result.
        n_chunks = min(max_chunks, max(1, c // (8 * radius)))
        size = (c + n_chunks - 1) // n_chunks
        for chunk in prange(n_chunks):
            s = chunk * size
            e = min(c, s + size)
            dist = np.empty(radius, dtype=np.float32)
            dist_bits = dist.view(np.int32)
            box_lx = box[0]
            box_ly = box[1]
            box_lz = box[2]
            box_hx = box[3]
            box_hy = box[4]
            box_hz = box[5]
            for i in range(max(0, s - radius), e):
                j0 = max(i + 1, s)
                j1 = min(c, i + radius + 1)
                # Merged-box areas of i with its window. The loops index with unsigned
                # integers: a signed index makes numba emit a negative-index wraparound
                # select per access, which keeps LLVM from vectorizing them (2.7× slower
                # on this scan).
                lx = box[0, i]
                ly = box[1, i]
                lz = box[2, i]
                hx = box[3, i]
                hy = box[4, i]
                hz = box[5, i]
                for k in range(j1 - j0):
                    j = np.uint64(j0 + k)
                    ex = max(hx, box_hx[j]) - min(lx, box_lx[j])
                    ey = max(hy, box_hy[j]) - min(ly, box_ly[j])
                    ez = max(hz, box_hz[j]) - min(lz, box_lz[j])
                    dist[np.uint64(k)] = ex * ey + ey * ez + ez * ex
                # Window slot k is cluster j0 + k at offset k + d0 from i; the partner
                # i xor 1 is slot partner_k (only when it is i + 1).
                d0 = j0 - i
                partner_k = (i ^ 1) - j0
                if i >= s:
                    best_i = best[i]
                    for k in range(j1 - j0):
                        key = 0 if k == partner_k else 2 * (k + d0) + 1
                        best_i = min(best_i, (np.int64(dist_bits[np.uint64(k)]) << 32) | key)
                    best[i] = best_i
                for k in range(min(j1, e) - j0):
                    key = 0 if k == partner_k else 2 * (k + d0)
                    j = np.uint64(j0 + k)
                    best[j] = min(best[j], (np.int64(dist_bits[np.uint64(k)]) << 32) | key)
        # Decode each cluster's neighbour from the key.
        for i in prange(c):
            key = best[i] & 0xFFFFFFFF
            if key == 0:
                nn[i] = i ^ 1
            elif key & 1:
                nn[i] = i + (key >> 1)
            else:
                nn[i] = i - (key >> 1)
        # Mutual pairs merge at the lower index; ids from an exclusive prefix sum.
        total = 0
        for i in range(c):
            rank[i] = total
            if nn[nn[i]] == i and i < nn[i]:
                total += 1
        if total * MIN_MERGE_SHARE < c:
            # Too few mutual pairs: degenerate input (a fan of triangles sharing one
            # vertex makes every cluster's neighbour the one growing cluster, so only
            # one pair merges per iteration: O(n) iterations of O(n·r) and a chain of
            # depth n). Merge neighbours in Morton order, (0, 1), (2, 3), ..., instead:
            # c halves, so the iterations and the depth stay logarithmic.
            for i in range(c):
                nn[i] = i ^ 1 if (i ^ 1) < c else i
            total = 0
            for i in range(c):
                rank[i] = total
                if nn[nn[i]] == i and i < nn[i]:
                    total += 1
        rank[c] = total
        for i in prange(c):
            j = nn[i]
            if nn[j] == i and i < j and rank[i + 1] > rank[i]:
                node = next_inner + rank[i]
                a = clusters[i]
                b = clusters[j]
                left[node] = a
                right[node] = b
                for k in range(3):
                    lo[node, k] = min(lo[a, k], lo[b, k])
                    hi[node, k] = max(hi[a, k], hi[b, k])
                swap[i] = node
            else:
                swap[i] = clusters[i]
        next_inner += total
        # Compact: drop the upper member of every merged pair, keep the order.
        count = 0
        for i in range(c):
            keep[i] = count
            j = nn[i]
            if not (nn[j] == i and j < i and rank[j + 1] > rank[j]):
                count += 1
        keep[c] = count
        for i in prange(c):
            if keep[i + 1] > keep[i]:
                clusters[keep[i]] = swap[i]
        c = count
    return clusters[0]


def build_ploc_refs(
    prim_lo: np.ndarray, prim_hi: np.ndarray, prim_id: np.ndarray, n_prims: int, opt: PlocOptions
) -> Bvh2:
    """Build a PLOC tree over reference boxes (``prim_id`` maps references to primitives)."""
    n = prim_lo.shape[0]
    _, tree = sorted_leaf_tree(prim_lo, prim_hi, prim_id, opt.morton_bits)
    root = 0
    if n > 1:
        max_chunks = 4 * numba.get_num_threads()
        root = int(_ploc_kernel(n, opt.radius, tree.left, tree.right, tree.lo, tree.hi, max_chunks))
    return collapsed_to_canonical(tree, root, n_prims, opt)


@register("builder", "bvh2.ploc")
def build_ploc(
    mesh: TriangleMesh, options: PlocOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Parallel locally-ordered clustering in a Morton-order window, SAH collapse.

    Build a BVH by parallel locally-ordered clustering (see the module docstring).

    The tree's depth is at most ``MAX_DEPTH``.

    References
    ----------
    Meister & Bittner 2018, Parallel Locally-Ordered Clustering for BVH Construction.
    """
    opt = options or PlocOptions()
    prim_lo, prim_hi, ids = reference_boxes(mesh, refs, "bvh2.ploc")
    return build_ploc_refs(prim_lo, prim_hi, ids, mesh.n_triangles, opt)
