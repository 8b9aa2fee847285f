"""Full-sweep SAH BVH construction (Wald, Boulos, Shirley 2007, §4).

Wald, Boulos, Shirley 2007, "Ray Tracing Deformable Scenes using Dynamic Bounding
Volume Hierarchies" (ACM TOG 26(1)), §4. At every node all ``N-1`` "first i | rest"
splits of the primitives sorted by centroid are evaluated on all three axes: a
suffix pass records the area of the right part, a prefix pass adds the left part and
keeps the cheapest ``C_trav + C_prim·(A_L·N_L + A_R·N_R)/A`` (MacDonald & Booth
1990). This is the reference-quality top-down greedy SAH build (binned SAH
approximates it).

The three orders are sorted once; a split marks the primitives that go left and
stably partitions each order within the node's range, so every node costs O(N) and
the build O(N log N) (no per-node sorting). Degenerate nodes (a split no better than
a leaf but too many primitives for one, or a depth that must stay bounded) are cut
at the median of the longest axis's order, so the depth stays below ``MAX_DEPTH``.
The split function is :mod:`rayaccel.bvh.builders.split_sweep`, run by the top-down
scheduler (:mod:`rayaccel.bvh.builders.topdown`). Serial; use ``bvh2.binned_sah``
for speed.

Given ``refs`` (:class:`~rayaccel.bvh.builders.refs.BuildRefs`, e.g. from ``+presplit``),
it builds over those boxes instead of one per triangle; leaves name mesh triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.common import compact_to_canonical, primitive_bounds
from rayaccel.bvh.builders.refs import BuildRefs, check_refs
from rayaccel.bvh.builders.split_sweep import SweepParams
from rayaccel.bvh.builders.topdown import SWEEP, build_top_down, check_split_options, new_pool
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.dtypes import IntArray
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
        check_split_options(self.max_leaf_size, self.traversal_cost, self.intersection_cost)


@cpu_kernel()
def _root_box(prim_lo, prim_hi, t_lo, t_hi):
    """Write the box of all primitive boxes into pool slot 0 (numpy's axis-0 min is slow)."""
    for k in range(3):
        t_lo[0, k] = np.inf
        t_hi[0, k] = -np.inf
    for p in range(prim_lo.shape[0]):
        for k in range(3):
            t_lo[0, k] = min(t_lo[0, k], prim_lo[p, k])
            t_hi[0, k] = max(t_hi[0, k], prim_hi[p, k])


@register("builder", "bvh2.sweep_sah")
def build_sweep_sah(
    mesh: TriangleMesh, options: SweepSahOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Top-down full-sweep SAH over presorted centroid orders (reference quality).

    Build a binary BVH evaluating every split of the sorted centroids.

    References
    ----------
    Wald, Boulos, Shirley 2007, Ray Tracing Deformable Scenes using Dynamic BVHs.
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
    pool = new_pool(2 * n - 1)
    _root_box(prim_lo, prim_hi, pool.lo, pool.hi)
    params = SweepParams(
        int(opt.max_leaf_size), float(opt.traversal_cost), float(opt.intersection_cost)
    )
    no_box = np.zeros(6, dtype=np.float32)
    n_used, pool = build_top_down(
        SWEEP, order, (prim_lo, prim_hi), params, n, n, no_box, 0, pool
    )
    prim_index = order[0] if ref_prim is None else ref_prim[order[0]]
    return compact_to_canonical(*pool, prim_index.copy(), mesh.n_triangles, n_used)
