"""Stackless BVH2 traversal with a bitstack and parent links (``bvh2.bitstack``).

Áfra & Szirmay-Kalos, "Stackless Multi-BVH Traversal for CPU, MIC and GPU Ray
Tracing", CGF 33(1), 2014, binary form (the "Stackless [Áfra 2014]" baseline of
Binder & Keller 2016). The stack of postponed far children is replaced by one bit
per level of the current path: descending shifts the bitstack left and sets the new
bit when both children were hit (the far one is pending at that level). To
backtrack, climb parent links while the lowest bit is 0, shifting it out; at the
first 1 the pending node is the *sibling* of the current one (it is always "the
other child"), so clear the bit and go there. Because the pending node is implied,
the near/far order can follow the ray's entry distances, exactly as ``bvh2.stack``.

Before entering the pending sibling its box is re-tested against the current
``[tmin, t_hit]`` (one box test from the parent's row): this is the stack's pop test
(``stack_t <= t_hit``), so the nodes visited and the hits are those of
``bvh2.stack``, bit for bit. State per ray: one int64 (depth <= 62) and the current
node; backtracking costs O(depth) parent steps.

Layout: the packed rows of ``bvh2.stack`` plus up-links
(:class:`~rayaccel.bvh.layouts.stackless_links.LinkedBvh2`), derived once per accel and cached.

Counters: ``steps`` iterations, ``nodes`` nodes entered (equals ``bvh2.stack``),
``box_tests``, ``prim_tests``, ``backtracks`` parent steps climbed, the histogram of
backtracking targets (``backtrack_sibling`` 0 levels up, ``_uncle`` 1,
``_grand_uncle`` 2, ``_further`` more; culled targets count too), ``bytes``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.bvh.layouts.bvh2 import PACKED_ROW_BYTES, Bvh2
from rayaccel.bvh.layouts.stackless_links import LINK_BYTES, linked_layout
from rayaccel.bvh.traverse.building_blocks import (
    INF32,
    box_entry,
    check_trail_depth,
    child_entries,
    leaf_hits,
    pick,
    tally_backtrack,
)
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels
from rayaccel.trace.skeleton import no_scratch, store_backtracks, store_counts, store_hit


@dataclass(frozen=True, slots=True)
class BitstackOptions:
    """Options of the ``bvh2.bitstack`` traversal (none; kept for a uniform API)."""


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Trace rays ``begin:end`` over ``bvh`` (LinkedArrays) with a bitstack; return 0."""
    _ = scratch
    box = bvh.inner_box
    refs = bvh.inner_ref
    for r in range(begin, end):
        n_steps = n_nodes = n_prim = n_up = n_bytes = 0
        targets = (0, 0, 0, 0)
        (
            valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            box_lo, box_hi, entry, best_prim, best_u, best_v,
        ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        # The root box was tested once up front.
        n_box = 1 if valid else 0
        node = bvh.root_ref[0]
        bits = np.int64(0)
        done = entry == INF32
        while not done:
            if with_stats:
                n_steps += 1
                n_nodes += 1
            if node >= 0:
                # Inner row: test both children; descend into the nearer hit one
                # and mark the level when the other is pending.
                c0, c1, t0, t1, n_box, n_bytes = child_entries(
                    box, refs, node, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                    box_lo, box_hi, n_box, n_bytes, with_stats,
                )  # fmt: skip
                if t0 < INF32 or t1 < INF32:
                    bits <<= 1
                    if t0 < INF32 and t1 < INF32:
                        bits |= 1
                    node = pick(t1 < t0, c1, c0)
                    continue
            else:
                # Leaf: test its triangles, shrinking t_hit.
                t_hit, best_prim, best_u, best_v, box_hi, n_prim, n_bytes = leaf_hits(
                    bvh, ~node, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
                    best_prim, best_u, best_v, query == QUERY_ANY, n_prim, n_bytes, with_stats,
                )  # fmt: skip
                if query == QUERY_ANY and best_prim >= 0:
                    break
            # Backtrack: climb while the level has nothing pending, then go to
            # the sibling if its box is still within [tmin, t_hit].
            done = True
            climbed = 0
            while bits != 0:
                up = bvh.row_up[node] if node >= 0 else bvh.leaf_up[~node]
                if with_stats:
                    n_bytes += LINK_BYTES
                if bits & 1 == 0:
                    node = up >> 1
                    bits >>= 1
                    climbed += 1
                    if with_stats:
                        n_up += 1
                    continue
                bits ^= 1
                parent = up >> 1
                slot = 1 - (up & 1)
                if with_stats:
                    n_box += 1
                    n_bytes += PACKED_ROW_BYTES
                    targets = tally_backtrack(climbed, targets)
                climbed = 0
                node = refs[parent, 12 + slot]
                t = box_entry(
                    box, parent, 6 * slot, ox, oy, oz, ix, iy, iz, nx, ny, nz,
                    fx, fy, fz, box_lo, box_hi,
                )  # fmt: skip
                if t < INF32:
                    done = False
                    break
        if with_stats:
            store_counts(counters, r, n_steps, n_nodes, n_box, n_prim, 0, n_bytes)
            store_backtracks(counters, r, 0, n_up, 0, targets)
        store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
    return 0


#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(no_scratch, cpu_inline(trace_rays_py))


@register_traversal("bvh2.bitstack")
def trace_bvh2_bitstack(
    bvh: Bvh2, mesh: TriangleMesh, options: BitstackOptions, cache: LayoutCache
) -> TracePlan:
    """Stackless ordered traversal with a per-level bitstack and parent links.

    Trace rays through a binary BVH with a bitstack and parent links.

    Hits are bit-identical to ``bvh2.stack``'s.

    References
    ----------
    Áfra & Szirmay-Kalos 2014, Stackless Multi-BVH Traversal for CPU, MIC and GPU.
    """
    check_trail_depth(bvh, cache, "bvh2.bitstack")
    packed = packed_layout(bvh, mesh, cache)
    linked = linked_layout(packed, cache)
    return TracePlan(trace_kernel, linked.arrays())
