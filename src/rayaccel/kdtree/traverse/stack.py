"""``kdtree.stack``: front-to-back kd-tree traversal with a stack (Slusallek's lecture).

Per node the ray's segment ``[t_near, t_far]`` is cut at ``t_split``: the near
child (by the sign of the direction, ``order="direction"``) gets
``[t_near, t_split]`` and the far child ``[t_split, t_far]``; a child whose part is
empty is skipped, and when both are needed the far one is pushed with its segment.
Comparisons use the culling pad (:func:`rayaccel.kernels.aabb.culling_pad`) on both
sides of ``t_split``, so a triangle touching the plane (listed on one side only) is
found whichever side the ray meets it from; a ray lying in the plane (``t_split``
NaN) visits both children.

Early termination: a hit beyond the current leaf is kept (triangles are not clipped
to cells), and a popped entry is skipped when its segment begins beyond the closest
hit, so the traversal stops as soon as the hit lies in front of every remaining cell
— exactly the leaf-interval rule of the thesis's Figure 3.21, with the hit already
found when its own leaf comes up.

``order="position"`` (the thesis's KD_positional) visits first the child that holds
the ray origin, which differs from the direction order only when the ray starts
beyond the plane moving away from it.

Counters (``with_stats``): ``steps`` loop iterations, ``nodes`` nodes visited,
``leaves`` and ``empty_leaves``, ``box_tests`` (the scene box), ``prim_tests``,
``stack_peak``, ``bytes`` (8 per node, 40 per triangle and reference, 12 per stack
push and pop).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.errors import InvalidInputError
from rayaccel.kdtree.layouts.kdtree import NODE_BYTES, STACK_SIZE, KdTree
from rayaccel.kdtree.traverse.common import (
    kd_trace_layout,
    leaf_hits,
    node_bits,
    node_split,
    root_segment,
    split_segments,
    store_leaf_counts,
)
from rayaccel.kdtree.traverse.common import make_scratch as make_scratch
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels
from rayaccel.trace.skeleton import store_counts, store_hit

INF32 = np.float32(np.inf)
_STACK_ENTRY_BYTES = 12
ORDER_DIRECTION = 0
ORDER_POSITION = 1
_ORDERS = {"direction": ORDER_DIRECTION, "position": ORDER_POSITION}


@dataclass(frozen=True, slots=True)
class KdStackOptions:
    """Options of ``kdtree.stack``.

    Attributes
    ----------
    order : {"direction", "position"}
        Which child comes first: the near one by the direction's sign, or the one
        holding the ray origin (the thesis's KD_positional).
    """

    order: str = "direction"

    def __post_init__(self) -> None:
        if self.order not in _ORDERS:
            raise InvalidInputError(f"order must be one of {sorted(_ORDERS)}, got {self.order!r}")


@functools.cache
def _body(order: int) -> Any:
    """Return the per-chunk body for one child order (a compile-time constant)."""

    def trace_rays_py(
        kd, scratch, origin, direction, tmin, tmax, begin, end,
        hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
    ):  # fmt: skip
        _ = order
        stack_node, stack_tn, stack_tf = scratch
        node_f = kd.node_f
        node_i = kd.node_i
        n_overflowed = 0
        for r in range(begin, end):
            overflowed = n_steps = n_nodes = n_leaves = n_empty = n_prim = peak = n_bytes = 0
            (
                valid, ox, oy, oz, ix, iy, iz, _nx, _ny, _nz, fx, fy, fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
                _box_lo, box_hi, entry, best_prim, best_u, best_v,
            ) = ray_start(origin, direction, tmin, tmax, r, kd.root_box)  # fmt: skip
            if valid:
                tn, tf = root_segment(
                    kd.root_box, ox, oy, oz, ix, iy, iz, fx, fy, fz, entry, box_hi
                )
                node = 0
                sp = 0
                done = tn == INF32
                while not done:
                    if with_stats:
                        n_steps += 1
                        n_nodes += 1
                        n_bytes += NODE_BYTES
                    bits = node_bits(node_i, node)
                    axis = bits & 3
                    if axis != 3:
                        split = node_split(node_f, node)
                        near, far, near_needed, far_needed, near_tf, far_tn = split_segments(
                            bits, split, tn, tf, pad, ox, oy, oz, ix, iy, iz
                        )
                        if near_needed and far_needed:
                            if sp == STACK_SIZE:
                                overflowed = 1
                                break
                            if with_stats:
                                n_bytes += _STACK_ENTRY_BYTES
                                peak = max(peak, sp + 1)
                            first_far = False
                            if order == ORDER_POSITION:
                                if axis == 0:
                                    o_a = ox
                                elif axis == 1:
                                    o_a = oy
                                else:
                                    o_a = oz
                                # The child holding the origin first (a tie: by direction).
                                if near < far:
                                    first_far = o_a > split
                                else:
                                    first_far = o_a < split
                            # Push one child with its segment, go on into the other.
                            if first_far:
                                pushed, pushed_tn, pushed_tf = near, tn, near_tf
                                node, tn = far, far_tn
                            else:
                                pushed, pushed_tn, pushed_tf = far, far_tn, tf
                                node, tf = near, near_tf
                            # Unsigned slots: no wraparound (common.node_bits).
                            slot = np.uint64(sp)
                            stack_node[slot] = pushed
                            stack_tn[slot] = pushed_tn
                            stack_tf[slot] = pushed_tf
                            sp += 1
                            continue
                        if near_needed:
                            node = near
                            tf = near_tf
                            continue
                        if far_needed:
                            node = far
                            tn = far_tn
                            continue
                    else:
                        (
                            t_hit, best_prim, best_u, best_v, box_hi,
                            n_leaves, n_empty, n_prim, n_bytes,
                        ) = leaf_hits(
                            kd, node, okx, oky, okz, kx, ky, kz,
                            Sx, Sy, Sz, t_lo, t_hit, pad, best_prim, best_u, best_v,
                            query == QUERY_ANY, n_leaves, n_empty, n_prim, n_bytes, with_stats,
                        )  # fmt: skip
                        if query == QUERY_ANY and best_prim >= 0:
                            break
                    # Pop the next entry that begins in front of the closest hit.
                    done = True
                    while sp > 0:
                        sp -= 1
                        if with_stats:
                            n_bytes += _STACK_ENTRY_BYTES
                        slot = np.uint64(sp)
                        if stack_tn[slot] <= box_hi:
                            node = stack_node[slot]
                            tn = stack_tn[slot]
                            tf = stack_tf[slot]
                            if box_hi < tf:
                                tf = box_hi
                            done = False
                            break
            if with_stats:
                # The scene box is the one box test.
                store_counts(counters, r, n_steps, n_nodes, int(valid), n_prim, peak, n_bytes)
                store_leaf_counts(counters, r, n_leaves, n_empty, 0)
            store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
            n_overflowed += overflowed
        return n_overflowed

    return cpu_inline(trace_rays_py)


@functools.cache
def trace_kernel(order: int) -> Any:
    """Return ``kernel_for(query, with_stats, parallel)`` for one child order."""
    return body_kernels(make_scratch, _body(order))


@register_traversal("kdtree.stack", default=True)
def trace_kdtree_stack(
    kd: KdTree, mesh: TriangleMesh, options: KdStackOptions, cache: LayoutCache
) -> TracePlan:
    """Front-to-back kd-tree traversal with a stack (closest and any hit).

    Trace rays through a kd-tree front to back with a stack.

    References
    ----------
    Slusallek, kd-tree traversal (lecture); Havran 2000, Heuristic Ray Shooting Algorithms.
    """
    layout = kd_trace_layout(kd, mesh, cache)
    return TracePlan(
        trace_kernel(_ORDERS[options.order]), layout.arrays(), "the tree is deeper than MAX_DEPTH"
    )
