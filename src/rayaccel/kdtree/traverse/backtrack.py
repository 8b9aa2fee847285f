"""``kdtree.backtrack``: kd-backtrack (Foley & Sugerman 2005), parent links and node boxes.

Like kd-restart, but the next descent starts at the nearest ancestor of the leaf
whose box the ray leaves after the leaf's exit, found by walking parent links and
testing each ancestor's box (24 bytes per node, derived once per accel:
:func:`backtrack_layout`). Counters: those of ``kdtree.stack`` plus ``restarts``
(descents after the first) and ``backtracks`` (parent links followed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from rayaccel.dtypes import REAL
from rayaccel.kdtree.layouts.kdtree import KdTree
from rayaccel.kdtree.traverse.common import kd_trace_layout
from rayaccel.kdtree.traverse.stackless import (
    METHOD_BACKTRACK,
    StacklessArrays,
    stackless_arrays,
    trace_kernel,
)
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import memoised_layout


@dataclass(frozen=True, slots=True)
class KdBacktrackOptions:
    """Options of ``kdtree.backtrack`` (none; kept for a uniform API)."""


@dataclass(frozen=True, slots=True, eq=False)
class BacktrackLinks:
    """Node cells (interleaved lo/hi per axis) and parent links of a kd-tree."""

    node_box: np.ndarray  # (n, 6) float32
    parent: np.ndarray  # (n,) int32, root -1

    def nbytes(self) -> int:
        """Return the size in bytes of the boxes and links."""
        return int(self.node_box.nbytes + self.parent.nbytes)


def backtrack_layout(kd: KdTree) -> BacktrackLinks:
    """Derive every node's box and parent from the canonical tree."""
    lo, hi, parent, _ = kd.cells()
    box = np.empty((kd.n_nodes, 6), dtype=REAL)
    box[:, 0::2] = lo
    box[:, 1::2] = hi
    return BacktrackLinks(box, np.ascontiguousarray(parent))


def _arrays(kd: KdTree, mesh: TriangleMesh, cache: dict[str, Any] | None) -> StacklessArrays:
    links = memoised_layout(cache, "kdtree.backtrack", lambda: backtrack_layout(kd))
    return stackless_arrays(
        kd_trace_layout(kd, mesh, cache), links.node_box, links.parent, method=METHOD_BACKTRACK
    )


@register_traversal("kdtree.backtrack")
def trace_kdtree_backtrack(
    kd: KdTree, mesh: TriangleMesh, options: KdBacktrackOptions, cache: LayoutCache
) -> TracePlan:
    """kd-backtrack: stackless, each descent from the nearest ancestor still ahead.

    Trace rays through a kd-tree with kd-backtrack.

    References
    ----------
    Foley & Sugerman 2005, KD-Tree Acceleration Structures for a GPU Raytracer.
    """
    return TracePlan(trace_kernel(METHOD_BACKTRACK), _arrays(kd, mesh, cache))
