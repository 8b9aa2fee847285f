"""``kdtree.median``: the spatial-median kd-tree, the baseline of the SAH build.

Each node with more than ``max_leaf_size`` triangles is cut in the middle of the
longest axis of its cell (Kaplan 1985's BSP of space, as in the early kd-tree ray
tracers), until the depth cap ``8 + 1.3·log2 N``. Triangles are classified and
clipped exactly as in ``kdtree.sah`` (:mod:`rayaccel.kdtree.builders.sweep`).
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel._variant import register
from rayaccel.errors import InvalidInputError
from rayaccel.kdtree.builders.sweep import MAX_DUPLICATION, MODE_MEDIAN, SweepParams, build_sweep
from rayaccel.kdtree.layouts.kdtree import MAX_DEPTH, KdTree
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

    max_leaf_size: int = 4
    max_depth: int = MAX_DEPTH
    perfect_splits: bool = True
    parallel_threshold: int = 4096
    max_duplication: float = MAX_DUPLICATION

    def __post_init__(self) -> None:
        if self.max_leaf_size < 1:
            raise InvalidInputError(f"max_leaf_size must be >= 1, got {self.max_leaf_size}")
        if self.parallel_threshold < 0:
            raise InvalidInputError(
                f"parallel_threshold must be >= 0, got {self.parallel_threshold}"
            )
        if not self.max_duplication >= 1:
            raise InvalidInputError(
                f"max_duplication must be >= 1, got {self.max_duplication}"
            )
        if not 1 <= self.max_depth <= MAX_DEPTH:
            raise InvalidInputError(f"max_depth must be in 1..{MAX_DEPTH}, got {self.max_depth}")


@register(
    "builder",
    "kdtree.median",
    options=KdMedianOptions,
    summary="spatial-median kd-tree (the longest axis of the cell cut in half)",
    reference="Kaplan 1985, Space-tracing: a constant time ray-tracer",
)
def build_kdtree_median(mesh: TriangleMesh, options: KdMedianOptions | None = None) -> KdTree:
    """Build a kd-tree by spatial median splits.

    Parameters
    ----------
    mesh : TriangleMesh
    options : KdMedianOptions, optional

    Returns
    -------
    KdTree
    """
    opt = options or KdMedianOptions()
    params = SweepParams(
        MODE_MEDIAN, 1.0, 1.0, 1.0, int(opt.max_depth), int(opt.max_leaf_size),
        bool(opt.perfect_splits), int(opt.parallel_threshold),
        max_duplication=float(opt.max_duplication),
    )  # fmt: skip
    return build_sweep(mesh, params)
