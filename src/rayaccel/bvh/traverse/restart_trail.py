"""Stackless BVH2 traversal with a restart trail (``bvh2.restart_trail``; Laine 2010).

Laine, "Restart Trail for Stackless BVH Traversal", HPG 2010. For a fixed ray the
ordered traversal (near child first) splits the tree into a processed and an
unprocessed part, and one bit per level records where the boundary runs: bit 0 at
a level means "take the near child" (nothing finished there yet), bit 1 means "take
the far child" (the near subtree is finished, or the node had only one child hit).
When a leaf is done, the trail is advanced (``trail &= -level; trail += level``
finds the deepest 0 above, sets it and clears everything below); if the root bit
(the sentinel, bit 62) is set the traversal is over, otherwise it *restarts from the
root*, following the bits. Per-ray state is two int64 words; backtracking costs a
descent from the root.

Shortened rays: a node that had two children hit on the way down may have only one
on the restart, because a hit shrank the interval. Descending into the near child
again would re-traverse it, so at the level just popped (``pop_level``) a node with
one child hit pops instead (Laine §3). Boxes are culled against the padded interval
of :mod:`rayaccel.kernels.aabb` exactly as in ``bvh2.stack``, and the near/far order
uses the same entry distances (ties to child 0), so the leaves are visited in the
stack's order and the hits are bit-identical.

Short stack (option ``short_stack=n``): a circular stack of the last ``n`` postponed
far children with their entry distance and level. A pop takes the top entry when
there is one (re-checked against the current ``t_hit``, like ``bvh2.stack``) and
restarts only when the stack is empty; overflow drops the oldest entry. With ``n``
at least the tree depth there are no restarts at all.

Layout: the packed rows of ``bvh2.stack`` (no extra memory).

Counters: ``steps``/``nodes`` nodes processed, re-descents included (Laine's
overvisit is ``nodes`` over ``bvh2.stack``'s), ``box_tests``, ``prim_tests``,
``stack_peak`` short-stack depth, ``restarts`` restarts from the root,
``backtracks`` trail pops, ``bytes``.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.bvh.layouts.bvh2 import STACK_ENTRY_BYTES, STACK_SIZE, Bvh2
from rayaccel.bvh.traverse.building_blocks import (
    INF32,
    check_trail_depth,
    child_entries,
    leaf_hits,
    pick,
)
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.dtypes import FloatArray, IntArray
from rayaccel.errors import InvalidInputError
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels
from rayaccel.trace.skeleton import store_backtracks, store_counts, store_hit

#: The root level's bit, the trail's sentinel (deeper levels are lower bits).
ROOT_LEVEL = np.int64(1) << np.int64(62)


@dataclass(frozen=True, slots=True)
class RestartTrailOptions:
    """Options of the ``bvh2.restart_trail`` traversal.

    Attributes
    ----------
    short_stack : int
        Entries of the short stack (0: pure stackless, restart on every pop). Laine
        reports 2.2–2.4× node overvisit without and 5–8% with 3 entries. At most
        ``STACK_SIZE`` (64).
    """

    short_stack: int = 0

    def __post_init__(self) -> None:
        value = self.short_stack
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InvalidInputError(f"short_stack: expected an integer >= 0, got {value!r}")
        if not 0 <= int(value) <= STACK_SIZE:
            raise InvalidInputError(
                f"short_stack: expected an integer in [0, {STACK_SIZE}], got {value!r}"
            )


class RestartArrays(NamedTuple):
    """Kernel argument: the packed layout's arrays and the short-stack size (one flat tuple)."""

    inner_box: FloatArray
    inner_ref: IntArray
    leaf_first: IntArray
    leaf_count: IntArray
    tri: FloatArray
    tri_prim: IntArray
    root_box: FloatArray
    root_ref: IntArray
    short_stack: int


def make_scratch_py(bvh):
    """Return one worker's short stack: far child, entry distance and level (one entry at least)."""
    cap = bvh.short_stack
    ss_ref = np.empty(max(cap, 1), dtype=np.int32)
    ss_t = np.empty(max(cap, 1), dtype=np.float32)
    ss_level = np.empty(max(cap, 1), dtype=np.int64)
    return ss_ref, ss_t, ss_level


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Trace rays ``begin:end`` over ``bvh`` (RestartArrays) with a restart trail; return 0."""
    ss_ref, ss_t, ss_level = scratch
    cap = bvh.short_stack
    box = bvh.inner_box
    refs = bvh.inner_ref
    for r in range(begin, end):
        n_steps = n_prim = n_bytes = n_restarts = n_pops = peak = 0
        (
            valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            box_lo, box_hi, entry, best_prim, best_u, best_v,
        ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        # The root box was tested once up front.
        n_box = 1 if valid else 0
        node = bvh.root_ref[0]
        trail = np.int64(0)
        level = ROOT_LEVEL
        pop_level = np.int64(0)
        ss_n = 0
        ss_top = 0
        done = entry == INF32
        while not done:
            if with_stats:
                n_steps += 1
            pop = True
            if node >= 0:
                # Inner row: test both children from the 64-byte row.
                c0, c1, t0, t1, n_box, n_bytes = child_entries(
                    box, refs, node, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                    box_lo, box_hi, n_box, n_bytes, with_stats,
                )  # fmt: skip
                if t0 < INF32 or t1 < INF32:
                    level >>= 1
                    swap = t1 < t0
                    near = c1 if swap else c0
                    if t0 < INF32 and t1 < INF32:
                        # Two children: the trail bit picks near (0) or far (1).
                        pop = False
                        if trail & level:
                            node = pick(swap, c0, c1)
                        else:
                            node = pick(swap, c1, c0)
                            if cap > 0:
                                # Remember the far child; overflow drops the oldest.
                                ss_ref[ss_top] = c0 if swap else c1
                                ss_t[ss_top] = t0 if swap else t1
                                ss_level[ss_top] = level
                                ss_top = ss_top + 1 if ss_top + 1 < cap else 0
                                ss_n = min(ss_n + 1, cap)
                                if with_stats:
                                    n_bytes += STACK_ENTRY_BYTES
                                    peak = max(peak, ss_n)
                    elif level != pop_level:
                        # One child: mark the level finished on the way down.
                        pop = False
                        trail |= level
                        node = near
                    # Else the far child of the level just popped is culled now
                    # (the ray got shorter): pop instead of re-entering the near.
            else:
                # Leaf: test its triangles, shrinking t_hit.
                t_hit, best_prim, best_u, best_v, box_hi, n_prim, n_bytes = leaf_hits(
                    bvh, ~node, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
                    best_prim, best_u, best_v, query == QUERY_ANY, n_prim, n_bytes, with_stats,
                )  # fmt: skip
                if query == QUERY_ANY and best_prim >= 0:
                    break
            if not pop:
                continue
            # Pop: advance the trail to the deepest unfinished level; continue from
            # the short stack if it has that level's far child, else restart.
            while True:
                if with_stats:
                    n_pops += 1
                trail &= -level
                trail += level
                if trail & ROOT_LEVEL:
                    done = True
                    break
                level = trail & -trail
                pop_level = level
                if ss_n > 0:
                    ss_top = ss_top - 1 if ss_top > 0 else cap - 1
                    ss_n -= 1
                    if with_stats:
                        n_bytes += STACK_ENTRY_BYTES
                    if ss_level[ss_top] == level:
                        if ss_t[ss_top] > box_hi:
                            # Culled by a nearer hit: that level is finished too.
                            continue
                        node = ss_ref[ss_top]
                        break
                    ss_n = 0
                # Restart from the root, following the trail.
                node = bvh.root_ref[0]
                level = ROOT_LEVEL
                if with_stats:
                    n_restarts += 1
                break
        if with_stats:
            store_counts(counters, r, n_steps, n_steps, n_box, n_prim, peak, n_bytes)
            store_backtracks(counters, r, n_restarts, n_pops, 0, (0, 0, 0, 0))
        store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
    return 0


make_scratch = cpu_inline(make_scratch_py)
#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(make_scratch, cpu_inline(trace_rays_py))


@register_traversal("bvh2.restart_trail")
def trace_bvh2_restart_trail(
    bvh: Bvh2, mesh: TriangleMesh, options: RestartTrailOptions, cache: LayoutCache
) -> TracePlan:
    """Stackless ordered traversal restarting from the root along a per-level trail.

    Trace rays through a binary BVH with a restart trail (and an optional short stack).

    Hits are bit-identical to ``bvh2.stack``'s.

    References
    ----------
    Laine 2010, Restart Trail for Stackless BVH Traversal.
    """
    check_trail_depth(bvh, cache, "bvh2.restart_trail")
    packed = packed_layout(bvh, mesh, cache)
    arrays = RestartArrays(*packed.arrays(), operator.index(options.short_stack))
    return TracePlan(trace_kernel, arrays)
