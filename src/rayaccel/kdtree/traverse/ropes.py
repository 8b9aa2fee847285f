"""``kdtree.ropes``: stackless traversal along the ropes of the leaf faces (Popov et al. 2007).

Each leaf keeps its box and six ropes, one per face: the node on the other side of
that face (null on the scene boundary). They are made in a post-pass
(:func:`rope_layout`): the root's ropes are null; a child inherits its parent's,
except across the split plane, where the rope is its sibling. With
``optimize=True`` each rope then descends while it is an inner node: to its child
adjacent to the face when it splits the face's axis, or to the child on the side
that holds the whole face, so the walk enters smaller subtrees (the thesis found
this hurt its packet version's coherence). After a leaf, the ray leaves through the
face of the nearest exit distance and descends from that face's rope; where it
leaves through an edge or a corner, the cells around it are visited as the stack
visits them (:mod:`rayaccel.kdtree.traverse.stackless`). Counters: those of
``kdtree.stack`` plus ``rope_steps``. ``info()`` of the accel counts the leaf boxes
and ropes in ``bytes`` (48 bytes per leaf, and 4 per node for the index that finds
a leaf node's box and ropes: the trace layout's leaves carry their triangle range
in place of their index).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_kernel
from rayaccel.dtypes import INDEX, REAL
from rayaccel.kdtree.layouts.kdtree import LEAF_AXIS, KdTree
from rayaccel.kdtree.traverse.common import kd_trace_layout
from rayaccel.kdtree.traverse.stackless import METHOD_ROPES, stackless_arrays, trace_kernel
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import memoised_layout


@dataclass(frozen=True, slots=True)
class KdRopesOptions:
    """Options of ``kdtree.ropes``.

    Attributes
    ----------
    optimize : bool
        Push each rope down to the smallest subtree that still covers its face.
    """

    optimize: bool = True


@dataclass(frozen=True, slots=True, eq=False)
class KdRopes:
    """Leaf boxes (interleaved lo/hi) and six ropes per leaf (face ``2·axis + upper``)."""

    leaf_box: np.ndarray  # (n_leaves, 6) float32
    leaf_rope: np.ndarray  # (n_leaves * 6,) int32 node ids, -1 null
    leaf_index: np.ndarray  # (n_nodes,) int32: a leaf node's leaf (its box and ropes), else -1

    def nbytes(self) -> int:
        """Return the size in bytes of the leaf boxes, the ropes and the leaf index."""
        return int(self.leaf_box.nbytes + self.leaf_rope.nbytes + self.leaf_index.nbytes)


@cpu_kernel()
def _make_ropes(node_split, node_bits, lo, hi, optimize, node_rope, leaf_box, leaf_rope):
    """Fill the ropes of every node top-down (children follow their parent), then the leaves'."""
    n = node_bits.shape[0]
    for f in range(6):
        node_rope[0, f] = -1
    for i in range(n):
        bits = node_bits[i]
        axis = bits & 3
        if axis == LEAF_AXIS:
            leaf = bits >> 2
            for a in range(3):
                leaf_box[leaf, 2 * a] = lo[i, a]
                leaf_box[leaf, 2 * a + 1] = hi[i, a]
            for f in range(6):
                rope = node_rope[i, f]
                if optimize:
                    # Descend while an inner node's children split the face or one holds it.
                    fa = f // 2
                    upper_face = f % 2 == 1
                    while rope >= 0:
                        rb = node_bits[rope]
                        ra = rb & 3
                        if ra == LEAF_AXIS:
                            break
                        rc = rb >> 2
                        rs = node_split[rope]
                        if ra == fa:
                            rope = rc if upper_face else rc + 1
                        elif hi[i, ra] <= rs:
                            rope = rc
                        elif lo[i, ra] >= rs:
                            rope = rc + 1
                        else:
                            break
                leaf_rope[6 * leaf + f] = rope
            continue
        child = bits >> 2
        for c in range(2):
            for f in range(6):
                node_rope[child + c, f] = node_rope[i, f]
        node_rope[child, 2 * axis + 1] = child + 1
        node_rope[child + 1, 2 * axis] = child


def rope_layout(kd: KdTree, optimize: bool) -> KdRopes:
    """Derive the leaf boxes and ropes of ``kd`` (see the module docstring)."""
    lo, hi, _, _ = kd.cells()
    node_rope = np.empty((kd.n_nodes, 6), dtype=INDEX)
    leaf_box = np.empty((kd.n_leaves, 6), dtype=REAL)
    leaf_rope = np.empty(kd.n_leaves * 6, dtype=INDEX)
    _make_ropes(
        np.ascontiguousarray(kd.node_split), np.ascontiguousarray(kd.node_bits), lo, hi,
        bool(optimize), node_rope, leaf_box, leaf_rope,
    )  # fmt: skip
    bits = kd.node_bits
    leaf_index = np.where((bits & 3) == LEAF_AXIS, bits >> 2, -1).astype(INDEX)
    return KdRopes(leaf_box, leaf_rope, leaf_index)


@register_traversal("kdtree.ropes")
def trace_kdtree_ropes(
    kd: KdTree, mesh: TriangleMesh, options: KdRopesOptions, cache: LayoutCache
) -> TracePlan:
    """Stackless traversal along leaf-face ropes (leaf boxes, optional rope optimisation).

    Trace rays through a kd-tree along its ropes.

    References
    ----------
    Popov, Günther, Seidel, Slusallek 2007, Stackless KD-Tree Traversal for High Performance GPU Ray
    Tracing.
    """
    name = "kdtree.ropes" if options.optimize else "kdtree.ropes_plain"
    ropes = memoised_layout(cache, name, lambda: rope_layout(kd, options.optimize))
    arrays = stackless_arrays(
        kd_trace_layout(kd, mesh, cache), ropes.leaf_box, ropes.leaf_rope,
        method=METHOD_ROPES, leaf_index=ropes.leaf_index,
    )  # fmt: skip
    return TracePlan(trace_kernel(METHOD_ROPES), arrays)
