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
from rayaccel._variant import register
from rayaccel.counters import Counter
from rayaccel.errors import InvalidInputError
from rayaccel.kdtree.layouts.kdtree import (
    NODE_BYTES,
    REF_BYTES,
    STACK_SIZE,
    TRIANGLE_BYTES,
    KdTree,
)
from rayaccel.kdtree.traverse.common import kd_trace_layout, split_segments
from rayaccel.kernels.aabb import ray_box_exit
from rayaccel.queries import QUERY_ANY
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.leaf import intersect_leaf
from rayaccel.trace.ray_setup import ray_prologue, root_entry
from rayaccel.trace.run import body_kernels, run_trace
from rayaccel.trace.skeleton import store_hit

INF32 = np.float32(np.inf)
ZERO32 = np.float32(0.0)
_PRIM_BYTES = TRIANGLE_BYTES + REF_BYTES
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


def make_scratch_py(kd):
    """Return one worker's stack: node, segment start and end."""
    stack_node = np.empty(STACK_SIZE, dtype=np.int32)
    stack_tn = np.empty(STACK_SIZE, dtype=np.float32)
    stack_tf = np.empty(STACK_SIZE, dtype=np.float32)
    return stack_node, stack_tn, stack_tf


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
            overflowed = 0
            n_steps = 0
            n_nodes = 0
            n_leaves = 0
            n_empty = 0
            n_prim = 0
            peak = 0
            n_bytes = 0
            (
                valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            ) = ray_prologue(origin, direction, tmin, tmax, r, kd.root_box)  # fmt: skip
            best_prim = -1
            best_u = ZERO32
            best_v = ZERO32
            if valid:
                box_lo = t_lo - pad
                box_hi = t_hit + pad
                root_box = kd.root_box
                tn = root_entry(
                    root_box, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, box_lo, box_hi
                )
                tf = ray_box_exit(ox, oy, oz, ix, iy, iz, root_box[fx], root_box[fy], root_box[fz])
                if box_hi < tf:
                    tf = box_hi
                node = 0
                sp = 0
                done = tn == INF32
                while not done:
                    if with_stats:
                        n_steps += 1
                        n_nodes += 1
                        n_bytes += NODE_BYTES
                    bits = node_i[node, 1]
                    axis = bits & 3
                    if axis != 3:
                        split = node_f[node, 0]
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
                            if first_far:
                                stack_node[sp] = near
                                stack_tn[sp] = tn
                                stack_tf[sp] = near_tf
                                sp += 1
                                node = far
                                tn = far_tn
                            else:
                                stack_node[sp] = far
                                stack_tn[sp] = far_tn
                                stack_tf[sp] = tf
                                sp += 1
                                node = near
                                tf = near_tf
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
                        leaf = bits >> 2
                        first = kd.leaf_first[leaf]
                        count = kd.leaf_count[leaf]
                        if with_stats:
                            n_leaves += 1
                            if count == 0:
                                n_empty += 1
                            n_bytes += _PRIM_BYTES * count
                        t_hit, best_prim, best_u, best_v, tested = intersect_leaf(
                            kd.tri, kd.tri_prim, first, first + count, okx, oky, okz,
                            kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, best_prim, best_u, best_v,
                            query == QUERY_ANY,
                        )  # fmt: skip
                        box_hi = t_hit + pad
                        if with_stats:
                            n_prim += tested
                        if query == QUERY_ANY and best_prim >= 0:
                            break
                    # Pop the next entry that begins in front of the closest hit.
                    done = True
                    while sp > 0:
                        sp -= 1
                        if with_stats:
                            n_bytes += _STACK_ENTRY_BYTES
                        if stack_tn[sp] <= box_hi:
                            node = stack_node[sp]
                            tn = stack_tn[sp]
                            tf = stack_tf[sp]
                            if box_hi < tf:
                                tf = box_hi
                            done = False
                            break
            if with_stats:
                counters[r, Counter.STEPS] = n_steps
                counters[r, Counter.NODES] = n_nodes
                counters[r, Counter.LEAVES] = n_leaves
                counters[r, Counter.EMPTY_LEAVES] = n_empty
                counters[r, Counter.BOX_TESTS] = 1 if valid else 0
                counters[r, Counter.PRIM_TESTS] = n_prim
                counters[r, Counter.STACK_PEAK] = peak
                counters[r, Counter.BYTES] = n_bytes
            store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
            n_overflowed += overflowed
        return n_overflowed

    return cpu_inline(trace_rays_py)


make_scratch = cpu_inline(make_scratch_py)


@functools.cache
def trace_kernel(order: int) -> Any:
    """Return ``kernel_for(query, with_stats, parallel)`` for one child order."""
    return body_kernels(make_scratch, _body(order))


@register(
    "traversal",
    "kdtree.stack",
    options=KdStackOptions,
    default=True,
    summary="front-to-back kd-tree traversal with a stack (closest and any hit)",
    reference="Slusallek, kd-tree traversal (lecture); Havran 2000, Heuristic Ray Shooting "
    "Algorithms",
)
def trace_kdtree_stack(
    kd: KdTree,
    mesh: TriangleMesh,
    rays: RayBatch,
    *,
    query: str = "closest",
    stats: bool = False,
    options: KdStackOptions | None = None,
    cache: dict[str, Any] | None = None,
) -> HitBatch:
    """Trace rays through a kd-tree front to back with a stack."""
    opt = options or KdStackOptions()
    layout = kd_trace_layout(kd, mesh, cache)
    return run_trace(
        trace_kernel(_ORDERS[opt.order]), layout.arrays(), rays, query, stats,
        "the tree is deeper than MAX_DEPTH",
    )  # fmt: skip
