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
from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel._variant import register
from rayaccel.bvh.layouts.bvh2 import LEAF_BYTES, REF_BYTES, TRIANGLE_BYTES, Bvh2
from rayaccel.bvh.layouts.stackless_links import SKIP_ROW_BYTES, skip_layout
from rayaccel.bvh.traverse.building_blocks import INF32, box_entry
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.counters import Counter
from rayaccel.queries import QUERY_ANY
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.leaf import intersect_leaf
from rayaccel.trace.ray_setup import ray_prologue
from rayaccel.trace.run import body_kernels, run_trace
from rayaccel.trace.skeleton import store_hit

ZERO32 = np.float32(0.0)
_PRIM_BYTES = TRIANGLE_BYTES + REF_BYTES


@dataclass(frozen=True, slots=True)
class SkipOptions:
    """Options of the ``bvh2.skip`` traversal (none; kept for a uniform API)."""


def make_scratch_py(bvh):
    """Return one worker's scratch: none (the walk keeps only an index per ray)."""
    return 0


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Walk the pre-order rows of ``bvh`` (SkipArrays) for rays ``begin:end``; return 0.

    The body of :func:`rayaccel.trace.skeleton.trace_kernel`: stores each hit with
    :func:`rayaccel.trace.skeleton.store_hit` and, with ``with_stats``, each ray's
    counters in ``counters[r]``.
    """
    _ = scratch
    rows = bvh.node_row
    ints = bvh.node_int
    n_nodes = rows.shape[0]
    for r in range(begin, end):
        n_steps = 0
        n_visited = 0
        n_prim = 0
        n_bytes = 0
        (
            valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
        ) = ray_prologue(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        best_prim = -1
        best_u = ZERO32
        best_v = ZERO32
        box_lo = t_lo - pad
        box_hi = t_hit + pad
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
                first = bvh.leaf_first[leaf]
                last = first + bvh.leaf_count[leaf]
                t_hit, best_prim, best_u, best_v, tested = intersect_leaf(
                    bvh.tri, bvh.tri_prim, first, last, okx, oky, okz, kx, ky, kz,
                    Sx, Sy, Sz, t_lo, t_hit, best_prim, best_u, best_v,
                    query == QUERY_ANY,
                )  # fmt: skip
                box_hi = t_hit + pad
                if with_stats:
                    n_prim += tested
                    n_bytes += LEAF_BYTES + _PRIM_BYTES * tested
                if query == QUERY_ANY and best_prim >= 0:
                    break
            node += 1
        if with_stats:
            counters[r, Counter.STEPS] = n_steps
            counters[r, Counter.NODES] = n_visited
            counters[r, Counter.BOX_TESTS] = n_steps
            counters[r, Counter.PRIM_TESTS] = n_prim
            counters[r, Counter.BYTES] = n_bytes
        store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
    return 0


make_scratch = cpu_inline(make_scratch_py)
trace_rays = cpu_inline(trace_rays_py)
#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(make_scratch, trace_rays)


@register(
    "traversal",
    "bvh2.skip",
    options=SkipOptions,
    summary="stackless fixed-order walk over pre-order nodes with skip pointers",
    reference="Smits 1998, Efficiency Issues for Ray Tracing",
)
def trace_bvh2_skip(
    bvh: Bvh2,
    mesh: TriangleMesh,
    rays: RayBatch,
    *,
    query: str = "closest",
    stats: bool = False,
    options: SkipOptions | None = None,
    cache: dict[str, Any] | None = None,
) -> HitBatch:
    """Trace rays through a binary BVH with skip pointers (no stack, fixed child order).

    The closest ``t`` equals ``bvh2.stack``'s bit for bit; the primitive may differ at
    exact ties (see the module docstring).
    """
    _ = options
    packed = packed_layout(bvh, mesh, cache)
    skip = skip_layout(bvh, packed, cache)
    return run_trace(trace_kernel, skip.arrays(), rays, query, stats)
