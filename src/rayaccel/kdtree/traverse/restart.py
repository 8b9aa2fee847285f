"""``kdtree.restart``: kd-restart (Foley & Sugerman 2005), no stack, each leaf found from the root.

After each leaf the ray's segment start moves to the leaf's exit and the descent
starts again at the root (:mod:`rayaccel.kdtree.traverse.stackless`). The thesis's
KD_restart did not finish on two scenes; here ``t`` strictly increases with every
descent, so a ray makes at most as many descents as the tree has leaves (tested).
Counters: those of ``kdtree.stack`` plus ``restarts`` (descents after the first).
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel.kdtree.layouts.kdtree import KdTree
from rayaccel.kdtree.traverse.common import kd_trace_layout
from rayaccel.kdtree.traverse.stackless import METHOD_RESTART, stackless_arrays, trace_kernel
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal


@dataclass(frozen=True, slots=True)
class KdRestartOptions:
    """Options of ``kdtree.restart`` (none; kept for a uniform API)."""


@register_traversal("kdtree.restart")
def trace_kdtree_restart(
    kd: KdTree, mesh: TriangleMesh, options: KdRestartOptions, cache: LayoutCache
) -> TracePlan:
    """kd-restart: stackless, every leaf found by a descent from the root.

    Trace rays through a kd-tree with kd-restart.

    References
    ----------
    Foley & Sugerman 2005, KD-Tree Acceleration Structures for a GPU Raytracer.
    """
    arrays = stackless_arrays(kd_trace_layout(kd, mesh, cache))
    return TracePlan(trace_kernel(METHOD_RESTART), arrays)
