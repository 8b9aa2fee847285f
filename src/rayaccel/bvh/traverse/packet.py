"""Packets of sixteen rays through a binary BVH (``bvh2.packet``).

Wald, Slusallek, Benthin, Wagner 2001, "Interactive Rendering with Coherent Ray
Tracing"; the masked descent of Wald, Boulos, Shirley 2007 ("Ray Tracing Deformable
Scenes using Dynamic Bounding Volume Hierarchies", §4). Sixteen consecutive rays of a
batch form a packet; rays whose directions have the same signs (an octant) traverse
together: each inner row of the pairs layout (:mod:`rayaccel.bvh.layouts.pairs`, both
children's boxes in 64 bytes) is fetched once for the packet and each child box is
tested against the sixteen rays in one ``<16 x float>`` slab test
(:data:`rayaccel.kernels.aabb_packet.packet_slab_test`). The packet descends into a
child if any of its rays hits it, nearer child first by the entry distance of the
lowest ray that hits both; the farther one is pushed with every ray's entry
distance, and a popped entry goes on with the rays whose closest hit is still beyond
their entry (none: it is dropped unfetched). A leaf tests its triangles for the rays
that hit its box: with one vector form of the watertight test per triangle when those
rays share their shear axes (:mod:`rayaccel.kernels.triangle_packet`, bit-identical to
the scalar test), else one ray at a time with the single-ray traversals' test
(:mod:`rayaccel.kernels.triangle`). Rays of another octant in the same packet traverse
as a packet of their own, so incoherent rays (diffuse bounces) pay up to eight descents
(one per octant) of a few rays each: this traversal is for coherent batches (camera rays
in image order, shadow rays towards one light from neighbouring hits); queries that name
no traversal take it only for those (:mod:`rayaccel.rays.coherence`).

Results: every ray visits each leaf whose box it hits before its closest hit, with
the single-ray box test lane by lane, so the closest ``t`` is ``bvh2.stack``'s; the
visiting order follows the packet, so the primitive may differ at exact ties. Any-hit
queries (``query="any"``) retire a ray at its first hit and end the packet when
every ray is retired.

Counters (per ray, as its share of the packet's work): ``steps`` and ``nodes`` the
packet's rows and leaves the ray took part in (a leaf only if its box was hit),
``box_tests`` two per row, ``prim_tests`` its own triangle tests, ``stack_peak`` the
deepest stack of its descent, ``bytes`` the rows, stack entries and triangles fetched,
divided among the rays that shared them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros

from rayaccel._jit import cpu_inline, prefetch_row
from rayaccel.bvh.layouts.bvh2 import PACKED_ROW_BYTES, REF_BYTES, STACK_SIZE, TRIANGLE_BYTES, Bvh2
from rayaccel.bvh.layouts.pairs import COUNT_COLUMN, REF_COLUMN
from rayaccel.bvh.traverse.building_blocks import lane_planes
from rayaccel.bvh.traverse.stack import pairs_plan
from rayaccel.kernels.aabb_packet import (
    HI_ROW,
    LO_ROW,
    PACKET,
    copy_lane_row,
    lanes_at_most,
    packet_slab_test,
)
from rayaccel.kernels.ray_packet import KX, OCTANT, packet_setup
from rayaccel.kernels.triangle import ray_triangle
from rayaccel.kernels.triangle_packet import ROWS as TRIANGLE_ROWS
from rayaccel.kernels.triangle_packet import (
    SHEAR,
    SHEARED_ORIGIN,
    T_HIT,
    T_LO,
    U,
    V,
    packet_triangle,
)
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import root_entry
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels
from rayaccel.trace.skeleton import store_counts, store_hit

INF32 = np.float32(np.inf)
_PRIM_BYTES = TRIANGLE_BYTES + REF_BYTES
#: A stack entry: reference, leaf count and an entry distance per ray.
_STACK_ENTRY_BYTES = 8 + 4 * PACKET

# Rows of a chunk's lane array after the eight that the box test reads (ox, oy, oz, ix, iy,
# iz, lo, hi): the rays' culling pads, intervals, shear constants, sheared origins,
# hit coordinates, the two children's entry distances, then the stack's.
_PAD = 8
_TRIANGLE = 9  # the rows packet_triangle reads and writes, from here on
_T_LO = _TRIANGLE + T_LO
_T_HIT = _TRIANGLE + T_HIT
_SHEAR = _TRIANGLE + SHEAR
_SHEARED_ORIGIN = _TRIANGLE + SHEARED_ORIGIN
_U = _TRIANGLE + U
_V = _TRIANGLE + V
_CHILD = _TRIANGLE + TRIANGLE_ROWS
_STACK = _CHILD + 2
_ROWS = _STACK + STACK_SIZE
# Rows of a worker's integer lane array: those packet_setup writes (the shear axes and
# the octant), the hit primitive, then the counters (with statistics).
_AXES = KX
_PRIM, _STEPS, _NODES, _BOX, _PRIMS, _BYTES, _PEAK, _INT_ROWS = range(OCTANT + 1, OCTANT + 9)
_OCTANT = OCTANT


@dataclass(frozen=True, slots=True)
class PacketOptions:
    """Options of the ``bvh2.packet`` traversal (none yet; packets are sixteen rays)."""


def make_scratch_py(bvh):
    """Return one worker's stack references, leaf counts and integer lane state."""
    stack_ref = np.empty(STACK_SIZE, dtype=np.int32)
    stack_count = np.empty(STACK_SIZE, dtype=np.int32)
    lane_int = np.zeros((_INT_ROWS, PACKET), dtype=np.int64)
    return stack_ref, stack_count, lane_int


def popcount_py(mask):
    """Return the number of set bits of a lane mask."""
    n = 0
    for lane in range(PACKET):
        n += (mask >> lane) & 1
    return n


popcount = cpu_inline(popcount_py)


def share_py(lane_int, mask, column, amount):
    """Add ``amount``, divided among the lanes of ``mask``, to their counter ``column``."""
    each = amount // max(popcount(mask), 1)
    for lane in range(PACKET):
        if (mask >> lane) & 1:
            lane_int[column, lane] += each


share = cpu_inline(share_py)


def setup_packet_py(bvh, origin, direction, tmin, tmax, p0, end, lanes, lane_int, with_stats):
    """Compute the constants of rays ``p0:min(p0 + PACKET, end)``; return the lanes to trace.

    In vectors (:data:`rayaccel.kernels.ray_packet.packet_setup`). Lanes of degenerate
    rays and past ``end`` stay out of the returned mask. The scene box is tested only
    when the root is a leaf: otherwise a ray that misses it misses the root's children,
    which the packet's first step tests anyway.
    """
    pending = packet_setup(
        origin, direction, tmin, tmax, p0, end, bvh.root_box, lanes, _PAD, _TRIANGLE, lane_int
    )
    for lane in range(PACKET):
        lane_int[_PRIM, lane] = -1
        if with_stats:
            for k in range(_STEPS, _INT_ROWS):
                lane_int[k, lane] = 0
    if bvh.root_ref[0] < 0:
        # A leaf root has no row to test the scene box with: test it here.
        for lane in range(PACKET):
            if not (pending >> lane) & 1:
                continue
            octant = lane_int[_OCTANT, lane]
            nx = octant & 1
            ny = 2 + ((octant >> 1) & 1)
            nz = 4 + ((octant >> 2) & 1)
            pad = lanes[_PAD, lane]
            entry = root_entry(
                bvh.root_box, lanes[0, lane], lanes[1, lane], lanes[2, lane], lanes[3, lane],
                lanes[4, lane], lanes[5, lane], nx, ny, nz, 1 - nx, 5 - ny, 9 - nz,
                lanes[_T_LO, lane] - pad, lanes[_T_HIT, lane] + pad,
            )  # fmt: skip
            if with_stats:
                lane_int[_BOX, lane] = 1
            if entry == INF32:
                pending &= ~(1 << lane)
    return pending


setup_packet = cpu_inline(setup_packet_py)


def leaf_packet_py(bvh, first, count, mask, axes, lanes, lane_int, stop_at_first, with_stats):
    """:func:`leaf_lanes_py` for rays sharing their shear ``axes``: a vector test per triangle."""
    retired = 0
    last = first + count
    testing = mask
    for i in range(first, last):
        hit = packet_triangle(bvh.tri, i, axes[0], axes[1], axes[2], lanes, _TRIANGLE, testing)
        if hit == 0:
            continue
        for lane in range(PACKET):
            if (hit >> lane) & 1:
                lane_int[_PRIM, lane] = bvh.tri_prim[i]
                if stop_at_first and with_stats:
                    lane_int[_PRIMS, lane] += i - first + 1
        if stop_at_first:
            retired |= hit
            testing &= ~hit
            if testing == 0:
                break
    if with_stats:
        for lane in range(PACKET):
            if ((mask & ~retired) >> lane) & 1:
                lane_int[_PRIMS, lane] += count
    close_leaf(lanes, lane_int, count, mask, retired, with_stats)
    return retired


leaf_packet = cpu_inline(leaf_packet_py)


def close_leaf_py(lanes, lane_int, count, mask, retired, with_stats):
    """Move each ray's bound ``hi`` to its closest hit (``-inf``: retired); count the leaf."""
    for lane in range(PACKET):
        if (mask >> lane) & 1:
            lanes[HI_ROW, lane] = lanes[_T_HIT, lane] + lanes[_PAD, lane]
            if (retired >> lane) & 1:
                lanes[HI_ROW, lane] = -np.inf
            if with_stats:
                lane_int[_NODES, lane] += 1
    if with_stats:
        share(lane_int, mask, _BYTES, _PRIM_BYTES * count * popcount(mask))


close_leaf = cpu_inline(close_leaf_py)


def leaf_lanes_py(bvh, first, count, mask, lanes, lane_int, stop_at_first, with_stats):
    """Test triangles ``first:first + count`` for the rays of ``mask``; return the retired ones.

    Each ray keeps its nearest hit (a triangle replaces it only when strictly nearer,
    as :func:`rayaccel.trace.leaf.intersect_leaf_py`) and its culling bound ``hi``
    follows; with ``stop_at_first`` a ray that hits is retired (``hi = -inf``) and its
    bit is set in the returned mask. One ray at a time: for rays whose shear axes
    differ.
    """
    retired = 0
    last = first + count
    for lane in range(PACKET):
        if not (mask >> lane) & 1:
            continue
        kx = lane_int[_AXES, lane]
        ky = lane_int[_AXES + 1, lane]
        kz = lane_int[_AXES + 2, lane]
        Sx = lanes[_SHEAR, lane]
        Sy = lanes[_SHEAR + 1, lane]
        Sz = lanes[_SHEAR + 2, lane]
        okx = lanes[_SHEARED_ORIGIN, lane]
        oky = lanes[_SHEARED_ORIGIN + 1, lane]
        okz = lanes[_SHEARED_ORIGIN + 2, lane]
        t_lo = lanes[_T_LO, lane]
        t_hit = lanes[_T_HIT, lane]
        tested = count
        for i in range(first, last):
            t, u, v = ray_triangle(bvh.tri, i, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit)
            if t < t_hit:
                t_hit = t
                lane_int[_PRIM, lane] = bvh.tri_prim[i]
                lanes[_U, lane] = u
                lanes[_V, lane] = v
                if stop_at_first:
                    tested = i - first + 1
                    retired |= 1 << lane
                    break
        lanes[_T_HIT, lane] = t_hit
        if with_stats:
            lane_int[_PRIMS, lane] += tested
    close_leaf(lanes, lane_int, count, mask, retired, with_stats)
    return retired


leaf_lanes = cpu_inline(leaf_lanes_py)


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Trace rays ``begin:end`` through ``bvh`` (PairsArrays) in packets; return the overflows."""
    stack_ref, stack_count, lane_int = scratch
    box = bvh.box
    refs = bvh.ref
    # The packet's real-valued state, in the rays' precision (one allocation per chunk).
    lanes = np.empty((_ROWS, PACKET), dtype=origin.dtype)
    n_overflowed = 0
    for p0 in range(begin, end, PACKET):
        n_lanes = min(PACKET, end - p0)
        pending = setup_packet(
            bvh, origin, direction, tmin, tmax, p0, end, lanes, lane_int, with_stats
        )
        while pending != 0:
            # The rays of the lowest pending ray's octant traverse together.
            lead = trailing_zeros(pending)
            octant = lane_int[_OCTANT, lead]
            group = 0
            for lane in range(PACKET):
                if (pending >> lane) & 1 and lane_int[_OCTANT, lane] == octant:
                    group |= 1 << lane
                    lanes[LO_ROW, lane] = lanes[_T_LO, lane] - lanes[_PAD, lane]
                    lanes[HI_ROW, lane] = lanes[_T_HIT, lane] + lanes[_PAD, lane]
                else:
                    # Out of this descent: no box test passes for ``hi = -inf``.
                    lanes[HI_ROW, lane] = -np.inf
            pending &= ~group
            # Rays sharing the lead's shear axes test a leaf's triangles as one packet.
            axes = (lane_int[_AXES, lead], lane_int[_AXES + 1, lead], lane_int[_AXES + 2, lead])
            shared_axes = True
            for lane in range(PACKET):
                if (group >> lane) & 1 and (
                    lane_int[_AXES, lane] != axes[0] or lane_int[_AXES + 1, lane] != axes[1]
                ):
                    shared_axes = False
            nx = octant & 1
            ny = 2 + ((octant >> 1) & 1)
            nz = 4 + ((octant >> 2) & 1)
            near_x, far_x, near_y, far_y, near_z, far_z = lane_planes(
                2, nx, ny, nz, 1 - nx, 5 - ny, 9 - nz
            )
            alive = group
            node = bvh.root_ref[0]
            count = bvh.root_ref[1]
            mask = group
            sp = 0
            peak = 0
            done = False
            while not done:
                if node >= 0:
                    # Inner row: both children's boxes against every ray of the packet.
                    c0 = refs[node, REF_COLUMN]
                    c1 = refs[node, REF_COLUMN + 1]
                    prefetch_row(box, max(c0, 0))
                    prefetch_row(box, max(c1, 0))
                    m0 = packet_slab_test(
                        box, node, near_x, far_x, near_y, far_y, near_z, far_z, lanes, _CHILD
                    )
                    m1 = packet_slab_test(
                        box, node, near_x + 1, far_x + 1, near_y + 1, far_y + 1,
                        near_z + 1, far_z + 1, lanes, _CHILD + 1,
                    )  # fmt: skip
                    if with_stats:
                        for lane in range(PACKET):
                            if (alive >> lane) & 1:
                                lane_int[_STEPS, lane] += 1
                                lane_int[_NODES, lane] += 1
                                lane_int[_BOX, lane] += 2
                        share(lane_int, alive, _BYTES, PACKED_ROW_BYTES)
                    if m0 != 0 and m1 != 0:
                        # Both hit: the nearer for the lowest ray hitting both goes first.
                        if sp == STACK_SIZE:
                            n_overflowed += popcount(group)
                            break
                        lane = trailing_zeros(m0 & m1) if (m0 & m1) != 0 else trailing_zeros(m0)
                        near = 1 if lanes[_CHILD + 1, lane] < lanes[_CHILD, lane] else 0
                        far = 1 - near
                        stack_ref[sp] = refs[node, REF_COLUMN + far]
                        stack_count[sp] = refs[node, COUNT_COLUMN + far]
                        copy_lane_row(lanes, _CHILD + far, _STACK + sp)
                        sp += 1
                        peak = max(peak, sp)
                        if with_stats:
                            share(lane_int, alive, _BYTES, _STACK_ENTRY_BYTES)
                        mask = m1 if near == 1 else m0
                        count = refs[node, COUNT_COLUMN + near]
                        node = refs[node, REF_COLUMN + near]
                        continue
                    if m0 != 0:
                        mask = m0
                        count = refs[node, COUNT_COLUMN]
                        node = c0
                        continue
                    if m1 != 0:
                        mask = m1
                        count = refs[node, COUNT_COLUMN + 1]
                        node = c1
                        continue
                else:
                    # Leaf: its triangles for the rays that hit its box.
                    if with_stats:
                        for lane in range(PACKET):
                            if (mask >> lane) & 1:
                                lane_int[_STEPS, lane] += 1
                    if shared_axes:
                        retired = leaf_packet(
                            bvh, ~node, count, mask, axes, lanes, lane_int, query == QUERY_ANY,
                            with_stats,
                        )  # fmt: skip
                    else:
                        retired = leaf_lanes(
                            bvh, ~node, count, mask, lanes, lane_int, query == QUERY_ANY,
                            with_stats,
                        )  # fmt: skip
                    if query == QUERY_ANY:
                        alive &= ~retired
                        if alive == 0:
                            break
                # Pop the next entry still in front of some ray's closest hit.
                done = True
                while sp > 0:
                    sp -= 1
                    if with_stats:
                        share(lane_int, alive, _BYTES, _STACK_ENTRY_BYTES)
                    mask = lanes_at_most(lanes, _STACK + sp, HI_ROW)
                    if mask != 0:
                        node = stack_ref[sp]
                        count = stack_count[sp]
                        done = False
                        break
            if with_stats:
                for lane in range(PACKET):
                    if (group >> lane) & 1:
                        lane_int[_PEAK, lane] = peak
        for lane in range(n_lanes):
            r = p0 + lane
            if with_stats:
                store_counts(
                    counters, r, lane_int[_STEPS, lane], lane_int[_NODES, lane],
                    lane_int[_BOX, lane], lane_int[_PRIMS, lane], lane_int[_PEAK, lane],
                    lane_int[_BYTES, lane],
                )  # fmt: skip
            store_hit(
                hit_t, hit_prim, hit_u, hit_v, r, lanes[_T_HIT, lane], lane_int[_PRIM, lane],
                lanes[_U, lane], lanes[_V, lane],
            )  # fmt: skip
    return n_overflowed


make_scratch = cpu_inline(make_scratch_py)
#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(make_scratch, cpu_inline(trace_rays_py))


@register_traversal("bvh2.packet")
def trace_bvh2_packet(
    bvh: Bvh2, mesh: TriangleMesh, options: PacketOptions, cache: LayoutCache
) -> TracePlan:
    """Packets of 16 rays of one octant, vector box and triangle tests (coherent rays).

    Trace rays through a binary BVH in packets of sixteen consecutive rays.

    The pairs layout of ``bvh2.stack`` is derived from the canonical tree on first use
    and shared with it.

    Raises
    ------
    TraversalOverflowError
        Never for trees from rayaccel builders (depth is bounded by ``MAX_DEPTH``).

    References
    ----------
    Wald, Slusallek, Benthin, Wagner 2001, Interactive Rendering with Coherent Ray Tracing.
    """
    return pairs_plan(trace_kernel, bvh, mesh, cache)
