"""Packets of sixteen rays through the 8-wide (or the binary) rows of a BVH (``bvh2.packet``).

Wald, Slusallek, Benthin, Wagner 2001, "Interactive Rendering with Coherent Ray
Tracing"; the masked descent of Wald, Boulos, Shirley 2007 ("Ray Tracing Deformable
Scenes using Dynamic Bounding Volume Hierarchies", §4). Sixteen consecutive rays of a
batch form a packet; rays whose directions have the same signs (an octant) traverse
together: each row is fetched once for the packet and each child box is tested
against the sixteen rays in one ``<16 x float>`` slab test
(:data:`rayaccel.kernels.aabb_packet.packet_slab_test`). By default the rows are the
8-wide rows of ``bvh2.wide`` (:mod:`rayaccel.bvh.layouts.wide`; eight child boxes per
256-byte row, as Embree's BVH8 packets), so the default queries, single rays and
packets, need one layout; ``width=2`` descends the pairs rows of ``bvh2.stack``
(:mod:`rayaccel.bvh.layouts.pairs`, both children's boxes in 64 bytes). The packet
descends into a child if any of its rays hits it, nearest child first by the entry
distance of the lowest ray that reached the row (binary rows: the lowest ray that hits
both children); the others are pushed with every ray's entry distance, and a popped
entry goes on with the rays whose closest hit is still beyond their entry (none: it is
dropped unfetched). A leaf tests its triangles for the rays that hit its box: with one
vector form of the watertight test per triangle when those rays share their shear axes
(:mod:`rayaccel.kernels.triangle_packet`, bit-identical to the scalar test), else one
ray at a time with the single-ray traversals' test (:mod:`rayaccel.kernels.triangle`).
Rays of another octant in the same packet traverse as a packet of their own, so
incoherent rays (diffuse bounces) pay up to eight descents (one per octant) of a few
rays each: this traversal is for coherent batches (camera rays in image order, shadow
rays towards one light from neighbouring hits); queries that name no traversal take it
only for those (:mod:`rayaccel.rays.coherence`).

Results: every ray visits each leaf whose box it hits before its closest hit, with
the single-ray box test lane by lane, so the closest ``t`` is ``bvh2.stack``'s; the
visiting order follows the packet, so the primitive may differ at exact ties. Any-hit
queries (``query="any"``) retire a ray at its first hit and end the packet when
every ray is retired.

Counters (per ray, as its share of the packet's work): ``steps`` and ``nodes`` the
packet's rows and leaves the ray took part in (a leaf only if its box was hit),
``box_tests`` the row's children, ``prim_tests`` its own triangle tests, ``stack_peak`` the
deepest stack of its descent, ``bytes`` the rows, stack entries and triangles fetched,
divided among the rays that shared them.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from rayaccel._jit import cpu_inline, prefetch_row
from rayaccel.bvh.layouts.bvh2 import (
    MAX_DEPTH,
    PACKED_ROW_BYTES,
    REF_BYTES,
    STACK_SIZE,
    TRIANGLE_BYTES,
    Bvh2,
)
from rayaccel.bvh.layouts.pairs import COUNT_COLUMN, REF_COLUMN
from rayaccel.bvh.layouts.wide import count_column, ref_column, row_floats
from rayaccel.bvh.traverse.building_blocks import lane_planes
from rayaccel.bvh.traverse.stack import pairs_plan
from rayaccel.bvh.traverse.wide import wide_bvh
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.aabb_packet import (
    HI_ROW,
    LO_ROW,
    PACKET,
    copy_lane_row,
    lanes_at_most,
    packet_slab_test,
)
from rayaccel.kernels.ray_packet import KX, OCTANT, packet_setup
from rayaccel.kernels.real import in_precision_of
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
    """Options of the ``bvh2.packet`` traversal (packets are sixteen rays).

    Attributes
    ----------
    width : {8, 2}
        Children per row the packet descends through: 8, the wide rows of ``bvh2.wide``
        (the default queries then need no other layout), or 2, the pairs rows of
        ``bvh2.stack`` (Wald et al. 2001's binary descent).
    """

    width: int = 8

    def __post_init__(self) -> None:
        if self.width not in PACKET_WIDTHS:
            raise InvalidInputError(f"width: expected one of {PACKET_WIDTHS}, got {self.width}")


#: The row widths ``bvh2.packet`` descends through.
PACKET_WIDTHS = (2, 8)


def make_scratch_py(bvh):
    """Return one worker's stack references, leaf counts, integer and real lane state.

    The real-valued lanes come in both precisions; the body takes the rays'
    (:func:`rayaccel.kernels.real.in_precision_of`).
    """
    stack_ref = np.empty(STACK_SIZE, dtype=np.int32)
    stack_count = np.empty(STACK_SIZE, dtype=np.int32)
    lane_int = np.zeros((_INT_ROWS, PACKET), dtype=np.int64)
    lanes = (np.empty((_ROWS, PACKET), np.float32), np.empty((_ROWS, PACKET), np.float64))
    return stack_ref, stack_count, lane_int, lanes


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


def octant_planes_py(octant):
    """Return the interleaved near and far plane indices ``(nx, ny, nz, fx, fy, fz)`` of an octant.

    As :func:`rayaccel.trace.ray_setup.ray_prologue_py` picks them from the direction's
    signs (bit ``a`` of the octant set: negative along axis ``a``).
    """
    nx = octant & 1
    ny = 2 + ((octant >> 1) & 1)
    nz = 4 + ((octant >> 2) & 1)
    return nx, ny, nz, 1 - nx, 5 - ny, 9 - nz


octant_planes = cpu_inline(octant_planes_py)


def octant_columns_py(width, octant):
    """Return the near and far plane columns of a ``width``-lane row for an octant's rays."""
    nx, ny, nz, fx, fy, fz = octant_planes(octant)
    return lane_planes(width, nx, ny, nz, fx, fy, fz)


octant_columns = cpu_inline(octant_columns_py)


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
            nx, ny, nz, fx, fy, fz = octant_planes(lane_int[_OCTANT, lane])
            pad = lanes[_PAD, lane]
            entry = root_entry(
                bvh.root_box, lanes[0, lane], lanes[1, lane], lanes[2, lane], lanes[3, lane],
                lanes[4, lane], lanes[5, lane], nx, ny, nz, fx, fy, fz,
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


def start_group_py(pending, lanes, lane_int):
    """Start the descent of the lowest pending ray's octant.

    Opens the culling interval of the group's rays and closes every other lane's (no
    box test passes for ``hi = -inf``). Returns ``(group, octant, axes, shared_axes)``:
    the group's lanes, its octant, the lowest ray's shear axes and whether every ray of
    the group shares them (then a leaf's triangles are tested as one packet).
    """
    lead = trailing_zeros(pending)
    octant = lane_int[_OCTANT, lead]
    group = 0
    for lane in range(PACKET):
        if (pending >> lane) & 1 and lane_int[_OCTANT, lane] == octant:
            group |= 1 << lane
            lanes[LO_ROW, lane] = lanes[_T_LO, lane] - lanes[_PAD, lane]
            lanes[HI_ROW, lane] = lanes[_T_HIT, lane] + lanes[_PAD, lane]
        else:
            lanes[HI_ROW, lane] = -np.inf
    axes = (lane_int[_AXES, lead], lane_int[_AXES + 1, lead], lane_int[_AXES + 2, lead])
    shared_axes = True
    for lane in range(PACKET):
        if (group >> lane) & 1 and (
            lane_int[_AXES, lane] != axes[0] or lane_int[_AXES + 1, lane] != axes[1]
        ):
            shared_axes = False
    return group, octant, axes, shared_axes


start_group = cpu_inline(start_group_py)


def visit_leaf_py(bvh, first, count, mask, axes, shared_axes, lanes, lane_int, stop_at_first,
                  with_stats):  # fmt: skip
    """Test triangles ``first:first + count`` for the rays of ``mask``; return the retired ones."""
    if with_stats:
        for lane in range(PACKET):
            if (mask >> lane) & 1:
                lane_int[_STEPS, lane] += 1
    if shared_axes:
        return leaf_packet(
            bvh, first, count, mask, axes, lanes, lane_int, stop_at_first, with_stats
        )
    return leaf_lanes(bvh, first, count, mask, lanes, lane_int, stop_at_first, with_stats)


visit_leaf = cpu_inline(visit_leaf_py)


def pop_entry_py(lanes, lane_int, sp, stack_row, alive, with_stats):
    """Pop entries until one is still in front of some ray's closest hit.

    Returns ``(sp, mask)``: the entry's index and the rays that go on there, or a zero
    mask when the stack is empty.
    """
    while sp > 0:
        sp -= 1
        if with_stats:
            share(lane_int, alive, _BYTES, _STACK_ENTRY_BYTES)
        mask = lanes_at_most(lanes, stack_row + sp, HI_ROW)
        if mask != 0:
            return sp, mask
    return 0, 0


pop_entry = cpu_inline(pop_entry_py)


def finish_group_py(lane_int, group, peak, with_stats):
    """Record the deepest stack of the group's descent for its rays."""
    if with_stats:
        for lane in range(PACKET):
            if (group >> lane) & 1:
                lane_int[_PEAK, lane] = peak


finish_group = cpu_inline(finish_group_py)


def store_packet_py(p0, n_lanes, lanes, lane_int, hit_t, hit_prim, hit_u, hit_v, counters,
                    with_stats):  # fmt: skip
    """Store the hits (and counters) of rays ``p0:p0 + n_lanes`` from the packet's lanes."""
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


store_packet = cpu_inline(store_packet_py)


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Trace rays ``begin:end`` through ``bvh`` (PairsArrays) in packets; return the overflows."""
    stack_ref, stack_count, lane_int, both_lanes = scratch
    box = bvh.box
    refs = bvh.ref
    # The packet's real-valued state, in the rays' precision.
    lanes = in_precision_of(origin, both_lanes[0], both_lanes[1])
    n_overflowed = 0
    for p0 in range(begin, end, PACKET):
        n_lanes = min(PACKET, end - p0)
        pending = setup_packet(
            bvh, origin, direction, tmin, tmax, p0, end, lanes, lane_int, with_stats
        )
        while pending != 0:
            # The rays of the lowest pending ray's octant traverse together.
            group, octant, axes, shared_axes = start_group(pending, lanes, lane_int)
            pending &= ~group
            near_x, far_x, near_y, far_y, near_z, far_z = octant_columns(2, octant)
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
                    retired = visit_leaf(
                        bvh, ~node, count, mask, axes, shared_axes, lanes, lane_int,
                        query == QUERY_ANY, with_stats,
                    )  # fmt: skip
                    if query == QUERY_ANY:
                        alive &= ~retired
                        if alive == 0:
                            break
                # Pop the next entry still in front of some ray's closest hit.
                sp, mask = pop_entry(lanes, lane_int, sp, _STACK, alive, with_stats)
                done = mask == 0
                if not done:
                    node = stack_ref[sp]
                    count = stack_count[sp]
            finish_group(lane_int, group, peak, with_stats)
        store_packet(p0, n_lanes, lanes, lane_int, hit_t, hit_prim, hit_u, hit_v, counters,
                     with_stats)  # fmt: skip
    return n_overflowed


@functools.cache
def wide_packet_body(width: int) -> tuple[Any, Any]:
    """Return the ``(make_scratch, trace_rays)`` inline pair of packets over ``width``-wide rows.

    The descent of :func:`trace_rays_py` over the wide rows of ``bvh2.wide``
    (:mod:`rayaccel.bvh.layouts.wide`): a row's children are each tested against the
    packet's rays, the hit ones visited nearest first for the lowest ray of the packet
    that reached the row (children it misses last, in lane order), the others pushed
    with every ray's entry distance. ``width`` and the sizes it fixes are compile-time
    constants of the body.
    """
    ref_col = ref_column(width)
    count_col = count_column(width)
    row_bytes = 4 * row_floats(width)
    # A row pushes at most width - 1 entries, a path crosses at most MAX_DEPTH rows.
    stack_size = (width - 1) * MAX_DEPTH + 1
    child_row = _CHILD
    stack_row = _CHILD + width
    n_rows = stack_row + stack_size

    def make_scratch_py(bvh):
        """Return one worker's stack references, integer and real lane state (both precisions)."""
        stack_ref = np.empty(stack_size, dtype=np.int32)
        lane_int = np.zeros((_INT_ROWS, PACKET), dtype=np.int64)
        lanes = (np.empty((n_rows, PACKET), np.float32), np.empty((n_rows, PACKET), np.float64))
        return stack_ref, lane_int, lanes

    def trace_rays_py(
        bvh, scratch, origin, direction, tmin, tmax, begin, end,
        hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
    ):  # fmt: skip
        """Trace rays ``begin:end`` through ``bvh`` (WideArrays) in packets; return overflows."""
        stack_ref, lane_int, both_lanes = scratch
        box = bvh.box
        refs = bvh.ref
        lanes = in_precision_of(origin, both_lanes[0], both_lanes[1])
        n_overflowed = 0
        for p0 in range(begin, end, PACKET):
            n_lanes = min(PACKET, end - p0)
            pending = setup_packet(
                bvh, origin, direction, tmin, tmax, p0, end, lanes, lane_int, with_stats
            )
            while pending != 0:
                group, octant, axes, shared_axes = start_group(pending, lanes, lane_int)
                pending &= ~group
                near_x, far_x, near_y, far_y, near_z, far_z = octant_columns(width, octant)
                alive = group
                node = bvh.root_ref[0]
                mask = group
                sp = 0
                peak = 0
                done = False
                while not done:
                    if node >= 0:
                        # Every child box against the packet; hit ones sorted by the
                        # entry distance of the lowest ray that reached this row.
                        n_children = refs[node, count_col]
                        hits = 0
                        for c in range(n_children):
                            m = packet_slab_test(
                                box, node, near_x + c, far_x + c, near_y + c, far_y + c,
                                near_z + c, far_z + c, lanes, child_row + c,
                            )  # fmt: skip
                            if m != 0:
                                hits |= 1 << c
                        if with_stats:
                            for lane in range(PACKET):
                                if (alive >> lane) & 1:
                                    lane_int[_STEPS, lane] += 1
                                    lane_int[_NODES, lane] += 1
                                    lane_int[_BOX, lane] += n_children
                            share(lane_int, alive, _BYTES, row_bytes)
                        if hits != 0:
                            # The farther children go on the stack, farthest first, by the
                            # entry distance of the lowest ray that reached this row (lane
                            # order among equals); the nearest is visited next.
                            first_ray = trailing_zeros(mask)
                            n_pushed = 0
                            while hits & (hits - 1) != 0:
                                if sp == stack_size:
                                    break
                                if query == QUERY_ANY:
                                    # Any hit ends a ray: lane order, no sort.
                                    far = 31 - leading_zeros(np.uint32(hits))
                                else:
                                    far = -1
                                    far_key = -np.inf
                                    rest = hits
                                    while rest != 0:
                                        c = trailing_zeros(rest)
                                        rest &= rest - 1
                                        key = lanes[child_row + c, first_ray]
                                        if key >= far_key:
                                            far_key = key
                                            far = c
                                stack_ref[sp] = refs[node, ref_col + far]
                                copy_lane_row(lanes, child_row + far, stack_row + sp)
                                sp += 1
                                n_pushed += 1
                                hits &= ~(1 << far)
                            if hits & (hits - 1) != 0:
                                n_overflowed += popcount(group)
                                break
                            if with_stats and n_pushed > 0:
                                peak = max(peak, sp)
                                share(lane_int, alive, _BYTES, _STACK_ENTRY_BYTES * n_pushed)
                            near = trailing_zeros(hits)
                            mask = lanes_at_most(lanes, child_row + near, HI_ROW)
                            node = refs[node, ref_col + near]
                            if node >= 0:
                                prefetch_row(box, node)
                            continue
                    else:
                        leaf = ~node
                        retired = visit_leaf(
                            bvh, bvh.leaf_first[leaf], bvh.leaf_count[leaf], mask, axes,
                            shared_axes, lanes, lane_int, query == QUERY_ANY, with_stats,
                        )  # fmt: skip
                        if query == QUERY_ANY:
                            alive &= ~retired
                            if alive == 0:
                                break
                    # Pop the next entry still in front of some ray's closest hit.
                    sp, mask = pop_entry(lanes, lane_int, sp, stack_row, alive, with_stats)
                    done = mask == 0
                    if not done:
                        node = stack_ref[sp]
                finish_group(lane_int, group, peak, with_stats)
            store_packet(p0, n_lanes, lanes, lane_int, hit_t, hit_prim, hit_u, hit_v, counters,
                         with_stats)  # fmt: skip
        return n_overflowed

    return cpu_inline(make_scratch_py), cpu_inline(trace_rays_py)


@functools.cache
def wide_packet_kernels(width: int) -> Any:
    """Return ``kernel_for(query, with_stats, parallel)``: the compiled ``width``-wide variants."""
    return body_kernels(*wide_packet_body(width))


make_scratch = cpu_inline(make_scratch_py)
#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(make_scratch, cpu_inline(trace_rays_py))


@register_traversal("bvh2.packet")
def trace_bvh2_packet(
    bvh: Bvh2, mesh: TriangleMesh, options: PacketOptions, cache: LayoutCache
) -> TracePlan:
    """Packets of 16 rays of one octant, vector box and triangle tests (coherent rays).

    Trace rays through a binary BVH in packets of sixteen consecutive rays.

    The rows it reads (the 8-wide rows of ``bvh2.wide``, or with ``width=2`` the pairs
    rows of ``bvh2.stack``) are derived from the canonical tree on first use and shared
    with that traversal.

    Raises
    ------
    TraversalOverflowError
        Never for trees from rayaccel builders (depth is bounded by ``MAX_DEPTH``).

    References
    ----------
    Wald, Slusallek, Benthin, Wagner 2001, Interactive Rendering with Coherent Ray Tracing;
    Wald, Benthin, Boulos 2008, Getting Rid of Packets (the wide rows).
    """
    if options.width == 2:
        return pairs_plan(trace_kernel, bvh, mesh, cache)
    wide = wide_bvh(bvh, mesh, cache, options.width)
    hint = f"the tree is deeper than its stack allows ({MAX_DEPTH} rows, MAX_DEPTH)"
    return TracePlan(wide_packet_kernels(options.width), wide.arrays(), hint)
