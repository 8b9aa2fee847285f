"""``kdtree.median``: the spatial-median kd-tree, the baseline of the SAH build.

Each node with more than ``max_leaf_size`` triangles is cut in the middle of the
longest axis of its cell (Kaplan 1985's BSP of space, as in the early kd-tree ray
tracers), until the depth cap ``8 + 1.3·log2 N``. Triangles are classified and
clipped exactly as in ``kdtree.sah`` (:mod:`rayaccel.kdtree.builders.sweep`).
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel._variant import register
from rayaccel.kdtree.builders.sweep import MAX_DUPLICATION, MODE_MEDIAN, SweepParams, build_sweep
from rayaccel.kdtree.layouts.kdtree import MAX_DEPTH, KdTree, check_build_options
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class KdMedianOptions:
    """Options of :func:`build_kdtree_median`.

    Attributes
    ----------
    max_leaf_size : int
        Nodes with more triangles are split (>= 1).
    max_depth : int
        Upper bound on the depth (1..MAX_DEPTH); also capped at ``8 + 1.3·log2 N``.
    perfect_splits : bool
        Clip straddling triangles to each child cell (True) or cut their boxes.
    parallel_threshold : int
        Subtree size of the concurrent phase, as for ``kdtree.sah``
        (:class:`~rayaccel.kdtree.builders.sah.KdSahOptions`).
    max_duplication : float
        Bound on the references a path accumulates, as for ``kdtree.sah``.
    """

    max_leaf_size: int = 4
    max_depth: int = MAX_DEPTH
    perfect_splits: bool = True
    parallel_threshold: int = 4096
    max_duplication: float = MAX_DUPLICATION

    def __post_init__(self) -> None:
        check_build_options(
            self.max_depth, self.max_leaf_size, self.parallel_threshold, self.max_duplication
        )


@register("builder", "kdtree.median")
def build_kdtree_median(mesh: TriangleMesh, options: KdMedianOptions | None = None) -> KdTree:
    """Spatial-median kd-tree (the longest axis of the cell cut in half).

    Build a kd-tree by spatial median splits.

    References
    ----------
    Kaplan 1985, Space-tracing: a constant time ray-tracer.
    """
    opt = options or KdMedianOptions()
    params = SweepParams(
        MODE_MEDIAN, 1.0, 1.0, 1.0, int(opt.max_depth), int(opt.max_leaf_size),
        bool(opt.perfect_splits), int(opt.parallel_threshold),
        max_duplication=float(opt.max_duplication),
    )  # fmt: skip
    return build_sweep(mesh, params)
