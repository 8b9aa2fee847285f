"""Stackless BVH2 traversal with parent links (``bvh2.parent_link``; Hapala et al. 2011).

Hapala, Davidovič, Wald, Havran, Slusallek, "Efficient Stack-less BVH Traversal for
Ray Tracing", SCCG 2011. Instead of a stack, every node knows its parent; the walk
is a three-state machine that decides the next node from where it came from:

- *from the parent* (``DOWN``): entering an inner node, go to its near child;
- *from the sibling* (``TRY``): test a child's box; a hit descends (or, for a leaf,
  intersects it), then the near child hands over to its sibling and the far child
  hands back to the parent;
- *from the child* (``UP``): back at the parent; if the child was the near one, try
  its sibling, otherwise keep climbing; leaving the root ends the traversal.

Per-ray state is O(1) (node, slot and state), backtracking costs O(depth) parent
steps. Hapala et al. use a ray-independent child order per node (the split axis and
the ray's sign), because the order must be recomputable on the way up. We re-derive
the *distance* order instead: in the packed layout (:mod:`rayaccel.bvh.layouts.bvh2`) both
child boxes sit in the parent's 64-byte row, so coming back up costs one row fetch
and two box tests, and the walk visits exactly the nodes of ``bvh2.stack`` in the
same order, giving bit-identical hits (same ``t`` and primitive, same any-hit).
Entry distances used for ordering are computed against ``[tmin, inf]``; a child is
entered only if its entry is also within the current ``[tmin, t_hit]`` (padded as in
``bvh2.stack``), which is exactly the stack's pop test.

Layout: the packed rows of ``bvh2.stack`` plus up-links
(:class:`~rayaccel.bvh.layouts.stackless_links.LinkedBvh2`, 4 bytes per node), derived
once per accel and cached.

Counters: ``steps`` loop iterations, ``nodes`` nodes entered (equals ``bvh2.stack``),
``box_tests`` (two per row visit, down or up), ``prim_tests``, ``backtracks`` parent
steps (row visits on the way up), ``bytes`` (64 per row visit, 4 per up-link, leaf
and triangle bytes).
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel._jit import cpu_inline
from rayaccel.bvh.layouts.bvh2 import PACKED_ROW_BYTES, Bvh2
from rayaccel.bvh.layouts.stackless_links import LINK_BYTES, linked_layout
from rayaccel.bvh.traverse.building_blocks import INF32, box_entry, leaf_hits
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels
from rayaccel.trace.skeleton import no_scratch, store_backtracks, store_counts, store_hit

#: States of the machine (Hapala et al.: from parent, from child, from sibling).
DOWN = 0
UP = 1
TRY = 2


@dataclass(frozen=True, slots=True)
class ParentLinkOptions:
    """Options of the ``bvh2.parent_link`` traversal (none; kept for a uniform API)."""


def climb_py(row_up, row, n_bytes, with_stats):
    """Follow the up-link of row ``row``: return ``(parent row, slot of row in it, n_bytes)``.

    With ``with_stats`` the byte counter is advanced by the link read.
    """
    up = row_up[row]
    if with_stats:
        n_bytes += LINK_BYTES
    return up >> 1, up & 1, n_bytes


climb = cpu_inline(climb_py)


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Trace rays ``begin:end`` over ``bvh`` (LinkedArrays), three-state machine; return 0."""
    _ = scratch
    box = bvh.inner_box
    refs = bvh.inner_ref
    for r in range(begin, end):
        n_steps = n_nodes = n_prim = n_up = n_bytes = 0
        (
            valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            box_lo, box_hi, entry, best_prim, best_u, best_v,
        ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        # The root box was tested once up front.
        n_box = 1 if valid else 0
        root = bvh.root_ref[0]
        if entry < INF32 and root < 0:
            # A single-leaf tree.
            t_hit, best_prim, best_u, best_v, box_hi, n_prim, n_bytes = leaf_hits(
                bvh, ~root, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
                best_prim, best_u, best_v, query == QUERY_ANY, n_prim, n_bytes, with_stats,
            )  # fmt: skip
            if with_stats:
                n_steps += 1
                n_nodes += 1
        elif entry < INF32:
            row = root
            state = DOWN
            slot = 0
            near = 0
            t0 = INF32
            t1 = INF32
            while True:
                if state != TRY:
                    # At a row (entered from above, or back from a child): the
                    # children's entry distances give the near child (ties: 0).
                    t0 = box_entry(
                        box, row, 0, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                        box_lo, INF32,
                    )  # fmt: skip
                    t1 = box_entry(
                        box, row, 6, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                        box_lo, INF32,
                    )  # fmt: skip
                    near = 1 if t1 < t0 else 0
                    if with_stats:
                        n_steps += 1
                        n_box += 2
                        n_bytes += PACKED_ROW_BYTES
                        if state == DOWN:
                            n_nodes += 1
                        else:
                            n_up += 1
                    if state == DOWN:
                        # From the parent: try the near child first.
                        slot = near
                        state = TRY
                    elif slot == near:
                        # From the near child: its sibling is next.
                        slot = 1 - near
                        state = TRY
                    else:
                        # From the far child: this row is finished, climb.
                        if row == root:
                            break
                        row, slot, n_bytes = climb(bvh.row_up, row, n_bytes, with_stats)
                        continue
                # Try child `slot`: enter it if its box is hit within [tmin, t_hit].
                t = t0 if slot == 0 else t1
                if t < INF32 and t <= box_hi:
                    child = refs[row, 12 + slot]
                    if child >= 0:
                        row = child
                        state = DOWN
                        continue
                    # Leaf: test its triangles, shrinking t_hit.
                    t_hit, best_prim, best_u, best_v, box_hi, n_prim, n_bytes = leaf_hits(
                        bvh, ~child, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
                        best_prim, best_u, best_v, query == QUERY_ANY, n_prim, n_bytes,
                        with_stats,
                    )  # fmt: skip
                    if with_stats:
                        n_steps += 1
                        n_nodes += 1
                    if query == QUERY_ANY and best_prim >= 0:
                        break
                # The child is finished: hand over to the sibling, or climb.
                if slot == near:
                    slot = 1 - near
                else:
                    if row == root:
                        break
                    row, slot, n_bytes = climb(bvh.row_up, row, n_bytes, with_stats)
                    state = UP
        if with_stats:
            store_counts(counters, r, n_steps, n_nodes, n_box, n_prim, 0, n_bytes)
            store_backtracks(counters, r, 0, n_up, 0, (0, 0, 0, 0))
        store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
    return 0


#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(no_scratch, cpu_inline(trace_rays_py))


@register_traversal("bvh2.parent_link")
def trace_bvh2_parent_link(
    bvh: Bvh2, mesh: TriangleMesh, options: ParentLinkOptions, cache: LayoutCache
) -> TracePlan:
    """Stackless three-state machine over parent and sibling links (distance order).

    Trace rays through a binary BVH with parent links and no stack.

    Hits are bit-identical to ``bvh2.stack``'s.

    References
    ----------
    Hapala et al. 2011, Efficient Stack-less BVH Traversal for Ray Tracing.
    """
    packed = packed_layout(bvh, mesh, cache)
    linked = linked_layout(packed, cache)
    return TracePlan(trace_kernel, linked.arrays())
