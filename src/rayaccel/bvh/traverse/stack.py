"""Ordered stack traversal of a binary BVH (Aila & Laine 2009 "while-while" loop).

Each step reads one inner row of the pairs layout (both children's boxes side by
side, 64 bytes, :mod:`rayaccel.bvh.layouts.pairs`), tests the two boxes against
``[tmin, t_closest]`` with one 2-lane vector slab test
(:data:`rayaccel.kernels.aabb_wide.slab_test2`) and descends into the nearer child
by entry distance, pushing the farther one with its entry distance; ties go to
child 0. Popped entries whose entry distance is beyond the closest hit found since
they were pushed are discarded without being fetched. Leaves are tested with the
watertight triangle test of Woop et al. 2013; boxes with the robust slab test of
Ize 2013. Any-hit queries (``query="any"``) stop at the first hit in ``[tmin, tmax]``.

Why it is fast: both children's rows are prefetched as soon as the row naming them
arrives, before the box test, so the next fetch overlaps the test; a leaf child's
triangle range sits in its parent's row, so entering a leaf reads no leaf table; the
two boxes share vector instructions; and the choice of the next child stays a branch
(:func:`rayaccel._jit.keep_branch`), which the CPU predicts and fetches ahead, where a
select would wait for the whole box test. Hits are bit-identical to the scalar
test's. (The measurements behind these choices are in docs/performance.md.)

The per-ray body (:func:`trace_rays_py`) runs in the shared skeleton of
:mod:`rayaccel.trace.skeleton`, compiled per ``query`` (closest/any), ``with_stats``
(per-ray counters, removed from the plain variant) and ``parallel``.

Counters (``with_stats``): ``steps`` loop iterations, ``nodes`` nodes entered
(inner and leaf, root included), ``box_tests`` slab tests, ``prim_tests`` triangle
tests, ``stack_peak`` deepest stack, ``bytes`` estimated bytes fetched (64 per
inner row, 40 per triangle and reference, 12 per stack push and pop: reference,
leaf count, entry distance).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline, keep_branch, prefetch_row
from rayaccel.bvh.layouts.bvh2 import (
    PACKED_ROW_BYTES,
    REF_BYTES,
    STACK_ENTRY_BYTES,
    STACK_SIZE,
    TRIANGLE_BYTES,
    Bvh2,
    PackedBvh2,
    pack_bvh2,
)
from rayaccel.bvh.layouts.pairs import COUNT_COLUMN, REF_COLUMN, PairsBvh2, pairs_layout
from rayaccel.bvh.traverse.building_blocks import lane_planes
from rayaccel.kernels.aabb_wide import slab_test2
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.leaf import intersect_leaf
from rayaccel.trace.ray_setup import ray_prologue, root_entry
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels, memoised_layout
from rayaccel.trace.skeleton import store_counts, store_hit

INF32 = np.float32(np.inf)
ZERO32 = np.float32(0.0)
_PRIM_BYTES = TRIANGLE_BYTES + REF_BYTES
#: A stack entry of this traversal: reference, leaf count and entry distance.
_STACK_ENTRY_BYTES = STACK_ENTRY_BYTES + 4


@dataclass(frozen=True, slots=True)
class StackOptions:
    """Options of the ``bvh2.stack`` traversal (it has none yet; kept for a uniform API)."""


def make_scratch_py(bvh):
    """Return one worker's stack (reference, leaf count, entry distance) and lane distances."""
    stack_ref = np.empty(STACK_SIZE, dtype=np.int32)
    stack_count = np.empty(STACK_SIZE, dtype=np.int32)
    stack_t = np.empty(STACK_SIZE, dtype=np.float32)
    lane_t = np.empty(2, dtype=np.float32)
    return stack_ref, stack_count, stack_t, lane_t


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Trace rays ``begin:end`` through ``bvh`` (PairsArrays); return how many overflowed."""
    stack_ref, stack_count, stack_t, lane_t = scratch
    box = bvh.box
    refs = bvh.ref
    n_overflowed = 0
    for r in range(begin, end):
        overflowed = n_steps = n_nodes = n_box = n_prim = peak = n_bytes = 0
        # Per-ray constants, shared with every traversal of every family.
        (
            valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
        ) = ray_prologue(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        best_prim = -1
        best_u = ZERO32
        best_v = ZERO32
        # Degenerate rays (zero or non-finite direction or origin, empty interval) miss.
        if valid:
            # Boxes are culled against a slightly widened interval (aabb.py).
            box_lo = t_lo - pad
            box_hi = t_hit + pad
            # Columns of the near and far plane pairs (pairs.py): plane k of child
            # c is column 2k + c, and nx, ny, nz are the interleaved plane indices.
            near_x, far_x, near_y, far_y, near_z, far_z = lane_planes(2, nx, ny, nz, fx, fy, fz)
            sp = 0
            # The root box is tested once up front.
            entry = root_entry(
                bvh.root_box, ox, oy, oz, ix, iy, iz,
                nx, ny, nz, fx, fy, fz, box_lo, box_hi,
            )  # fmt: skip
            if with_stats:
                n_box += 1
            node = bvh.root_ref[0]
            count = bvh.root_ref[1]
            done = entry == INF32
            while not done:
                if with_stats:
                    n_steps += 1
                    n_nodes += 1
                if node >= 0:
                    # Inner row: start fetching the children's rows, then test both
                    # children's boxes from this 64-byte row in one 2-lane test.
                    c0 = refs[node, REF_COLUMN]
                    c1 = refs[node, REF_COLUMN + 1]
                    # (A leaf child prefetches row 0 instead: no branch to mispredict.)
                    prefetch_row(box, max(c0, 0))
                    prefetch_row(box, max(c1, 0))
                    mask = slab_test2(
                        box, node, near_x, far_x, near_y, far_y, near_z, far_z,
                        ox, oy, oz, ix, iy, iz, box_lo, box_hi, lane_t,
                    )  # fmt: skip
                    if with_stats:
                        n_box += 2
                        n_bytes += PACKED_ROW_BYTES
                    if mask == 3:
                        # Both hit: the nearer (ties: child 0) is next, the other
                        # is pushed with its entry distance.
                        if sp == STACK_SIZE:
                            overflowed = 1
                            break
                        if with_stats:
                            n_bytes += _STACK_ENTRY_BYTES
                            peak = max(peak, sp + 1)
                        if lane_t[1] < lane_t[0]:
                            keep_branch()
                            stack_ref[sp] = c0
                            stack_count[sp] = refs[node, COUNT_COLUMN]
                            stack_t[sp] = lane_t[0]
                            sp += 1
                            count = refs[node, COUNT_COLUMN + 1]
                            node = c1
                            continue
                        keep_branch()
                        stack_ref[sp] = c1
                        stack_count[sp] = refs[node, COUNT_COLUMN + 1]
                        stack_t[sp] = lane_t[1]
                        sp += 1
                        count = refs[node, COUNT_COLUMN]
                        node = c0
                        continue
                    if mask == 1:
                        # One hit: go there.
                        keep_branch()
                        count = refs[node, COUNT_COLUMN]
                        node = c0
                        continue
                    if mask == 2:
                        keep_branch()
                        count = refs[node, COUNT_COLUMN + 1]
                        node = c1
                        continue
                else:
                    # Leaf: test its triangles, shrinking t_hit.
                    first = ~node
                    last = first + count
                    if with_stats:
                        n_bytes += _PRIM_BYTES * count
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
                        n_bytes += _STACK_ENTRY_BYTES
                    if stack_t[sp] <= box_hi:
                        node = stack_ref[sp]
                        count = stack_count[sp]
                        done = False
                        # Start fetching the entry below: the subtree since its push
                        # may have evicted its row (branch-free: a leaf or no entry
                        # prefetches row 0 or itself).
                        prefetch_row(box, max(stack_ref[max(sp - 1, 0)], 0))
                        break
        if with_stats:
            store_counts(counters, r, n_steps, n_nodes, n_box, n_prim, peak, n_bytes)
        store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
        n_overflowed += overflowed
    return n_overflowed


make_scratch = cpu_inline(make_scratch_py)
#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(make_scratch, cpu_inline(trace_rays_py))


def packed_layout(bvh: Bvh2, mesh: TriangleMesh, cache: dict[str, Any] | None) -> PackedBvh2:
    """Return the packed layout of ``bvh``, memoised in ``cache`` when given."""
    return memoised_layout(cache, "bvh2.packed", lambda: pack_bvh2(bvh, mesh.hit_rows()))


def stack_layout(bvh: Bvh2, mesh: TriangleMesh, cache: dict[str, Any] | None) -> PairsBvh2:
    """Return the pairs layout ``bvh2.stack`` traces, memoised in ``cache`` when given."""
    return memoised_layout(
        cache, "bvh2.pairs", lambda: pairs_layout(packed_layout(bvh, mesh, cache))
    )


@register_traversal("bvh2.stack", default=True)
def trace_bvh2_stack(
    bvh: Bvh2, mesh: TriangleMesh, options: StackOptions, cache: LayoutCache
) -> TracePlan:
    """Ordered stack traversal, near child first (closest and any hit).

    Trace rays through a binary BVH with an ordered stack.

    The pairs layout is derived from the canonical tree on first use.

    Raises
    ------
    TraversalOverflowError
        Never for trees from rayaccel builders (depth is bounded by ``MAX_DEPTH``).

    References
    ----------
    Aila & Laine 2009, Understanding the Efficiency of Ray Traversal on GPUs.
    """
    return pairs_plan(trace_kernel, bvh, mesh, cache)


def pairs_plan(
    kernel_for: Any, bvh: Bvh2, mesh: TriangleMesh, cache: dict[str, Any] | None
) -> TracePlan:
    """Return the plan running ``kernel_for`` on the pairs rows (``bvh2.stack``, ``.packet``)."""
    pairs = stack_layout(bvh, mesh, cache)
    hint = f"the tree is deeper than its {STACK_SIZE}-entry stack allows (MAX_DEPTH)"
    return TracePlan(kernel_for, pairs.arrays(), hint)
