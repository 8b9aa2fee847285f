"""The top-down kd-tree build by sorted events (Wald & Havran 2006), shared by both builders.

Wald & Havran 2006, "On building fast kd-Trees for Ray Tracing, and on doing that
in O(N log N)" (IEEE Symposium on Interactive Ray Tracing).

Events. Each triangle contributes, per axis, the extent of its bounds in the node's
cell: a *start* event at the low end and an *end* event at the high end, or one
*planar* event when the two coincide. A node's events are kept sorted by
``(axis, position, type)`` with ``end < planar < start``. They are sorted **once**,
at the root (numpy's stable lexsort); below, each child's list is spliced from its
parent's.

Sweep (``kdtree.sah``). Per axis, walking the distinct positions ``p`` in order
with ``N_L = 0, N_R = N``: count the ends ``p−``, planars ``p|`` and starts ``p+`` at
``p``; ``N_R -= p| + p−``; evaluate the split at ``p`` with the planar triangles put
left and put right (keeping the cheaper); ``N_L += p+ + p|``. The cost of a split is
``λ·(K_T + K_I·(P_L·N_L + P_R·N_R))`` with ``P = SA(child)/SA(cell)`` and ``λ`` the
empty-space bonus when one side is empty (§4.1), against ``K_I·N`` for a leaf. Only
planes strictly inside the cell are candidates (pbrt), so no child equals its
parent and the build terminates; the depth cap ``8 + 1.3·log2 N`` (pbrt) is a
safety net that also bounds every traversal stack.

Duplication budget. The depth cap alone bounds the tree only by ``2^depth``
cells, about ``256·N^1.3``: long thin triangles crossing many cells (a fan of
slivers around one vertex) make a median or SAH tree whose references grow as
``N²``: a 4000-triangle fan got 5.2M references from ``kdtree.median`` (1.2
billion and 19 minutes without perfect splits), and 100k triangles held 5 GB
after 8 minutes unfinished. A split
multiplies the references of its node by ``δ = (N_L + N_R) / N``; a node is split
only while the product of the ``δ`` along its path, this split's included, stays
at most ``max_duplication``. The references at any depth then sum to at most
``max_duplication·N``. The rule depends on the path alone, so the tree does not
depend on the thread count. On the benchmark scenes the default (64) stops only a
few splits of small nodes whose triangles all straddle the plane: ``kdtree.sah``
keeps 93-100% of its references and its SAH cost within 0.01% (sponza, living
room, bunny, teapot), with the same triangle tests and nodes per ray.

Classification and splicing (§4.3). Walking the chosen axis's events: a triangle
whose end is ``<= p`` (or planar below ``p``) is left-only; whose start is ``>= p``
(or planar above) is right-only; planar *at* ``p`` goes to the side the sweep chose;
every other triangle straddles the plane and goes to both. Left- and right-only
triangles keep their events, already in order. Each straddling triangle is clipped
to each child cell (Sutherland–Hodgman, :func:`rayaccel.kernels.clip.clip_triangle_box`,
bounds rounded outward): these *perfect splits* (Havran 2000) bound the part of the
triangle in the child, not its whole box. Their new events (few: O(√N) straddle a
plane in a typical scene) are sorted and merged with the kept ones, so each node
costs time linear in its events and the whole build O(N log N). Without perfect
splits (``perfect_splits=False``, the thesis's KD_no_ps) the new bounds are the
triangle's box cut by the child cell. A straddling triangle whose part on one side
clips to nothing (its box straddles the plane, the triangle does not) goes to the
other side only.

A triangle touching a plane only from one side, or lying in it, is therefore listed on
one side only; the traversals visit closed cells so a ray meeting it on the plane
still finds it (:mod:`rayaccel.kdtree.traverse`).

Parallelism. Below the top levels the subtrees are independent: the serial
kernel stops at nodes of at most ``max(parallel_threshold, N/64)`` triangles and
hands them (with a copy of their events) to a thread pool, one kernel call per
subtree, largest first (:func:`_build_frontier`); the subtrees are spliced in a
fixed order, so the tree is the same for every thread count, and the same as the
serial build's up to node numbering (each node's plane depends only on its events).
The finished tree is renumbered into cache blocks
(:func:`rayaccel.kdtree.layouts.node_order.blocked_node_order`), which makes the
numbering the same too.

Memory. Event lists live in one buffer used as a stack: a split writes the right
child's list, then the left child's, after its own; the left child (popped first)
writes its children after that, and the space is reused when a subtree is done.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.dtypes import REAL
from rayaccel.kdtree.layouts.kdtree import LEAF_AXIS, KdTree, max_depth_for
from rayaccel.kdtree.layouts.node_order import blocked_node_order
from rayaccel.kernels.box_grow import store_box
from rayaccel.kernels.clip import clip_triangle_box, polygon_bounds
from rayaccel.kernels.radix_sort import radix_sort
from rayaccel.scene.mesh import TriangleMesh

#: Event types, in sort order at one position.
END = 0
PLANAR = 1
START = 2

#: Default duplication budget of both kd builders (see the module docstring).
MAX_DUPLICATION = 64.0

#: Plane choice: the surface area heuristic over all events, or the cell's spatial median.
MODE_SAH = 0
MODE_MEDIAN = 1

_LEFT = 1
_RIGHT = 2
_BOTH = 3


class SweepParams(NamedTuple):
    """Build parameters as one kernel argument."""

    mode: int
    traversal_cost: float
    intersection_cost: float
    empty_bonus: float
    max_depth: int
    max_leaf_size: int
    perfect_splits: bool
    #: Subtrees of at most ``max(parallel_threshold, N // 64)`` triangles are built
    #: concurrently after the top levels; 0 builds serially.
    parallel_threshold: int = 0
    #: Absolute outward padding of clipped bounds (set by :func:`build_sweep`).
    round_pad: float = 0.0
    #: Largest product of the splits' duplication factors along a path (see above).
    max_duplication: float = np.inf


#: Key of an unused event slot (a planar triangle's second one): above every real key.
_NO_EVENT = 3 << 34


def initial_events(tri: np.ndarray) -> tuple[np.ndarray, ...]:
    """Return the root's events ``(pos, type, axis, prim)``, sorted by (axis, pos, type).

    Each event is one 36-bit key (axis, the position's bits in float order, type),
    sorted stably by the parallel radix sort; equal keys keep triangle order, as a
    lexsort on (axis, pos, type) would. The keys decode back to the events.
    """
    keys, prims = _event_keys(np.ascontiguousarray(tri, dtype=REAL).view(np.int32))
    keys, prims = radix_sort(keys, prims, 36)
    count = int(np.searchsorted(keys, _NO_EVENT))
    pos_bits, typ, axis = _decode_events(keys[:count])
    return pos_bits.view(REAL), typ, axis, np.ascontiguousarray(prims[:count])


@cpu_kernel(parallel=True)
def _event_keys(tri_bits):
    """Return the sort keys and triangle ids of each triangle's events, six slots each.

    ``tri_bits`` is the float32 corner array viewed as int32: the key holds the
    bits of the corner that bounds the triangle on an axis (``-0.0`` as ``+0.0``), in
    an order that sorts like the float. Slots ``6t + 2a`` and ``6t + 2a + 1`` hold
    triangle ``t``'s start and end on axis ``a``, or its planar event and
    :data:`_NO_EVENT`.
    """
    n = tri_bits.shape[0]
    keys = np.empty(6 * n, dtype=np.int64)
    prims = np.empty(6 * n, dtype=np.int32)
    for t in prange(n):
        for a in range(3):
            lo = tri_bits[t, 0, a]
            hi = lo
            for v in range(1, 3):
                b = tri_bits[t, v, a]
                if _float_order(b) < _float_order(lo):
                    lo = b
                if _float_order(b) > _float_order(hi):
                    hi = b
            slot = 6 * t + 2 * a
            prims[slot] = t
            prims[slot + 1] = t
            if _float_order(lo) == _float_order(hi):
                keys[slot] = _event_key(a, lo, PLANAR)
                keys[slot + 1] = _NO_EVENT
            else:
                keys[slot] = _event_key(a, lo, START)
                keys[slot + 1] = _event_key(a, hi, END)
    return keys, prims


@cpu_inline
def _float_order(bits):
    """Return float32 ``bits`` (as int32) as an int64 in the float's order, ``-0.0 == +0.0``."""
    u = np.int64(bits) & 0xFFFFFFFF
    if u == 0x80000000:
        u = np.int64(0)
    if u >= 0x80000000:
        return (~u) & 0xFFFFFFFF
    return u | 0x80000000


@cpu_inline
def _event_key(axis, bits, kind):
    """Return the sort key of an event on ``axis`` at the float32 ``bits`` of type ``kind``."""
    return (np.int64(axis) << 34) | (_float_order(bits) << 2) | np.int64(kind)


@cpu_kernel(parallel=True)
def _decode_events(keys):
    """Return ``(position bits as int32, type, axis)`` of sorted event keys."""
    m = keys.shape[0]
    pos_bits = np.empty(m, dtype=np.int32)
    typ = np.empty(m, dtype=np.int8)
    axis = np.empty(m, dtype=np.int8)
    for i in prange(m):
        key = keys[i]
        ordered = (key >> 2) & 0xFFFFFFFF
        if ordered >= 0x80000000:
            u = ordered & 0x7FFFFFFF
        else:
            u = (~ordered) & 0xFFFFFFFF
        pos_bits[i] = np.int32(u - (np.int64(1) << 32) if u >= 0x80000000 else u)
        typ[i] = np.int8(key & 3)
        axis[i] = np.int8(key >> 34)
    return pos_bits, typ, axis


def build_sweep(mesh: TriangleMesh, params: SweepParams) -> KdTree:
    """Build a kd-tree over ``mesh`` with the event sweep (see the module docstring)."""
    tri = np.ascontiguousarray(mesh.triangles(), dtype=REAL)
    n = tri.shape[0]
    lo, hi = mesh.bounds()
    lo = np.ascontiguousarray(lo, dtype=REAL)
    hi = np.ascontiguousarray(hi, dtype=REAL)
    pos, typ, axis, prim = initial_events(tri)
    max_depth = min(int(params.max_depth), max_depth_for(n))
    # Clipped bounds are padded by the float64 error of the crossing points, which
    # is relative to the scene's coordinates (see ``polygon_bounds_py``).
    scale = max(float(np.abs(lo).max()), float(np.abs(hi).max()))
    params = params._replace(max_depth=max_depth, round_pad=scale * 2.0**-40)
    threshold = int(params.parallel_threshold)
    task_prims = max(threshold, n // 64) if 0 < threshold < n else 0
    top = _build_kernel(tri, lo, hi, pos, typ, axis, prim, params, n, 0, 1.0, task_prims)
    tree, tasks = top[:5], top[5:]
    if tasks[0].size:
        tree = _build_frontier(tri, params, tree, *tasks)
    split, bits, leaf_first, leaf_count, prim_index = tree
    nodes = np.empty((split.shape[0], 2), dtype=REAL)
    nodes[:, 0] = split
    nodes.view(np.int32)[:, 1] = bits
    return KdTree(
        nodes=blocked_node_order(nodes),
        leaf_first=leaf_first,
        leaf_count=leaf_count,
        prim_index=prim_index,
        lo=lo,
        hi=hi,
        n_prims=n,
        perfect_splits=bool(params.perfect_splits),
    )


def _build_frontier(
    tri: np.ndarray,
    params: SweepParams,
    top: tuple[np.ndarray, ...],
    t_node: np.ndarray,
    t_n: np.ndarray,
    t_depth: np.ndarray,
    t_dup: np.ndarray,
    t_cell: np.ndarray,
    t_range: np.ndarray,
    *events: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """Build the frontier subtrees concurrently and splice them into the top tree.

    Each task is a kernel call (``nogil``) on a thread of a pool of
    ``numba.get_num_threads()``, largest first. The STYLE's ``prange`` over a
    frontier with prefix-sum allocation does not fit here: a subtree's node and
    reference counts are unknown until it is built (perfect splits duplicate
    references), so each subtree builds into its own arrays. They are spliced in
    task order, so the tree does not depend on the thread count: subtree ``i``'s
    root fills the top tree's node ``t_node[i]``, its other nodes, leaves and
    references are appended, and its child and leaf indices shifted accordingly.
    """

    def build_task(i: int) -> tuple[np.ndarray, ...]:
        a, b = t_range[2 * i], t_range[2 * i + 1]
        cell = t_cell[6 * i : 6 * i + 6]
        subtree: tuple[np.ndarray, ...] = _build_kernel(
            tri, cell[:3], cell[3:], *(e[a:b] for e in events), params, int(t_n[i]),
            int(t_depth[i]), float(t_dup[i]), 0,
        )[:5]  # fmt: skip
        return subtree

    largest_first = [int(i) for i in np.argsort(-t_n, kind="stable")]
    with ThreadPoolExecutor(max_workers=numba.get_num_threads()) as pool:
        built = dict(zip(largest_first, pool.map(build_task, largest_first), strict=True))
    split, bits, first, count, prims = (np.array(a) for a in top)
    parts = [[split], [bits], [first], [count], [prims]]
    n_nodes, n_leaves, n_refs = split.size, first.size, prims.size
    for i in range(t_node.size):
        s_split, s_bits, s_first, s_count, s_prims = built[i]
        leaf = (s_bits & 3) == LEAF_AXIS
        payload = (s_bits >> 2).astype(np.int64)
        payload = np.where(leaf, payload + n_leaves, payload - 1 + n_nodes)
        s_bits = ((payload << 2) | (s_bits & 3)).astype(np.int32)
        split[t_node[i]] = s_split[0]
        bits[t_node[i]] = s_bits[0]
        for part, new in zip(
            parts, (s_split[1:], s_bits[1:], s_first + n_refs, s_count, s_prims), strict=True
        ):
            part.append(new)
        n_nodes += s_split.size - 1
        n_leaves += s_first.size
        n_refs += s_prims.size
    spliced: tuple[np.ndarray, ...] = tuple(
        np.ascontiguousarray(np.concatenate(part)) for part in parts
    )
    return spliced


@cpu_inline
def _grow_f(a, need):
    """Return ``a`` or a copy at least ``need`` long (doubling); inlined, for any dtype."""
    if need <= a.shape[0]:
        return a
    b = np.empty(max(need, 2 * a.shape[0]), dtype=a.dtype)
    b[: a.shape[0]] = a
    return b


@cpu_inline
def _new_events(n):
    """Return uninitialised event arrays ``(pos, typ, axis, prim)`` for ``n`` events."""
    return (
        np.empty(n, dtype=np.float32),
        np.empty(n, dtype=np.int8),
        np.empty(n, dtype=np.int8),
        np.empty(n, dtype=np.int32),
    )


@cpu_inline
def _grow_events(pos, typ, axis, prim, need):
    """Return the event arrays, each grown to at least ``need`` (:func:`_grow_f`)."""
    return _grow_f(pos, need), _grow_f(typ, need), _grow_f(axis, need), _grow_f(prim, need)


@cpu_inline
def _copy_events(pos, typ, axis, prim, at, from_pos, from_typ, from_axis, from_prim, begin, end):
    """Copy events ``begin:end`` of the ``from_*`` arrays to the event arrays from ``at``."""
    stop = at + (end - begin)
    pos[at:stop] = from_pos[begin:end]
    typ[at:stop] = from_typ[begin:end]
    axis[at:stop] = from_axis[begin:end]
    prim[at:stop] = from_prim[begin:end]


@cpu_inline
def _set_event(pos, typ, axis, prim, j, p, t, a, pr):
    """Write event ``j``: position ``p``, type ``t``, axis ``a``, triangle ``pr``."""
    pos[j] = p
    typ[j] = t
    axis[j] = a
    prim[j] = pr


@cpu_inline
def _axis_range(axis, begin, end, k):
    """Return the range of events ``begin:end`` on axis ``k`` (sorted by axis first)."""
    lo = begin
    hi = end
    while lo < hi:  # the first event on an axis >= k
        mid = (lo + hi) >> 1
        if axis[mid] < k:
            lo = mid + 1
        else:
            hi = mid
    first = lo
    hi = end
    while lo < hi:  # the first event on an axis > k
        mid = (lo + hi) >> 1
        if axis[mid] <= k:
            lo = mid + 1
        else:
            hi = mid
    return first, lo


#: New-event segments up to this long are sorted in place (no allocation per node).
_INSERTION_SORT_MAX = 48


@cpu_inline
def _insertion_sort_events(pos, typ, prim, begin, end):
    """Sort events ``begin:end`` (one axis) by ``(position, type)`` in place, stably."""
    for i in range(begin + 1, end):
        p = pos[i]
        t = typ[i]
        pr = prim[i]
        j = i - 1
        while j >= begin and (pos[j] > p or (pos[j] == p and typ[j] > t)):
            pos[j + 1] = pos[j]
            typ[j + 1] = typ[j]
            prim[j + 1] = prim[j]
            j -= 1
        pos[j + 1] = p
        typ[j + 1] = t
        prim[j + 1] = pr


@cpu_kernel()
def _half_area(lo0, lo1, lo2, hi0, hi1, hi2):
    ex = np.float64(hi0) - lo0
    ey = np.float64(hi1) - lo1
    ez = np.float64(hi2) - lo2
    return ex * ey + ey * ez + ez * ex


@cpu_kernel()
def _less(a0, p0, t0, a1, p1, t1):
    """Event order: axis, then position, then type."""
    if a0 != a1:
        return a0 < a1
    if p0 != p1:
        return p0 < p1
    return t0 < t1


@cpu_kernel()
def _build_kernel(
    tri, scene_lo, scene_hi, pos0, typ0, axis0, prim0, params, n0, depth0, dup0, task_prims
):
    """Build the subtree of a cell with ``n0`` triangles at depth ``depth0`` from its events.

    ``dup0`` is the product of the duplication factors on the path to the cell (1 at
    the root; see the module docstring).

    With ``task_prims > 0`` a node below the root with at most ``task_prims``
    triangles is not split but recorded as a frontier task (its node, triangle
    count, depth, cell and a copy of its events) for :func:`build_sweep` to build
    concurrently. Returns the tree's arrays, then the tasks'.
    """
    n_prims = tri.shape[0]
    k_t = params.traversal_cost
    k_i = params.intersection_cost
    bonus = params.empty_bonus
    max_depth = params.max_depth
    # Event buffer used as a stack (see the module docstring).
    cap = max(3 * pos0.shape[0], 16)
    e_pos, e_typ, e_axis, e_prim = _new_events(cap)
    m0 = pos0.shape[0]
    _copy_events(e_pos, e_typ, e_axis, e_prim, 0, pos0, typ0, axis0, prim0, 0, m0)
    # Per-node scratch (grown as needed): new events of one child, sides, clipping buffers.
    n_pos, n_typ, n_axis, n_prim = _new_events(1536)
    side = np.zeros(n_prims, dtype=np.int8)
    poly = np.empty((16, 3), dtype=np.float64)
    poly_tmp = np.empty((16, 3), dtype=np.float64)
    c_lo = np.empty(3, dtype=np.float32)
    c_hi = np.empty(3, dtype=np.float32)
    bounds = np.empty(6, dtype=np.float32)
    box_lo = np.empty(3, dtype=np.float32)
    box_hi = np.empty(3, dtype=np.float32)
    both_bounds = np.empty((256, 6), dtype=np.float32)
    keep = np.empty(256, dtype=np.int8)
    straddling = np.empty(256, dtype=np.int32)
    o_lo = np.empty(3, dtype=np.float32)
    o_hi = np.empty(3, dtype=np.float32)
    # Output, grown as needed.
    out_split = np.empty(1024, dtype=np.float32)
    out_bits = np.empty(1024, dtype=np.int32)
    out_first = np.empty(512, dtype=np.int32)
    out_count = np.empty(512, dtype=np.int32)
    out_prims = np.empty(max(n_prims, 16), dtype=np.int32)
    n_nodes = 1
    n_leaves = 0
    n_refs = 0
    # Work stack: node, event range, prim count, depth, cell.
    stack_cap = max_depth + 4
    s_node = np.empty(stack_cap, dtype=np.int32)
    s_begin = np.empty(stack_cap, dtype=np.int64)
    s_end = np.empty(stack_cap, dtype=np.int64)
    s_n = np.empty(stack_cap, dtype=np.int32)
    s_depth = np.empty(stack_cap, dtype=np.int32)
    s_dup = np.empty(stack_cap, dtype=np.float64)
    s_lo = np.empty((stack_cap, 3), dtype=np.float32)
    s_hi = np.empty((stack_cap, 3), dtype=np.float32)
    s_node[0] = 0
    s_begin[0] = 0
    s_end[0] = m0
    s_n[0] = n0
    s_depth[0] = depth0
    s_dup[0] = dup0
    # Frontier tasks: node, triangles, depth, cell (6 floats each), event range.
    n_tasks = 0
    n_task_events = 0
    t_node = np.empty(16, dtype=np.int32)
    t_n = np.empty(16, dtype=np.int32)
    t_depth = np.empty(16, dtype=np.int32)
    t_dup = np.empty(16, dtype=np.float64)
    t_cell = np.empty(96, dtype=np.float32)
    t_range = np.empty(32, dtype=np.int64)
    tp_pos, tp_typ, tp_axis, tp_prim = _new_events(16)
    for a in range(3):
        s_lo[0, a] = scene_lo[a]
        s_hi[0, a] = scene_hi[a]
    sp = 1
    while sp > 0:
        sp -= 1
        node = s_node[sp]
        begin = s_begin[sp]
        end = s_end[sp]
        n = s_n[sp]
        depth = s_depth[sp]
        dup = s_dup[sp]
        for a in range(3):
            c_lo[a] = s_lo[sp, a]
            c_hi[a] = s_hi[sp, a]
        if task_prims > 0 and depth > depth0 and n <= task_prims:
            # ---- a frontier subtree, built later (concurrently)
            if n_tasks == t_node.shape[0]:
                t_node = _grow_f(t_node, n_tasks + 1)
                t_n = _grow_f(t_n, n_tasks + 1)
                t_depth = _grow_f(t_depth, n_tasks + 1)
                t_dup = _grow_f(t_dup, n_tasks + 1)
            t_cell = _grow_f(t_cell, 6 * (n_tasks + 1))
            t_range = _grow_f(t_range, 2 * (n_tasks + 1))
            stop = n_task_events + (end - begin)
            tp_pos, tp_typ, tp_axis, tp_prim = _grow_events(tp_pos, tp_typ, tp_axis, tp_prim, stop)
            _copy_events(
                tp_pos, tp_typ, tp_axis, tp_prim, n_task_events, e_pos, e_typ, e_axis, e_prim,
                begin, end,
            )  # fmt: skip
            t_node[n_tasks] = node
            t_n[n_tasks] = n
            t_depth[n_tasks] = depth
            t_dup[n_tasks] = dup
            for a in range(3):
                t_cell[6 * n_tasks + a] = c_lo[a]
                t_cell[6 * n_tasks + 3 + a] = c_hi[a]
            t_range[2 * n_tasks] = n_task_events
            t_range[2 * n_tasks + 1] = stop
            n_task_events = stop
            n_tasks += 1
            continue
        # ---- choose a plane
        best_axis = -1
        best_pos = np.float32(0.0)
        best_side = _LEFT
        area = _half_area(c_lo[0], c_lo[1], c_lo[2], c_hi[0], c_hi[1], c_hi[2])
        can_split = n > 0 and depth < max_depth
        if can_split and params.mode == MODE_SAH and area > 0:
            best_cost = np.inf
            inv_area = 1.0 / area
            i = begin
            while i < end:
                k = e_axis[i]
                # One axis: its events are contiguous.
                n_l = 0
                n_r = n
                while i < end and e_axis[i] == k:
                    p = e_pos[i]
                    p_end = 0
                    p_planar = 0
                    p_start = 0
                    while i < end and e_axis[i] == k and e_pos[i] == p and e_typ[i] == END:
                        p_end += 1
                        i += 1
                    while i < end and e_axis[i] == k and e_pos[i] == p and e_typ[i] == PLANAR:
                        p_planar += 1
                        i += 1
                    while i < end and e_axis[i] == k and e_pos[i] == p and e_typ[i] == START:
                        p_start += 1
                        i += 1
                    n_r -= p_planar + p_end
                    if c_lo[k] < p < c_hi[k]:
                        l_hi0, l_hi1, l_hi2 = c_hi[0], c_hi[1], c_hi[2]
                        r_lo0, r_lo1, r_lo2 = c_lo[0], c_lo[1], c_lo[2]
                        if k == 0:
                            l_hi0 = p
                            r_lo0 = p
                        elif k == 1:
                            l_hi1 = p
                            r_lo1 = p
                        else:
                            l_hi2 = p
                            r_lo2 = p
                        p_l = _half_area(c_lo[0], c_lo[1], c_lo[2], l_hi0, l_hi1, l_hi2) * inv_area
                        p_r = _half_area(r_lo0, r_lo1, r_lo2, c_hi[0], c_hi[1], c_hi[2]) * inv_area
                        # Planar triangles left ...
                        nl = n_l + p_planar
                        nr = n_r
                        cost = k_t + k_i * (p_l * nl + p_r * nr)
                        if nl == 0 or nr == 0:
                            cost *= bonus
                        if cost < best_cost:
                            best_cost = cost
                            best_axis = k
                            best_pos = p
                            best_side = _LEFT
                        # ... or right (the same split when there are none).
                        nl = n_l
                        nr = n_r + p_planar
                        cost = k_t + k_i * (p_l * nl + p_r * nr)
                        if nl == 0 or nr == 0:
                            cost *= bonus
                        if p_planar > 0 and cost < best_cost:
                            best_cost = cost
                            best_axis = k
                            best_pos = p
                            best_side = _RIGHT
                    n_l += p_start + p_planar
            if best_axis >= 0 and best_cost >= k_i * n and n <= params.max_leaf_size:
                best_axis = -1
        elif can_split and params.mode == MODE_MEDIAN and n > params.max_leaf_size:
            k = 0
            for a in range(1, 3):
                if c_hi[a] - c_lo[a] > c_hi[k] - c_lo[k]:
                    k = a
            p = np.float32(0.5) * (c_lo[k] + c_hi[k])
            if c_lo[k] < p < c_hi[k]:
                best_axis = k
                best_pos = p
                best_side = _LEFT
        # ---- classify against the plane
        n_left = 0
        n_right = 0
        n_both = 0
        if best_axis >= 0:
            k = best_axis
            p = best_pos
            k_begin, k_end = _axis_range(e_axis, begin, end, k)
            for i in range(k_begin, k_end):
                side[e_prim[i]] = _BOTH
            for i in range(k_begin, k_end):
                t = e_typ[i]
                q = e_pos[i]
                if t == END and q <= p:
                    side[e_prim[i]] = _LEFT
                elif t == START and q >= p:
                    side[e_prim[i]] = _RIGHT
                elif t == PLANAR:
                    if q < p:
                        side[e_prim[i]] = _LEFT
                    elif q > p:
                        side[e_prim[i]] = _RIGHT
                    else:
                        side[e_prim[i]] = best_side
            # Count the sides; list the straddling triangles in event order.
            straddling = _grow_f(straddling, n)
            for i in range(k_begin, k_end):
                if e_typ[i] != END:
                    s = side[e_prim[i]]
                    if s == _LEFT:
                        n_left += 1
                    elif s == _RIGHT:
                        n_right += 1
                    else:
                        straddling[n_both] = e_prim[i]
                        n_both += 1
            # A split that separates nothing (every triangle on both sides, as for many
            # copies of one triangle under the median) would only repeat the node.
            if n_left == 0 and n_right == 0 and params.mode == MODE_MEDIAN:
                best_axis = -1
            # The duplication budget: no split that takes the path past it.
            if dup * (n + n_both) > params.max_duplication * n:
                best_axis = -1
        if best_axis < 0:
            # ---- leaf: the prims of this node (one non-end event each on axis 0)
            if n_leaves == out_first.shape[0]:
                out_first = _grow_f(out_first, n_leaves + 1)
                out_count = _grow_f(out_count, n_leaves + 1)
            out_prims = _grow_f(out_prims, n_refs + n)
            first = n_refs
            a_begin, a_end = _axis_range(e_axis, begin, end, e_axis[begin])
            for i in range(a_begin, a_end):
                if e_typ[i] != END:
                    out_prims[n_refs] = e_prim[i]
                    n_refs += 1
            out_first[n_leaves] = first
            out_count[n_leaves] = n_refs - first
            out_split[node] = np.float32(0.0)
            out_bits[node] = (n_leaves << 2) | LEAF_AXIS
            n_leaves += 1
            continue
        # ---- inner node: two adjacent children
        k = best_axis
        p = best_pos
        child = n_nodes
        n_nodes += 2
        if n_nodes > out_split.shape[0]:
            out_split = _grow_f(out_split, n_nodes)
            out_bits = _grow_f(out_bits, n_nodes)
        out_split[node] = p
        out_bits[node] = (child << 2) | np.int32(k)  # k is int8: widened as numba does
        # Clip every straddling triangle to both children (perfect splits).
        # both_bounds[j] holds the left then the right part's bounds, in two passes.
        n_new_max = 6 * n_both
        child_begin = end
        # Children event ranges: right first, then left (popped first).
        right_cap = (end - begin) + n_new_max
        left_cap = right_cap
        need = child_begin + right_cap + left_cap
        if need > e_pos.shape[0]:
            e_pos, e_typ, e_axis, e_prim = _grow_events(e_pos, e_typ, e_axis, e_prim, need)
        if n_new_max > n_pos.shape[0]:
            n_pos, n_typ, n_axis, n_prim = _grow_events(n_pos, n_typ, n_axis, n_prim, n_new_max)
        if n_both > both_bounds.shape[0]:
            both_bounds = np.empty((2 * n_both, 6), dtype=np.float32)
            keep = np.empty(2 * n_both, dtype=np.int8)
        write = child_begin
        for half in range(2):
            # half 0: the right child (written first); half 1: the left child.
            this_side = _RIGHT if half == 0 else _LEFT
            h_lo0, h_lo1, h_lo2 = c_lo[0], c_lo[1], c_lo[2]
            h_hi0, h_hi1, h_hi2 = c_hi[0], c_hi[1], c_hi[2]
            if half == 0:
                if k == 0:
                    h_lo0 = p
                elif k == 1:
                    h_lo1 = p
                else:
                    h_lo2 = p
            else:
                if k == 0:
                    h_hi0 = p
                elif k == 1:
                    h_hi1 = p
                else:
                    h_hi2 = p
            # New events of the straddling triangles, axis by axis.
            dropped = 0
            for j in range(n_both):
                pr = straddling[j]
                box_lo[0] = h_lo0
                box_lo[1] = h_lo1
                box_lo[2] = h_lo2
                box_hi[0] = h_hi0
                box_hi[1] = h_hi1
                box_hi[2] = h_hi2
                m = 0
                keep[j] = 1
                if params.perfect_splits:
                    m = clip_triangle_box(tri, pr, box_lo, box_hi, poly, poly_tmp, 1)
                    if m < 1:
                        # The part on this side is empty: drop it here when the other
                        # side's part is not (its box straddled the plane, the
                        # triangle does not); keep it when rounding emptied both.
                        for a in range(3):
                            o_lo[a] = c_lo[a]
                            o_hi[a] = c_hi[a]
                        if half == 0:
                            o_hi[k] = p
                        else:
                            o_lo[k] = p
                        if clip_triangle_box(tri, pr, o_lo, o_hi, poly, poly_tmp, 1) >= 1:
                            keep[j] = 0
                            dropped += 1
                if m >= 1:
                    polygon_bounds(poly, m, box_lo, box_hi, bounds, params.round_pad)
                else:
                    # The triangle's box cut by the cell (also the fallback when
                    # rounding clips a touching triangle away).
                    for a in range(3):
                        lo_a = min(tri[pr, 0, a], tri[pr, 1, a], tri[pr, 2, a])
                        hi_a = max(tri[pr, 0, a], tri[pr, 1, a], tri[pr, 2, a])
                        bounds[a] = max(lo_a, box_lo[a])
                        bounds[3 + a] = min(hi_a, box_hi[a])
                for a in range(3):
                    if bounds[a] > bounds[3 + a]:
                        bounds[3 + a] = bounds[a]
                    both_bounds[j, a] = bounds[a]
                    both_bounds[j, 3 + a] = bounds[3 + a]
            n_new = 0
            for a in range(3):
                seg = n_new
                for j in range(n_both):
                    if keep[j]:
                        pr = straddling[j]
                        blo = both_bounds[j, a]
                        bhi = both_bounds[j, 3 + a]
                        if blo == 0:
                            blo = np.float32(0.0)
                        if bhi == 0:
                            bhi = np.float32(0.0)
                        if blo == bhi:
                            _set_event(n_pos, n_typ, n_axis, n_prim, n_new, blo, PLANAR, a, pr)
                            n_new += 1
                        else:
                            _set_event(n_pos, n_typ, n_axis, n_prim, n_new, blo, START, a, pr)
                            _set_event(n_pos, n_typ, n_axis, n_prim, n_new + 1, bhi, END, a, pr)
                            n_new += 2
                # Sort this axis's few new events by (position, type), stably.
                cnt = n_new - seg
                if 1 < cnt <= _INSERTION_SORT_MAX:
                    _insertion_sort_events(n_pos, n_typ, n_prim, seg, n_new)
                elif cnt > 1:
                    o1 = np.argsort(n_typ[seg:n_new], kind="mergesort")
                    tp = n_pos[seg:n_new][o1]
                    o2 = np.argsort(tp, kind="mergesort")
                    order = o1[o2]
                    sp_pos = n_pos[seg:n_new][order]
                    sp_typ = n_typ[seg:n_new][order]
                    sp_prim = n_prim[seg:n_new][order]
                    n_pos[seg:n_new] = sp_pos
                    n_typ[seg:n_new] = sp_typ
                    n_prim[seg:n_new] = sp_prim
            # Merge the events of this side's triangles (already sorted, read in place:
            # the child's range lies after the node's) with the new ones.
            start_w = write
            ia = begin
            ib = 0
            while True:
                while ia < end and side[e_prim[ia]] != this_side:
                    ia += 1
                if ia == end and ib == n_new:
                    break
                take_a = ib == n_new or (
                    ia < end
                    and not _less(
                        n_axis[ib], n_pos[ib], n_typ[ib], e_axis[ia], e_pos[ia], e_typ[ia]
                    )
                )
                if take_a:
                    e_pos[write] = e_pos[ia]
                    e_typ[write] = e_typ[ia]
                    e_axis[write] = e_axis[ia]
                    e_prim[write] = e_prim[ia]
                    ia += 1
                else:
                    e_pos[write] = n_pos[ib]
                    e_typ[write] = n_typ[ib]
                    e_axis[write] = n_axis[ib]
                    e_prim[write] = n_prim[ib]
                    ib += 1
                write += 1
            # Push the child: right first (popped last).
            s_node[sp] = child + 1 if half == 0 else child
            s_begin[sp] = start_w
            s_end[sp] = write
            s_n[sp] = (n_right if half == 0 else n_left) + n_both - dropped
            s_depth[sp] = depth + 1
            s_dup[sp] = dup * (n + n_both) / n
            store_box(s_lo, s_hi, sp, (h_lo0, h_lo1, h_lo2, h_hi0, h_hi1, h_hi2))
            sp += 1
    return (
        out_split[:n_nodes].copy(),
        out_bits[:n_nodes].copy(),
        out_first[:n_leaves].copy(),
        out_count[:n_leaves].copy(),
        out_prims[:n_refs].copy(),
        t_node[:n_tasks].copy(),
        t_n[:n_tasks].copy(),
        t_depth[:n_tasks].copy(),
        t_dup[:n_tasks].copy(),
        t_cell[: 6 * n_tasks].copy(),
        t_range[: 2 * n_tasks].copy(),
        tp_pos[:n_task_events].copy(),
        tp_typ[:n_task_events].copy(),
        tp_axis[:n_task_events].copy(),
        tp_prim[:n_task_events].copy(),
    )
