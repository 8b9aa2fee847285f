"""Stackless BVH2 traversal with skip pointers (``bvh2.skip``; Smits 1998).

Smits, "Efficiency Issues for Ray Tracing", JGT 3(2), 1998: store the nodes in
depth-first pre-order and give each a *skip* pointer to the node that follows its
subtree. The walk is a single index moving forward: a hit box goes to the next row
(its first child, or for a leaf, after testing it, the next subtree), a missed box
jumps to its skip pointer, and the walk ends past the last row. No stack, no
backtracking, no per-ray state but the index; the price is a fixed child order
(child 0 first, whatever the ray direction), so a closest-hit query cannot prune the
far child with a hit found in the near one as early as an ordered traversal does.
It is the stackless baseline without ordering.

Layout: :class:`rayaccel.bvh.layouts.stackless_links.SkipBvh2` (32 bytes per node), derived once per
accel and cached under ``"bvh2.skip"``; leaf tables and triangles are shared with
the packed layout of ``bvh2.stack``.

Results: the closest ``t`` is exactly that of ``bvh2.stack`` (every box that could
hold a nearer hit is visited, and the triangle test is the same), but where two
primitives are hit at exactly the same ``t`` the first found wins, and the order
differs from the stack's, so the primitive may differ at exact ties. Any-hit queries
agree on *whether* a ray is occluded; the reported primitive may differ.

Counters: ``steps`` rows visited (boxes tested), ``nodes`` boxes hit (inner and
leaf), ``box_tests``, ``prim_tests``, ``bytes`` (32 per row, 8 per leaf record, 40
per triangle and reference); ``stack_peak`` and the backtracking counters are 0.
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel._jit import cpu_inline
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.stackless_links import SKIP_ROW_BYTES, skip_layout
from rayaccel.bvh.traverse.building_blocks import INF32, box_entry, leaf_hits
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels
from rayaccel.trace.skeleton import no_scratch, store_counts, store_hit


@dataclass(frozen=True, slots=True)
class SkipOptions:
    """Options of the ``bvh2.skip`` traversal (none; kept for a uniform API)."""


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Walk the pre-order rows of ``bvh`` (SkipArrays) for rays ``begin:end``; return 0."""
    _ = scratch
    rows = bvh.node_row
    ints = bvh.node_int
    n_nodes = rows.shape[0]
    for r in range(begin, end):
        n_steps = n_visited = n_prim = n_bytes = 0
        # (Row 0 is the root: the walk tests it as it tests every row.)
        (
            valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            box_lo, box_hi, _entry, best_prim, best_u, best_v,
        ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        node = 0 if valid else n_nodes
        while node < n_nodes:
            # Test this row's box: a hit steps into the subtree, a miss skips it.
            entry = box_entry(
                rows, node, 0, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                box_lo, box_hi,
            )  # fmt: skip
            if with_stats:
                n_steps += 1
                n_bytes += SKIP_ROW_BYTES
            if entry == INF32:
                node = ints[node, 6]
                continue
            if with_stats:
                n_visited += 1
            leaf = ints[node, 7]
            if leaf >= 0:
                # Leaf: test its triangles, shrinking t_hit, then go on after it.
                t_hit, best_prim, best_u, best_v, box_hi, n_prim, n_bytes = leaf_hits(
                    bvh, leaf, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
                    best_prim, best_u, best_v, query == QUERY_ANY, n_prim, n_bytes, with_stats,
                )  # fmt: skip
                if query == QUERY_ANY and best_prim >= 0:
                    break
            node += 1
        if with_stats:
            store_counts(counters, r, n_steps, n_visited, n_steps, n_prim, 0, n_bytes)
        store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
    return 0


#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(no_scratch, cpu_inline(trace_rays_py))


@register_traversal("bvh2.skip")
def trace_bvh2_skip(
    bvh: Bvh2, mesh: TriangleMesh, options: SkipOptions, cache: LayoutCache
) -> TracePlan:
    """Stackless fixed-order walk over pre-order nodes with skip pointers.

    Trace rays through a binary BVH with skip pointers (no stack, fixed child order).

    The closest ``t`` equals ``bvh2.stack``'s bit for bit; the primitive may differ at
    exact ties (see the module docstring).

    References
    ----------
    Smits 1998, Efficiency Issues for Ray Tracing.
    """
    packed = packed_layout(bvh, mesh, cache)
    skip = skip_layout(bvh, packed, cache)
    return TracePlan(trace_kernel, skip.arrays())
