"""Ordered stack traversal of the 4- or 8-wide form of a binary BVH (``bvh2.wide``).

Wald, Benthin, Boulos 2008, "Getting Rid of Packets — Efficient SIMD Single-Ray
Traversal using Multi-branching BVHs"; Dammertz, Hanika, Keller 2008, "Shallow
Bounding Volume Hierarchies for Fast SIMD Ray Tracing of Incoherent Rays". The
binary tree any ``bvh2`` builder made is collapsed once per accel into rows of
``width`` = 8 (default) or 4 children (:mod:`rayaccel.bvh.layouts.wide`, the SAH-optimal
collapse cached as ``"bvh2.wide4"`` / ``"bvh2.wide8"``, the greedy one with ``.greedy``
added); a traversal step tests the child boxes of one
row as the lanes of one vector slab test (:mod:`rayaccel.kernels.aabb_wide`), then
visits the hit children nearest first: the nearest becomes the next node, the
others are pushed farthest first with their entry distances. As in ``bvh2.stack``
popped entries beyond the closest hit are dropped unfetched, and leaves, the
triangle test, the box test's robustness (Ize 2013 2-ulp exit widening) and the
culling pad are the same (:mod:`rayaccel.bvh.traverse.building_blocks`).

Results: the same closest ``t`` as ``bvh2.stack`` on every ray (every box that could
hold a nearer hit is visited with the same test); where two triangles are hit at
exactly the same ``t`` the first found wins, and the visiting order differs from
the binary traversal's, so the primitive may differ at exact ties. Any-hit queries
agree on whether a ray is occluded.

Counters: ``steps`` loop iterations, ``nodes`` nodes entered (wide rows and
leaves), ``box_tests`` child boxes tested (the real children of each row, not the
empty lanes), ``prim_tests``, ``stack_peak``, ``bytes`` (256 per 8-wide row, 128 per
4-wide row, 8 per leaf record, 40 per triangle and reference, 8 per stack push and pop).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros

from rayaccel._jit import cpu_inline, keep_branch, prefetch_row
from rayaccel.bvh.layouts.bvh2 import (
    LEAF_BYTES,
    MAX_DEPTH,
    REF_BYTES,
    STACK_ENTRY_BYTES,
    TRIANGLE_BYTES,
    Bvh2,
)
from rayaccel.bvh.layouts.wide import (
    COLLAPSES,
    WIDTHS,
    WideBvh,
    count_column,
    ref_column,
    row_floats,
    wide_layout,
)
from rayaccel.bvh.traverse.building_blocks import lane_planes
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.aabb_wide import slab_test4, slab_test8
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.leaf import intersect_leaf
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels, memoised_layout
from rayaccel.trace.skeleton import store_counts, store_hit

INF32 = np.float32(np.inf)
_PRIM_BYTES = TRIANGLE_BYTES + REF_BYTES


@dataclass(frozen=True, slots=True)
class WideOptions:
    """Options of the ``bvh2.wide`` traversal.

    Attributes
    ----------
    width : {4, 8}
        Children per wide row: 8 (AVX-sized vectors, 256-byte rows; the faster on every
        scene measured) or 4 (SSE-sized, 128-byte rows).
    any_order : {"nearest", "lanes"}
        The order an any-hit query visits a row's hit children in: ``"nearest"`` as
        closest-hit queries do (the others pushed sorted by entry distance), or
        ``"lanes"``, the row's order, unsorted (an occluder anywhere on the segment ends
        the walk, so the sort buys nothing certain; Embree's any-hit traversal does not
        sort either). Closest-hit queries always visit nearest first.
    collapse : {"sah", "greedy"}
        How the binary tree becomes rows (:mod:`rayaccel.bvh.layouts.wide`): the
        SAH-optimal collapse (Ylitie et al. 2017), or Wald et al. 2008's greedy one.
    """

    width: int = 8
    any_order: str = "nearest"
    collapse: str = "sah"

    def __post_init__(self) -> None:
        if self.width not in WIDTHS:
            raise InvalidInputError(f"width: expected one of {WIDTHS}, got {self.width}")
        if self.collapse not in COLLAPSES:
            raise InvalidInputError(f"collapse: expected one of {COLLAPSES}, got {self.collapse!r}")
        if self.any_order not in ANY_ORDERS:
            raise InvalidInputError(
                f"any_order: expected one of {ANY_ORDERS}, got {self.any_order!r}"
            )


#: The orders ``bvh2.wide`` may visit a row's hit children in for any-hit queries.
ANY_ORDERS = ("nearest", "lanes")


@functools.cache
def wide_body(width: int, any_order: str) -> tuple[Any, Any]:
    """Return the ``(make_scratch, trace_rays)`` inline pair of the ``width``-wide traversal.

    ``width``, the columns and sizes it fixes, and ``any_order`` (:class:`WideOptions`)
    are compile-time constants of the body (:mod:`rayaccel.trace.skeleton`).
    """
    any_in_lanes = any_order == "lanes"
    ref_col = ref_column(width)
    count_col = count_column(width)
    row_bytes = 4 * row_floats(width)
    # Stack entries: a row pushes at most width - 1, a path crosses at most MAX_DEPTH rows.
    stack_size = (width - 1) * MAX_DEPTH + 1

    def make_scratch_py(bvh):
        """Return one worker's stack (reference, entry distance) and lane distances."""
        stack_ref = np.empty(stack_size, dtype=np.int32)
        stack_t = np.empty(stack_size, dtype=np.float32)
        lane_t = np.empty(width, dtype=np.float32)
        return stack_ref, stack_t, lane_t

    def trace_rays_py(
        bvh, scratch, origin, direction, tmin, tmax, begin, end,
        hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
    ):  # fmt: skip
        """Trace rays ``begin:end`` through ``bvh`` (WideArrays); return how many overflowed."""
        stack_ref, stack_t, lane_t = scratch
        box = bvh.box
        refs = bvh.ref
        n_overflowed = 0
        for r in range(begin, end):
            overflowed = n_steps = n_nodes = n_prim = peak = n_bytes = 0
            (
                valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
                box_lo, box_hi, entry, best_prim, best_u, best_v,
            ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
            # The root box was tested once up front.
            n_box = 1 if valid else 0
            # Near/far plane columns of each axis in the structure-of-arrays row.
            near_x, far_x, near_y, far_y, near_z, far_z = lane_planes(width, nx, ny, nz, fx, fy, fz)
            sp = 0
            node = bvh.root_ref[0]
            done = entry == INF32
            while not done:
                if with_stats:
                    n_steps += 1
                    n_nodes += 1
                if node >= 0:
                    # All child boxes in one vector slab test (aabb_wide.py).
                    if width == 8:
                        mask = slab_test8(
                            box, node, near_x, far_x, near_y, far_y, near_z, far_z,
                            ox, oy, oz, ix, iy, iz, box_lo, box_hi, lane_t,
                        )  # fmt: skip
                    else:
                        mask = slab_test4(
                            box, node, near_x, far_x, near_y, far_y, near_z, far_z,
                            ox, oy, oz, ix, iy, iz, box_lo, box_hi, lane_t,
                        )  # fmt: skip
                    if with_stats:
                        n_box += refs[node, count_col]
                        n_bytes += row_bytes
                    if mask != 0 and mask & (mask - 1) == 0:
                        # One hit (the common case): go there, through a branch per
                        # lane, so the CPU predicts the child and fetches it at once
                        # instead of waiting for the test to compute its index.
                        for j in range(width):
                            if mask == 1 << j:
                                keep_branch()
                                node = refs[node, ref_col + j]
                                break
                        continue
                    if mask != 0:
                        # The first hit lane; with one hit (the common case) go there.
                        j = trailing_zeros(mask)
                        mask &= mask - 1
                        next_node = refs[node, ref_col + j]
                        next_t = lane_t[j]
                        n_hit = 1
                        # More hits: keep the nearest as the next node and insert the
                        # others among this row's pushes, nearest on top (a stable
                        # insertion sort: equal distances keep lane order).
                        while mask != 0:
                            j = trailing_zeros(mask)
                            mask &= mask - 1
                            child = refs[node, ref_col + j]
                            tj = lane_t[j]
                            if query == QUERY_ANY and any_in_lanes:
                                k = sp  # pushed as they come, unsorted
                            elif tj < next_t:
                                keep_branch()
                                child, next_node = next_node, child
                                tj, next_t = next_t, tj
                                k = sp
                                while k > sp - (n_hit - 1) and stack_t[k - 1] < tj:
                                    stack_ref[k] = stack_ref[k - 1]
                                    stack_t[k] = stack_t[k - 1]
                                    k -= 1
                            else:
                                keep_branch()
                                k = sp
                                while k > sp - (n_hit - 1) and stack_t[k - 1] <= tj:
                                    stack_ref[k] = stack_ref[k - 1]
                                    stack_t[k] = stack_t[k - 1]
                                    k -= 1
                            stack_ref[k] = child
                            stack_t[k] = tj
                            sp += 1
                            n_hit += 1
                        if next_node >= 0:
                            prefetch_row(box, next_node)
                        if sp > stack_size - width:
                            overflowed = 1
                            break
                        if with_stats and n_hit > 1:
                            n_bytes += STACK_ENTRY_BYTES * (n_hit - 1)
                            peak = max(peak, sp)
                        node = next_node
                        continue
                else:
                    # Leaf: test its triangles, shrinking t_hit.
                    leaf = ~node
                    first = bvh.leaf_first[leaf]
                    last = first + bvh.leaf_count[leaf]
                    if with_stats:
                        n_bytes += LEAF_BYTES + _PRIM_BYTES * (last - first)
                    t_hit, best_prim, best_u, best_v, tested = intersect_leaf(
                        bvh.tri, bvh.tri_prim, first, last, okx, oky, okz, kx, ky, kz,
                        Sx, Sy, Sz, t_lo, t_hit, best_prim, best_u, best_v,
                        query == QUERY_ANY,
                    )  # fmt: skip
                    box_hi = t_hit + pad
                    if with_stats:
                        n_prim += tested
                    if query == QUERY_ANY and best_prim >= 0:
                        break
                # Pop the next entry still in front of the closest hit.
                done = True
                while sp > 0:
                    sp -= 1
                    if with_stats:
                        n_bytes += STACK_ENTRY_BYTES
                    if stack_t[sp] <= box_hi:
                        node = stack_ref[sp]
                        done = False
                        break
            if with_stats:
                store_counts(counters, r, n_steps, n_nodes, n_box, n_prim, peak, n_bytes)
            store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
            n_overflowed += overflowed
        return n_overflowed

    return cpu_inline(make_scratch_py), cpu_inline(trace_rays_py)


@functools.cache
def wide_kernels(width: int, any_order: str) -> Any:
    """Return ``kernel_for(query, with_stats, parallel)``: the compiled ``width``-wide variants."""
    return body_kernels(*wide_body(width, any_order))


def wide_bvh(
    bvh: Bvh2,
    mesh: TriangleMesh,
    cache: dict[str, Any] | None,
    width: int = 8,
    collapse: str = "sah",
) -> WideBvh:
    """Return the ``width``-wide layout of ``bvh``, memoised in ``cache`` when given.

    The SAH collapse is cached as ``bvh2.wide{width}``, the greedy one with ``.greedy``
    added.
    """
    name = f"bvh2.wide{width}" + ("" if collapse == "sah" else f".{collapse}")
    return memoised_layout(
        cache, name, lambda: wide_layout(packed_layout(bvh, mesh, cache), width, collapse)
    )


@register_traversal("bvh2.wide")
def trace_bvh2_wide(
    bvh: Bvh2, mesh: TriangleMesh, options: WideOptions, cache: LayoutCache
) -> TracePlan:
    """Ordered stack traversal of the 4- or 8-wide collapsed tree, vector box tests.

    Trace rays through the wide form of a binary BVH (see the module docstring).

    The derived wide rows are cached under ``"bvh2.wide4"`` or ``"bvh2.wide8"`` (the
    greedy collapse: ``"bvh2.wide4.greedy"``, ``"bvh2.wide8.greedy"``).

    References
    ----------
    Wald, Benthin, Boulos 2008, Getting Rid of Packets;
    Dammertz, Hanika, Keller 2008, Shallow Bounding Volume Hierarchies.
    """
    wide = wide_bvh(bvh, mesh, cache, options.width, options.collapse)
    return TracePlan(wide_kernels(options.width, options.any_order), wide.arrays())
