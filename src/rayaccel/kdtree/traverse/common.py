"""What every kd traversal shares: the memoised trace layout and the per-ray steps.

The ray's segment through the scene box (:func:`root_segment`); the step at an inner
node (:func:`split_segments`): the split plane's distance, the near and far child,
whether the ray's segment ``[tn, tf]`` reaches each, and each child's part of it; the
triangle test of a leaf with its counters (:func:`leaf_hits`); the next pending level
of a restart trail (:func:`next_pending`); and the store of the kd counters
(:func:`store_leaf_counts`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.counters import Counter
from rayaccel.kdtree.layouts.kdtree import (
    REF_BYTES,
    STACK_SIZE,
    TRIANGLE_BYTES,
    KdTraceLayout,
    KdTree,
    trace_layout,
)
from rayaccel.kernels.aabb import ray_box_exit
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.leaf import intersect_leaf
from rayaccel.trace.run import memoised_layout

_PRIM_BYTES = TRIANGLE_BYTES + REF_BYTES


def kd_trace_layout(kd: KdTree, mesh: TriangleMesh, cache: dict[str, Any] | None) -> KdTraceLayout:
    """Return the trace layout of ``kd``, memoised in ``cache`` when given."""
    return memoised_layout(cache, "kdtree.trace", lambda: trace_layout(kd, mesh.hit_rows()))


def split_distance_py(axis, split, ox, oy, oz, ix, iy, iz):
    """Return ``(t_split, inv)`` of the plane ``x[axis] = split`` (NaN: the ray lies in it)."""
    if axis == 0:
        return (split - ox) * ix, ix
    if axis == 1:
        return (split - oy) * iy, iy
    return (split - oz) * iz, iz


def node_bits_py(node_i, node):
    """Return the packed word (axis, child or leaf) of ``node`` from the flat int32 view.

    Read at the unsigned flat index ``2 node + 1``: numba then neither wraps a negative
    index nor multiplies by the row length, two steps fewer on the walk's chain from one
    node to the next (docs/performance.md, ``kdtree.stack``).
    """
    return node_i[np.uint64(2 * node + 1)]


def node_split_py(node_f, node):
    """Return the split position of inner node ``node`` from the flat float32 view."""
    return node_f[np.uint64(2 * node)]


def leaf_range_py(node_i, node):
    """Return ``(first, count)`` of leaf node ``node``: its two words in the trace layout.

    The trace layout's leaves carry their range themselves
    (:func:`rayaccel.kdtree.layouts.kdtree.nodes_with_leaf_ranges`), in the cache line
    the walk has just read for the node's bits.
    """
    return node_i[np.uint64(2 * node)], node_i[np.uint64(2 * node + 1)] >> 2


node_bits = cpu_inline(node_bits_py)
node_split = cpu_inline(node_split_py)
leaf_range = cpu_inline(leaf_range_py)


def descend_py(node_f, node_i, node, tn, tf, ox, oy, oz, ix, iy, iz, side_mask, pad):
    """Descend from ``node`` to the leaf containing ``t = tn``; return it and its exit.

    At each inner node the near child is taken when ``tn <= t_split + pad`` (its exit
    becomes ``min(tf, t_split)``), else the far child: of two cells meeting within
    the culling pad of ``t``, the nearer one, so no cell the ray passes within
    rounding of is skipped. A ray in the split plane goes to the upper child when bit
    ``axis`` of ``side_mask`` is set. ``node_f`` and ``node_i`` are the trace layout's
    flat views (:func:`node_bits`). Returns ``(leaf node, exit, axes of planes the ray
    lies in, nodes visited)``.
    """
    in_plane = 0
    n_nodes = 1
    bits = node_bits(node_i, node)
    axis = bits & 3
    while axis != 3:
        child = bits >> 2
        ts, inv = split_distance(axis, node_split(node_f, node), ox, oy, oz, ix, iy, iz)
        near = child if inv >= 0 else child + 1
        if tn <= ts + pad:
            node = near
            if ts < tf:
                tf = ts
        elif ts != ts:
            in_plane |= 1 << axis
            node = child + ((side_mask >> axis) & 1)
        else:
            node = 2 * child + 1 - near
        n_nodes += 1
        bits = node_bits(node_i, node)
        axis = bits & 3
    return node, tf, in_plane, n_nodes


def split_segments_py(bits, split, tn, tf, pad, ox, oy, oz, ix, iy, iz):
    """Return the children of the inner node ``bits`` and the segment each one needs.

    Returns ``(near, far, near_needed, far_needed, near_tf, far_tn)``: the near child
    holds ``[tn, near_tf]`` and is needed unless the split lies before ``tn - pad``, the
    far child holds ``[far_tn, tf]`` and is needed unless the split lies beyond ``tf +
    pad`` (the culling pad). A ray in the split plane (NaN distance) needs both, each
    for the whole segment.
    """
    child = bits >> 2
    ts, inv = split_distance(bits & 3, split, ox, oy, oz, ix, iy, iz)
    near = child if inv >= 0 else child + 1
    near_tf = ts + pad
    if not (near_tf < tf):
        near_tf = tf
    far_tn = ts - pad
    if not (far_tn > tn):
        far_tn = tn
    return near, 2 * child + 1 - near, not (ts < tn - pad), not (ts > tf + pad), near_tf, far_tn


def make_scratch_py(kd):
    """Return one worker's stack of (node, segment start, segment end), ``STACK_SIZE`` deep.

    ``kdtree.stack``'s stack, and the short stack's ring at its largest size (the
    other stackless walks leave it unused).
    """
    stack_node = np.empty(STACK_SIZE, dtype=np.int32)
    stack_tn = np.empty(STACK_SIZE, dtype=np.float32)
    stack_tf = np.empty(STACK_SIZE, dtype=np.float32)
    return stack_node, stack_tn, stack_tf


make_scratch = cpu_inline(make_scratch_py)


def root_segment_py(root_box, ox, oy, oz, ix, iy, iz, fx, fy, fz, t_entry, box_hi):
    """Return the ray's segment ``[t_entry, t_exit]`` through the scene box.

    ``t_entry`` is the root box's entry distance
    (:func:`rayaccel.trace.ray_setup.ray_start_py`); the exit is the box's
    (2-ulp enlarged), cut at the culling interval's end ``box_hi``.
    """
    t_exit = ray_box_exit(ox, oy, oz, ix, iy, iz, root_box[fx], root_box[fy], root_box[fz])
    if box_hi < t_exit:
        t_exit = box_hi
    return t_entry, t_exit


root_segment = cpu_inline(root_segment_py)


def leaf_hits_py(
    kd, node, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
    best_prim, best_u, best_v, stop_at_first, n_leaves, n_empty, n_prim, n_bytes, with_stats,
):  # fmt: skip
    """Test the triangles of leaf node ``node`` (its range: :func:`leaf_range`).

    Returns ``(t_hit, best_prim, best_u, best_v, box_hi, n_leaves, n_empty, n_prim,
    n_bytes)``: the hit as :func:`rayaccel.trace.leaf.intersect_leaf` leaves it, the
    culling interval's new end ``t_hit + pad``, and, with ``with_stats``, the leaf,
    empty leaf, triangle test and byte counters advanced by this leaf.
    """
    first, count = leaf_range(kd.node_i, node)
    tested = 0
    if count != 0:
        # An empty leaf skips the call: most leaves a ray reaches are empty.
        t_hit, best_prim, best_u, best_v, tested = intersect_leaf(
            kd.tri, kd.tri_prim, first, first + count, okx, oky, okz,
            kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, best_prim, best_u, best_v, stop_at_first,
        )  # fmt: skip
    if with_stats:
        n_leaves += 1
        if count == 0:
            n_empty += 1
        n_prim += tested
        n_bytes += _PRIM_BYTES * count
    return t_hit, best_prim, best_u, best_v, t_hit + pad, n_leaves, n_empty, n_prim, n_bytes


leaf_hits = cpu_inline(leaf_hits_py)


def next_pending_py(trail, branch, level):
    """Return ``(trail, branch, k)``: the deepest pending level ``k < level``, now taken.

    ``branch`` has bit ``k`` set where the node at depth ``k`` on the path has both
    children to visit and only the near one visited; the deepest such bit is cleared,
    and the trail gets bit ``k`` set ("near child done") and the bits below it cleared.
    ``branch`` must not be 0.
    """
    k = level - 1
    while not (branch >> k) & 1:
        k -= 1
    branch &= ~(np.int64(1) << k)
    trail = (trail & ((np.int64(1) << k) - 1)) | (np.int64(1) << k)
    return trail, branch, k


next_pending = cpu_inline(next_pending_py)


def store_leaf_counts_py(counters, r, leaves, empty_leaves, rope_steps):
    """Store the kd traversals' own counters of ray ``r`` (0 for one a traversal has not)."""
    counters[r, Counter.LEAVES] = leaves
    counters[r, Counter.EMPTY_LEAVES] = empty_leaves
    counters[r, Counter.ROPE_STEPS] = rope_steps


store_leaf_counts = cpu_inline(store_leaf_counts_py)


split_distance = cpu_inline(split_distance_py)
descend = cpu_inline(descend_py)
split_segments = cpu_inline(split_segments_py)
