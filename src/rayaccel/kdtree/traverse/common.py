"""What every kd traversal shares: the memoised trace layout and the split-plane step.

The step at an inner node (:func:`split_segments`): the split plane's distance, the near
and far child, whether the ray's segment ``[tn, tf]`` reaches each, and each child's
part of it.
"""

from __future__ import annotations

from typing import Any

from rayaccel._jit import cpu_inline
from rayaccel.kdtree.layouts.kdtree import KdTraceLayout, KdTree, trace_layout
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.run import memoised_layout


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


def descend_py(node_f, node_i, node, tn, tf, ox, oy, oz, ix, iy, iz, side_mask, pad):
    """Descend from ``node`` to the leaf containing ``t = tn``; return it and its exit.

    At each inner node the near child is taken when ``tn <= t_split + pad`` (its exit
    becomes ``min(tf, t_split)``), else the far child: of two cells meeting within
    the culling pad of ``t``, the nearer one, so no cell the ray passes within
    rounding of is skipped. A ray in the split plane goes to the upper child when bit
    ``axis`` of ``side_mask`` is set. Returns ``(leaf node, exit, axes of planes the
    ray lies in, nodes visited)``.
    """
    in_plane = 0
    n_nodes = 1
    bits = node_i[node, 1]
    axis = bits & 3
    while axis != 3:
        child = bits >> 2
        ts, inv = split_distance(axis, node_f[node, 0], ox, oy, oz, ix, iy, iz)
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
        bits = node_i[node, 1]
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


split_distance = cpu_inline(split_distance_py)
descend = cpu_inline(descend_py)
split_segments = cpu_inline(split_segments_py)
