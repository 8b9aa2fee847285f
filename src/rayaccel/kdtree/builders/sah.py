"""``kdtree.sah``: the surface area heuristic kd-tree of Wald & Havran 2006, with perfect splits.

Every event position of every axis is a candidate plane; the cheapest by
``λ·(K_T + K_I·(P_L·N_L + P_R·N_R))`` is taken when it beats a leaf (``K_I·N``).
Events are sorted once and spliced per node, so the build is O(N log N)
(:mod:`rayaccel.kdtree.builders.sweep` has the algorithm). Defaults are the paper's:
``K_T = 15``, ``K_I = 20``, empty-space bonus ``λ = 0.8``.
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel._variant import register
from rayaccel.errors import InvalidInputError
from rayaccel.kdtree.builders.sweep import MAX_DUPLICATION, MODE_SAH, SweepParams, build_sweep
from rayaccel.kdtree.layouts.kdtree import MAX_DEPTH, KdTree, check_build_options
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class KdSahOptions:
    """Options of :func:`build_kdtree_sah`.

    Attributes
    ----------
    traversal_cost : float
        ``K_T``, the cost of one traversal step (> 0; paper: 15).
    intersection_cost : float
        ``K_I``, the cost of one triangle test (> 0; paper: 20).
    empty_bonus : float
        ``λ`` multiplying the cost of a split with an empty side (0 < λ <= 1; paper: 0.8).
    perfect_splits : bool
        Clip straddling triangles to each child cell (True) or cut their boxes (False,
        the thesis's KD_no_ps).
    max_depth : int
        Upper bound on the depth (1..MAX_DEPTH); the build also stops at
        ``8 + 1.3·log2 N`` (pbrt).
    max_leaf_size : int
        Nodes with more triangles are split whenever a plane inside the cell exists,
        even when the SAH prefers a leaf (>= 1).
    parallel_threshold : int
        After the top levels, subtrees of at most ``max(parallel_threshold, N/64)``
        triangles are built concurrently (0: serially). The tree does not depend on it
        nor on the thread count, up to node numbering.
    max_duplication : float
        Most references a path may accumulate, as a multiple of its root's (>= 1; the
        product of ``(N_L + N_R) / N`` over its splits). Bounds the references of the
        whole tree by ``max_duplication·N`` at each depth, where long slivers crossing
        many cells (a fan around one vertex) otherwise grow them as ``N²``
        (:mod:`rayaccel.kdtree.builders.sweep`; on the benchmark scenes the default
        trims a few small nodes only).
    """

    traversal_cost: float = 15.0
    intersection_cost: float = 20.0
    empty_bonus: float = 0.8
    perfect_splits: bool = True
    max_depth: int = MAX_DEPTH
    max_leaf_size: int = 1 << 30
    parallel_threshold: int = 4096
    max_duplication: float = MAX_DUPLICATION

    def __post_init__(self) -> None:
        if not self.traversal_cost > 0 or not self.intersection_cost > 0:
            raise InvalidInputError("traversal_cost and intersection_cost must be > 0")
        if not 0 < self.empty_bonus <= 1:
            raise InvalidInputError(f"empty_bonus must be in (0, 1], got {self.empty_bonus}")
        check_build_options(
            self.max_depth, self.max_leaf_size, self.parallel_threshold, self.max_duplication
        )


@register("builder", "kdtree.sah", default=True)
def build_kdtree_sah(mesh: TriangleMesh, options: KdSahOptions | None = None) -> KdTree:
    """SAH kd-tree by the O(N log N) event sweep with perfect splits.

    Build a kd-tree with the surface area heuristic.

    The tree's depth is at most ``min(max_depth, 8 + 1.3·log2 N)``.

    References
    ----------
    Wald & Havran 2006, On building fast kd-Trees for Ray Tracing, and on doing that in O(N log N).
    """
    opt = options or KdSahOptions()
    params = SweepParams(
        MODE_SAH,
        float(opt.traversal_cost),
        float(opt.intersection_cost),
        float(opt.empty_bonus),
        int(opt.max_depth),
        int(opt.max_leaf_size),
        bool(opt.perfect_splits),
        int(opt.parallel_threshold),
        max_duplication=float(opt.max_duplication),
    )
    return build_sweep(mesh, params)
