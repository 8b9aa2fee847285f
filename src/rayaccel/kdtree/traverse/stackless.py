"""The stackless kd traversals' shared per-ray body (restart, backtrack, short stack, ropes).

kd-restart, kd-backtrack and the short stack visit the leaves in exactly the order
of ``kdtree.stack`` (the same padded segments, the near child first, a ray in a
split plane into both children) without keeping the far children. Where the stack
would pop, they find the next subtree again:

``METHOD_RESTART`` (Foley & Sugerman 2005, kd-restart)
    descend again from the root.
``METHOD_BACKTRACK`` (Foley & Sugerman 2005, kd-backtrack)
    walk up the parent links to the pending node and recompute its segment from its
    box (node boxes: 24 bytes per node; ``backtracks`` counts the links followed).
``METHOD_SHORT_STACK`` (Horn et al. 2007)
    pop a ring of the ``size`` most recent far children (a push onto a full ring
    drops the oldest); when it is empty, descend again from the push-down root, the
    first node on the path with two children to visit (all above it have one).

Which subtree is pending is not kept as a ``t`` to restart from, as Foley &
Sugerman do, but as one bit per level (the restart trail of Laine 2010): bit
``k`` set means "the near child at depth ``k`` is done". A ``t``-based restart
skips cells the ray crosses within rounding (the leaf's exit equals the split
distance of the next cell): the thesis's KD_restart did not finish on two scenes,
and a first version of ours missed hits at grid vertices. With the trail, a descent
goes near at a depth whose bit is clear and far where it is set, and after each
leaf the deepest clear bit of a two-child node is set and the bits below it
cleared; the trail grows in the path order, so every ray ends after at most one
descent per leaf (tested), and the hits are ``kdtree.stack``'s bit for bit.
Subtrees whose segment begins beyond the closest hit (plus the culling pad) are
skipped, as the stack skips such entries.

``METHOD_ROPES`` (Popov et al. 2007)
    walks from leaf to leaf through the rope of the face the ray leaves by
    (:func:`rope_walk`). The leaf's box gives the exit distance and face; the walk
    descends from the rope to the cell holding the exit point (of two cells meeting
    within the culling pad of it, the nearer one,
    :func:`~rayaccel.kdtree.traverse.common.descend`). One rope leads to one cell, so
    where the ray leaves through an edge or a corner (two or more faces within the
    culling pad, :func:`rope_exit`) the cells around it that it touches without
    crossing are not on the walk, and a triangle touching that edge may be listed
    only there (or only beyond a null rope on the scene boundary): there the walk
    visits the leaves ``kdtree.stack`` visits for a window of a few pads around the
    exit, by kd-restart (:func:`trail_walk`), then goes on by the rope. It stops on
    a null rope, once the next cell begins beyond the closest hit (plus the pad) or
    beyond the end of the segment (a cell beginning exactly there is still visited),
    or at the first hit of an any-hit query. A ray lying in a split plane follows the
    lower side of such planes first, then once per combination of sides of their
    axes. A safety cap of four steps per leaf reports an overflow instead of looping.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.dtypes import FloatArray, IntArray
from rayaccel.kdtree.layouts.kdtree import NODE_BYTES, KdTraceLayout
from rayaccel.kdtree.traverse.common import (
    descend,
    leaf_hits,
    next_pending,
    node_bits,
    node_split,
    root_segment,
    split_segments,
    store_leaf_counts,
)
from rayaccel.kdtree.traverse.common import make_scratch as make_scratch
from rayaccel.queries import QUERY_ANY
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.run import body_kernels
from rayaccel.trace.skeleton import store_backtracks, store_counts, store_hit

INF32 = np.float32(np.inf)
_BOX_BYTES = 24

METHOD_RESTART = 0
METHOD_BACKTRACK = 1
METHOD_SHORT_STACK = 2
METHOD_ROPES = 3


class StacklessArrays(NamedTuple):
    """The trace layout plus what one method needs (empty arrays for the others)."""

    node_f: FloatArray
    node_i: IntArray
    leaf_index: IntArray  # (n,) each leaf node's leaf, which names its ropes (ropes), or (1,)
    tri: FloatArray
    tri_prim: IntArray
    root_box: FloatArray
    node_box: FloatArray  # (n, 6) interleaved cells (backtrack) or (n_leaves, 6) (ropes)
    link: IntArray  # (n,) parents (backtrack) or (n_leaves, 6) ropes flattened (ropes)
    ring_size: IntArray  # (1,) the short stack's ring entries (1..STACK_SIZE)
    method: IntArray  # (1,) the METHOD_* constant the walk follows


def stackless_arrays(
    layout: KdTraceLayout,
    box: FloatArray | None = None,
    link: IntArray | None = None,
    ring_size: int = 1,
    method: int = METHOD_RESTART,
    leaf_index: IntArray | None = None,
) -> StacklessArrays:
    """Return the kernel argument: ``layout``'s arrays plus boxes, links, ring size and method.

    The ring size and the method are array entries rather than compile-time constants,
    so one kernel serves every ring size and every trail method (kd-restart,
    kd-backtrack, short stack); the ropes have a kernel of their own.
    """
    t = layout.arrays()
    return StacklessArrays(
        t.node_f, t.node_i, np.zeros(1, np.int32) if leaf_index is None else leaf_index,
        t.tri, t.tri_prim, t.root_box,
        np.zeros((1, 6), np.float32) if box is None else box,
        np.zeros(1, np.int32) if link is None else link,
        np.array([ring_size], np.int32),
        np.array([method], np.int32),
    )  # fmt: skip


def box_exit_py(box, row, ox, oy, oz, ix, iy, iz, fx, fy, fz):
    """Return ``(exit distance, exit axis)`` of interleaved box ``row`` (NaN ignored, no pad)."""
    t_x = (box[row, fx] - ox) * ix
    t_y = (box[row, fy] - oy) * iy
    t_z = (box[row, fz] - oz) * iz
    leave = INF32
    axis = -1
    if t_x < leave:
        leave = t_x
        axis = 0
    if t_y < leave:
        leave = t_y
        axis = 1
    if t_z < leave:
        leave = t_z
        axis = 2
    return leave, axis


box_exit = cpu_inline(box_exit_py)


def box_enter_py(box, row, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, t_entry, t_exit, pad):
    """Return where the ray's padded segment enters interleaved box ``row``, at least ``t_entry``.

    (``t_exit`` and the far offsets are unused; the signature mirrors the slab tests.)
    """
    _ = (t_exit, fx, fy, fz)
    t_x = (box[row, nx] - ox) * ix
    t_y = (box[row, ny] - oy) * iy
    t_z = (box[row, nz] - oz) * iz
    enter = t_entry
    if t_x - pad > enter:
        enter = t_x - pad
    if t_y - pad > enter:
        enter = t_y - pad
    if t_z - pad > enter:
        enter = t_z - pad
    return enter


box_enter = cpu_inline(box_enter_py)


def rope_exit_py(box, link, leaf, ox, oy, oz, ix, iy, iz, fx, fy, fz, pad):
    """Return ``(exit, rope, corner)`` of leaf ``leaf``.

    The ray leaves through the nearest far face (NaN ignored; exact ties: x, then y,
    then z): ``exit`` is its distance (``inf`` when no face is crossed) and ``rope``
    its rope (-1: the scene boundary). ``corner`` is True when the ray leaves through
    an edge or a corner within the culling pad: two or more faces within ``2·pad`` of
    the nearest, one of them with a rope, so cells around it that the ray touches
    without crossing may hold a triangle touching that edge (:func:`trail_walk`).
    """
    t_x = (box[leaf, fx] - ox) * ix
    t_y = (box[leaf, fy] - oy) * iy
    t_z = (box[leaf, fz] - oz) * iz
    up_x = 1 if ix >= 0 else 0
    up_y = 3 if iy >= 0 else 2
    up_z = 5 if iz >= 0 else 4
    leave = INF32
    face = -1
    if t_x < leave:
        leave = t_x
        face = up_x
    if t_y < leave:
        leave = t_y
        face = up_y
    if t_z < leave:
        leave = t_z
        face = up_z
    if face < 0:
        return leave, -1, False
    limit = leave + 2 * pad
    n_near = 0
    open_near = False
    if t_x <= limit:
        n_near += 1
        open_near |= link[6 * leaf + up_x] >= 0
    if t_y <= limit:
        n_near += 1
        open_near |= link[6 * leaf + up_y] >= 0
    if t_z <= limit:
        n_near += 1
        open_near |= link[6 * leaf + up_z] >= 0
    return leave, link[6 * leaf + face], n_near > 1 and open_near


rope_exit = cpu_inline(rope_exit_py)


def trail_walk_py(
    kd, method, ring, size, t_entry, t_exit, box_ray, tri_ray, t_lo, t_hit, pad,
    best_prim, best_u, best_v, stop_at_first, with_stats,
):  # fmt: skip
    """Visit the leaves ``kdtree.stack`` visits for the segment ``[t_entry, t_exit]``.

    The walk of ``METHOD_RESTART``, ``METHOD_BACKTRACK`` and ``METHOD_SHORT_STACK``
    (``method``, read from the layout at run time; see the module docstring): descend by the
    restart trail, test the leaf, take the deepest pending level and find its subtree
    again. ``ring`` is the short stack's ring (node, segment start, segment end) of
    ``size`` entries, unused by the other methods. Also the rope walk's answer to an
    edge or a corner (:func:`rope_walk_py`): kd-restart over a window of a few pads, so
    every cell the ray touches there (within the pad) is tested. ``box_ray`` is the
    ray's ``(ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz)`` and ``tri_ray`` its
    ``(okx, oky, okz, kx, ky, kz, Sx, Sy, Sz)`` (:func:`rayaccel.trace.ray_setup.ray_start`;
    as tuples, since a call of more than 30 arguments compiles to a ``*args`` call that
    numba cannot inline). Returns ``(t_hit, prim, u, v, nodes, leaves, empty leaves,
    triangle tests, restarts, backtracks, stack peak, bytes)``, the counters 0 unless
    ``with_stats``.
    """
    ring_node, ring_tn, ring_tf = ring
    ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz = box_ray
    okx, oky, okz, kx, ky, kz, Sx, Sy, Sz = tri_ray
    node_f = kd.node_f
    node_i = kd.node_i
    n_nodes = n_leaves = n_empty = n_prim = n_restarts = n_back = peak = n_bytes = 0
    box_hi = t_hit + pad
    trail = np.int64(0)
    branch = np.int64(0)
    node = 0
    level = 0
    tn = t_entry
    tf = t_exit
    n_ring = 0
    head = 0
    push_node = 0
    push_level = 0
    push_tn = t_entry
    push_tf = t_exit
    push_set = False
    while True:
        # ---- descend from (node, level, [tn, tf]) by the trail
        pruned = False
        while True:
            if with_stats:
                n_nodes += 1
                n_bytes += NODE_BYTES
            if tn > box_hi:
                pruned = True
                break
            bits = node_bits(node_i, node)
            axis = bits & 3
            if axis == 3:
                break
            near, far, near_needed, far_needed, near_tf, far_tn = split_segments(
                bits, node_split(node_f, node), tn, tf, pad, ox, oy, oz, ix, iy, iz
            )
            if near_needed and far_needed:
                if method == METHOD_SHORT_STACK and not push_set:
                    # The push-down root: the first node with two children.
                    push_set = True
                    push_node = node
                    push_level = level
                    push_tn = tn
                    push_tf = tf
                if (trail >> level) & 1:
                    node = far
                    tn = far_tn
                else:
                    branch |= np.int64(1) << level
                    if method == METHOD_SHORT_STACK:
                        ring_node[head] = far
                        ring_tn[head] = far_tn
                        ring_tf[head] = tf
                        head = head + 1 if head + 1 < size else 0
                        if n_ring < size:
                            n_ring += 1
                        if with_stats:
                            peak = max(peak, n_ring)
                    node = near
                    tf = near_tf
            elif near_needed:
                node = near
                tf = near_tf
            elif far_needed:
                node = far
                tn = far_tn
            else:
                pruned = True
                break
            level += 1
        if not pruned:
            t_hit, best_prim, best_u, best_v, box_hi, n_leaves, n_empty, n_prim, n_bytes = (
                leaf_hits(
                    kd, node, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo,
                    t_hit, pad, best_prim, best_u, best_v, stop_at_first,
                    n_leaves, n_empty, n_prim, n_bytes, with_stats,
                )
            )  # fmt: skip
            if stop_at_first and best_prim >= 0:
                break
        # ---- pop: the deepest level whose second child is pending
        if branch == 0:
            break
        trail, branch, k = next_pending(trail, branch, level)
        if method == METHOD_SHORT_STACK and n_ring > 0:
            head = head - 1 if head > 0 else size - 1
            n_ring -= 1
            node = ring_node[head]
            tn = ring_tn[head]
            tf = ring_tf[head]
            level = k + 1
        elif method == METHOD_BACKTRACK:
            # Walk up to the level-k node; its segment from its box.
            while level > k:
                node = kd.link[node]
                level -= 1
                if with_stats:
                    n_back += 1
                    n_bytes += _BOX_BYTES
            tn = box_enter(
                kd.node_box, node, ox, oy, oz, ix, iy, iz,
                nx, ny, nz, fx, fy, fz, t_entry, t_exit, pad,
            )  # fmt: skip
            tf, _a = box_exit(kd.node_box, node, ox, oy, oz, ix, iy, iz, fx, fy, fz)
            tf = tf + pad
            if t_exit < tf:
                tf = t_exit
            if with_stats:
                n_restarts += 1
        else:
            if method == METHOD_SHORT_STACK:
                node = push_node
                level = push_level
                tn = push_tn
                tf = push_tf
            else:
                node = 0
                level = 0
                tn = t_entry
                tf = t_exit
            if with_stats:
                n_restarts += 1
    return (
        t_hit, best_prim, best_u, best_v, n_nodes, n_leaves, n_empty, n_prim, n_restarts,
        n_back, peak, n_bytes,
    )  # fmt: skip


trail_walk = cpu_inline(trail_walk_py)


def rope_walk_py(
    kd, ring, t_entry, t_exit, box_ray, tri_ray, t_lo, t_hit, pad,
    best_prim, best_u, best_v, stop_at_first, n_leaf_total,
):  # fmt: skip
    """Walk the leaves along the ray by their ropes (Popov et al. 2007); see the module docstring.

    ``ring``, ``box_ray`` and ``tri_ray`` as for :func:`trail_walk_py` (the windows'
    kd-restart leaves the ring unused).

    Returns ``(t_hit, prim, u, v, overflowed, nodes, leaves, empty leaves, triangle
    tests, rope steps, bytes)``.
    """
    ox, oy, oz, ix, iy, iz, _nx, _ny, _nz, fx, fy, fz = box_ray
    okx, oky, okz, kx, ky, kz, Sx, Sy, Sz = tri_ray
    n_nodes = 0
    n_leaves = 0
    n_empty = 0
    n_prim = 0
    n_rope = 0
    n_bytes = 0
    overflowed = 0
    box_hi = t_hit + pad
    mask = 0 if t_entry != INF32 else -1
    done_masks = 0
    in_plane = 0
    # The end of the last window: an edge or a corner within it needs no other.
    window_end = -INF32
    finished = False
    while mask >= 0 and not finished:
        t = t_entry
        start = 0
        n_walk = 0
        while True:
            leaf_node, _tf, seen, n_desc = descend(
                kd.node_f, kd.node_i, start, t, t_exit, ox, oy, oz, ix, iy, iz, mask, pad
            )
            in_plane |= seen
            n_nodes += n_desc
            n_bytes += NODE_BYTES * n_desc
            leaf = kd.leaf_index[np.uint64(leaf_node)]
            t_hit, best_prim, best_u, best_v, box_hi, n_leaves, n_empty, n_prim, n_bytes = (
                leaf_hits(
                    kd, leaf_node, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
                    best_prim, best_u, best_v, stop_at_first, n_leaves, n_empty, n_prim,
                    n_bytes, True,
                )
            )  # fmt: skip
            n_bytes += _BOX_BYTES
            if stop_at_first and best_prim >= 0:
                finished = True
                break
            leave, rope, corner = rope_exit(
                kd.node_box, kd.link, leaf, ox, oy, oz, ix, iy, iz, fx, fy, fz, pad
            )
            # The next cell begins at ``leave``: needed up to the closest hit plus the
            # pad, and up to the end of the segment inclusive (a hit on it counts).
            if leave > box_hi or leave > t_exit:
                break
            if corner and leave > window_end:
                # An edge or a corner: every cell around it, as the stack visits them.
                w0 = leave - 2 * pad
                if w0 < t_entry:
                    w0 = t_entry
                w1 = leave + 2 * pad
                if w1 > t_exit:
                    w1 = t_exit
                window_end = w1
                (
                    t_hit, best_prim, best_u, best_v, w_nodes, w_leaves, w_empty, w_prim,
                    _w_restarts, _w_back, _w_peak, w_bytes,
                ) = trail_walk(
                    kd, METHOD_RESTART, ring, 0, w0, w1, box_ray, tri_ray, t_lo, t_hit, pad,
                    best_prim, best_u, best_v, stop_at_first, True,
                )  # fmt: skip
                box_hi = t_hit + pad
                n_nodes += w_nodes
                n_leaves += w_leaves
                n_empty += w_empty
                n_prim += w_prim
                n_bytes += w_bytes
                if stop_at_first and best_prim >= 0:
                    finished = True
                    break
                if leave > box_hi:
                    break
            if rope < 0:
                break
            n_walk += 1
            if n_walk > 4 * n_leaf_total + 8:
                overflowed = 1
                finished = True
                break
            n_rope += 1
            start = rope
            if leave > t:
                t = leave
        done_masks |= 1 << mask
        mask = -1
        if not finished:
            for m in range(8):
                if (m & ~in_plane) == 0 and not (done_masks >> m) & 1:
                    mask = m
                    break
    return (
        t_hit, best_prim, best_u, best_v, overflowed, n_nodes, n_leaves, n_empty, n_prim,
        n_rope, n_bytes,
    )  # fmt: skip


rope_walk = cpu_inline(rope_walk_py)


@functools.cache
def _body(ropes: bool) -> Any:
    """Return the per-chunk body of the rope walk, or of the trail walk of the layout's method."""

    def trace_rays_py(
        kd, scratch, origin, direction, tmin, tmax, begin, end,
        hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
    ):  # fmt: skip
        _ = ropes
        method = kd.method[0]
        size = np.int64(kd.ring_size[0])
        n_leaf_total = kd.node_box.shape[0]  # the ropes' leaf boxes (read by the rope walk)
        n_overflowed = 0
        for r in range(begin, end):
            overflowed = n_steps = n_nodes = n_leaves = n_empty = n_prim = n_restarts = 0
            n_back = n_rope = peak = n_bytes = 0
            (
                valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
                _box_lo, box_hi, entry, best_prim, best_u, best_v,
            ) = ray_start(origin, direction, tmin, tmax, r, kd.root_box)  # fmt: skip
            if valid:
                t_entry, t_exit = root_segment(
                    kd.root_box, ox, oy, oz, ix, iy, iz, fx, fy, fz, entry, box_hi
                )
                box_ray = (ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz)
                tri_ray = (okx, oky, okz, kx, ky, kz, Sx, Sy, Sz)
                if ropes:
                    (
                        t_hit, best_prim, best_u, best_v, overflowed, n_nodes, n_leaves,
                        n_empty, n_prim, n_rope, n_bytes,
                    ) = rope_walk(
                        kd, scratch, t_entry, t_exit, box_ray, tri_ray, t_lo, t_hit, pad,
                        best_prim, best_u, best_v, query == QUERY_ANY, n_leaf_total,
                    )  # fmt: skip
                    n_steps = n_nodes
                elif t_entry != INF32:
                    (
                        t_hit, best_prim, best_u, best_v, n_nodes, n_leaves, n_empty, n_prim,
                        n_restarts, n_back, peak, n_bytes,
                    ) = trail_walk(
                        kd, method, scratch, size, t_entry, t_exit, box_ray, tri_ray,
                        t_lo, t_hit, pad, best_prim, best_u, best_v, query == QUERY_ANY,
                        with_stats,
                    )  # fmt: skip
                    n_steps = n_nodes
            if with_stats:
                # The scene box is the one box test.
                store_counts(counters, r, n_steps, n_nodes, int(valid), n_prim, peak, n_bytes)
                store_leaf_counts(counters, r, n_leaves, n_empty, n_rope)
                store_backtracks(counters, r, n_restarts, n_back, 0, (0, 0, 0, 0))
            store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
            n_overflowed += overflowed
        return n_overflowed

    return cpu_inline(trace_rays_py)


@functools.cache
def trace_kernel(method: int) -> Any:
    """Return ``kernel_for(query, with_stats, parallel)`` of one method.

    Every method but the ropes shares one compiled kernel (:func:`stackless_arrays`).
    """
    return body_kernels(make_scratch, _body(method == METHOD_ROPES))
