"""Stackless BVH2 traversal with backtracking in constant time (``bvh2.perfect_hash``).

Binder & Keller, "Efficient Stackless Hierarchy Traversal on GPUs with Backtracking
in Constant Time", HPG 2016. The building blocks, each switchable by an option so
its effect can be measured:

1. *Node keys and a bit trail*: the root's key is 1, a child's key appends 0 or 1;
   the trail has one bit per level of the current path, 1 where the sibling of the
   path node was postponed. Backtracking goes to the deepest postponed node, ``n =
   ctz(trail)`` levels up, the ``n``-th uncle: ``key = (key >> n) ^ 1``, ``trail =
   (trail >> n) ^ 1``: constant time, whatever ``n``.
2. *Perfect hash* (``hash``; :mod:`rayaccel.bvh.layouts.perfect_hash`): the key of the
   target's parent is mapped to its packed row in one lookup (the target is a child
   slot of that row, ``key & 1``). Off: climb ``n`` parent links instead (O(n)).
3. *Fewer lookups* (``uncle_refs`` and ``register``): the spare room of each packed
   row (columns 14, 15, padding in ``bvh2.stack``'s layout) holds the rows of its
   parent and grandparent, i.e. the rows holding the uncle and the grand-uncle of the
   row's children, so backtracking one or two levels needs no lookup; and the most
   recently postponed node (with its entry distance) is kept in registers, which
   always serves backtracking to a sibling and sometimes further up.
4. *Level mask* (``level_mask``): one bit per level, cleared when the postponed
   node's interval lies entirely behind the chosen child's (by more than twice the
   culling pad); after a hit, ``trail &= mask`` drops postponed nodes that cannot
   hold a nearer hit without visiting them.
5. *Pause and resume*: :func:`start_traversal` returns a :class:`TraversalState`
   (node, parent row, key and trail per ray) that stops at every hit and continues
   from there (all hits along a ray, transparency; ``Accel.traversal_state``).

Differences from the paper: it enters a postponed node without re-checking its entry
distance; we re-check it against the current ``t_hit`` (from the register, or with
one box test from the row the lookup gives), which is ``bvh2.stack``'s pop test, so
the nodes entered and the hits are exactly those of ``bvh2.stack`` (bit-identical
``t`` and primitive, same any-hit). The table holds inner-node keys only (the key of
a target's parent), so the target's box can be re-tested from the same row.

Layout: :class:`KeyedBvh2`, a copy of the packed rows with the spare room filled,
plus the hash tables (4 bytes per inner node each, about), cached per accel.

Counters: ``steps``/``nodes`` nodes entered (equals ``bvh2.stack``), ``box_tests``,
``prim_tests``, ``backtracks`` jumps (plus parent steps with ``hash=False``),
``hash_lookups``, the histogram of targets (``backtrack_sibling`` ``n = 0``,
``_uncle`` 1, ``_grand_uncle`` 2, ``_further`` 3+; culled targets count), ``bytes``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np
from numba import prange
from numba.cpython.unsafe.numbers import trailing_zeros

from rayaccel._docstrings import with_sections
from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register_pausable
from rayaccel.bvh.layouts.bvh2 import (
    CACHE_LINE,
    PACKED_ROW_BYTES,
    Bvh2,
    PackedBvh2,
    aligned_zeros,
)
from rayaccel.bvh.layouts.perfect_hash import ENTRY_BYTES, PerfectHash, build_perfect_hash
from rayaccel.bvh.layouts.stackless_links import LINK_BYTES, link_packed
from rayaccel.bvh.traverse.all_hits import BVH_QUERY_PARAMETERS
from rayaccel.bvh.traverse.building_blocks import (
    INF32,
    box_entry,
    box_exit,
    check_trail_depth,
    child_entries,
    leaf_hits,
    pick,
    tally_backtrack,
)
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.config import parallel_section
from rayaccel.dtypes import REAL, FloatArray, IntArray
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.triangle import ray_triangle
from rayaccel.queries import QUERY_ANY
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels, memoised_layout
from rayaccel.trace.skeleton import no_scratch, store_backtracks, store_counts, store_hit

TWO32 = np.float32(2.0)
#: Building-block switches, passed to the kernel as one bit mask.
USE_HASH = 1
USE_UNCLES = 2
USE_REGISTER = 4
USE_LEVEL_MASK = 8
#: Traversal status of a paused ray.
FRESH = 0
PAUSED = 1
FINISHED = 2


@dataclass(frozen=True, slots=True)
class PerfectHashOptions:
    """Options of ``bvh2.perfect_hash``: switch each building block off to measure it.

    Attributes
    ----------
    hash : bool
        Backtrack further than the spare-room references with one perfect-hash
        lookup (off: climb parent links, O(levels)).
    uncle_refs : bool
        Use the rows of the uncle and grand-uncle stored in the row's spare room
        (off: a lookup for those too).
    register : bool
        Keep the most recently postponed node in registers.
    level_mask : bool
        Drop postponed nodes whose interval lies entirely behind a hit.
    """

    hash: bool = True
    uncle_refs: bool = True
    register: bool = True
    level_mask: bool = True

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, (bool, np.bool_)):
                raise InvalidInputError(f"{f.name}: expected True or False, got {value!r}")

    def switches(self) -> int:
        """Return the kernel's bit mask of enabled building blocks."""
        return (
            USE_HASH * bool(self.hash)
            | USE_UNCLES * bool(self.uncle_refs)
            | USE_REGISTER * bool(self.register)
            | USE_LEVEL_MASK * bool(self.level_mask)
        )


class KeyedArrays(NamedTuple):
    """The keyed layout as one kernel argument (flat: nested tuples break parfors)."""

    inner_box: FloatArray  # (n_inner, 16): child boxes; int32 view holds refs and spare
    inner_ref: IntArray  # cols 12, 13 child refs; 14 parent row; 15 grandparent row
    leaf_first: IntArray
    leaf_count: IntArray
    tri: FloatArray
    tri_prim: IntArray
    root_box: FloatArray
    root_ref: IntArray
    hash_table: IntArray  # T: row of the inner node with the hashed key
    hash_disp: IntArray  # D: bucket displacements
    switches: int


@dataclass(frozen=True, slots=True, eq=False)
class KeyedBvh2:
    """Packed rows with parent/grandparent rows in the spare room, and the key hash.

    Attributes
    ----------
    rows : (n_inner, 16) float32
        A copy of the packed rows; int32 columns 14 and 15 hold the rows of the
        row's parent and grandparent (``-1`` above the root).
    row_key : (n_inner,) int64
        Key of each row's node (root 1, children ``2k + slot``); build-time only.
    hash : PerfectHash
        Row key to row index.
    packed : PackedBvh2
        The shared packed layout (leaf tables and triangles, not counted here).
    """

    rows: FloatArray
    row_key: np.ndarray
    hash: PerfectHash
    packed: PackedBvh2

    def arrays(self, switches: int) -> KeyedArrays:
        """Return the arrays as a NamedTuple kernels take as one argument."""
        p = self.packed
        return KeyedArrays(
            self.rows,
            self.rows.view(np.int32),
            p.leaf_first,
            p.leaf_count,
            p.tri,
            p.tri_prim,
            p.root_box,
            p.root_ref,
            self.hash.table,
            self.hash.disp,
            int(switches),
        )

    def nbytes(self) -> int:
        """Bytes of the rows copy and the hash tables (keys are not kept for traversal)."""
        return int(self.rows.nbytes + self.hash.nbytes())


@cpu_kernel()
def _keys_kernel(ints, n_inner, row_up, row_key):
    """Fill row keys and the spare room (parent and grandparent rows) of every row."""
    # Children rows follow their parent in the packed numbering.
    for row in range(n_inner):
        up = row_up[row]
        parent = up >> 1 if up >= 0 else -1
        ints[row, 14] = parent
        ints[row, 15] = ints[parent, 14] if parent >= 0 else -1
        for slot in range(2):
            child = ints[row, 12 + slot]
            if child >= 0:
                row_key[child] = 2 * row_key[row] + slot


def key_packed(packed: PackedBvh2) -> KeyedBvh2:
    """Derive the keyed layout (spare-room links and the perfect hash) of a packed BVH2."""
    linked = link_packed(packed)
    n_inner = linked.row_up.shape[0] if packed.root_ref[0] >= 0 else 0
    rows = aligned_zeros(packed.rows.shape, REAL, CACHE_LINE)
    rows[...] = packed.rows
    row_key = np.zeros(max(n_inner, 1), dtype=np.int64)
    row_key[0] = 1
    _keys_kernel(rows.view(np.int32), n_inner, linked.row_up, row_key)
    keys = row_key[:n_inner] if n_inner else np.ones(1, dtype=np.int64)
    table = build_perfect_hash(keys, np.arange(keys.shape[0], dtype=np.int32))
    return KeyedBvh2(rows, row_key, table, packed)


def keyed_layout(packed: PackedBvh2, cache: dict[str, Any] | None) -> KeyedBvh2:
    """Return the keyed layout of ``packed``, memoised in ``cache`` under ``"bvh2.keyed"``."""
    return memoised_layout(cache, "bvh2.keyed", lambda: key_packed(packed))


def hash_row_py(table, disp, key):
    """Return the row of the inner node whose key is ``key``: one probe of the perfect hash.

    ``disp`` has a power-of-two length, so the bucket ``key % len(disp)`` is a mask.
    """
    n_table = np.int64(table.shape[0])
    return table[(key % n_table + disp[key & np.int64(disp.shape[0] - 1)]) % n_table]


hash_row = cpu_inline(hash_row_py)


def trace_rays_py(
    bvh, scratch, origin, direction, tmin, tmax, begin, end,
    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
):  # fmt: skip
    """Trace rays ``begin:end`` over ``bvh`` (KeyedArrays) with keys, trail and hash; return 0."""
    _ = scratch
    box = bvh.inner_box
    refs = bvh.inner_ref
    table = bvh.hash_table
    disp = bvh.hash_disp
    use_hash = (bvh.switches & USE_HASH) != 0
    use_uncles = (bvh.switches & USE_UNCLES) != 0
    use_register = (bvh.switches & USE_REGISTER) != 0
    use_mask = (bvh.switches & USE_LEVEL_MASK) != 0
    for r in range(begin, end):
        n_steps = n_prim = n_bytes = n_back = n_lookups = 0
        targets = (0, 0, 0, 0)
        (
            valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            box_lo, box_hi, entry, best_prim, best_u, best_v,
        ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        # The root box was tested once up front.
        n_box = 1 if valid else 0
        margin = TWO32 * pad
        node = bvh.root_ref[0]
        prow = -1
        key = np.int64(1)
        trail = np.int64(0)
        mask = np.int64(0)
        reg_pos = -1
        reg_ref = 0
        reg_row = 0
        reg_t = INF32
        done = entry == INF32
        while not done:
            if with_stats:
                n_steps += 1
            if node >= 0:
                # Inner row: test both children, descend into the nearer hit one.
                c0, c1, t0, t1, n_box, n_bytes = child_entries(
                    box, refs, node, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                    box_lo, box_hi, n_box, n_bytes, with_stats,
                )  # fmt: skip
                if t0 < INF32 or t1 < INF32:
                    swap = t1 < t0
                    trail <<= 1
                    mask <<= 1
                    if reg_pos >= 0:
                        reg_pos += 1
                    if t0 < INF32 and t1 < INF32:
                        # Postpone the far child: trail bit, register, level mask.
                        trail |= 1
                        t_far = t0 if swap else t1
                        if use_register:
                            reg_ref = c0 if swap else c1
                            reg_row = node
                            reg_t = t_far
                            reg_pos = 0
                        if use_mask:
                            t_out = box_exit(
                                box, node, 6 if swap else 0, ox, oy, oz, ix, iy, iz,
                                fx, fy, fz,
                            )  # fmt: skip
                            if t_far <= t_out + margin:
                                mask |= 1
                    key = 2 * key + (1 if swap else 0)
                    prow = node
                    node = pick(swap, c1, c0)
                    continue
            else:
                # Leaf: test its triangles; a hit drops unreachable postponed nodes.
                t_before = t_hit
                t_hit, best_prim, best_u, best_v, box_hi, n_prim, n_bytes = leaf_hits(
                    bvh, ~node, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
                    best_prim, best_u, best_v, query == QUERY_ANY, n_prim, n_bytes, with_stats,
                )  # fmt: skip
                if query == QUERY_ANY and best_prim >= 0:
                    break
                if use_mask and t_hit < t_before:
                    trail &= mask
            # Backtrack to the deepest postponed node, n levels up, in O(1).
            done = True
            while trail != 0:
                n = trailing_zeros(trail)
                key = (key >> n) ^ 1
                trail = (trail >> n) ^ 1
                mask >>= n
                slot = key & 1
                if with_stats:
                    n_back += 1
                    targets = tally_backtrack(n, targets)
                if reg_pos == n:
                    # The register holds it (always the case for a sibling).
                    node = reg_ref
                    prow = reg_row
                    t = reg_t if reg_t <= box_hi else INF32
                else:
                    # Find the row holding the target: the current parent row, the
                    # spare room's uncle/grand-uncle rows, or one hash lookup.
                    if n == 0:
                        row = prow
                    elif n == 1 and use_uncles:
                        row = refs[prow, 14]
                    elif n == 2 and use_uncles:
                        row = refs[prow, 15]
                    elif use_hash:
                        row = hash_row(table, disp, key >> 1)
                        if with_stats:
                            n_lookups += 1
                            n_bytes += 2 * ENTRY_BYTES
                    else:
                        row = prow
                        for _ in range(n):
                            row = refs[row, 14]
                        if with_stats:
                            n_back += n
                            n_bytes += LINK_BYTES * n
                    node = refs[row, 12 + slot]
                    prow = row
                    # Re-check the postponed node against the current t_hit.
                    t = box_entry(
                        box, row, 6 * slot, ox, oy, oz, ix, iy, iz, nx, ny, nz,
                        fx, fy, fz, box_lo, box_hi,
                    )  # fmt: skip
                    if with_stats:
                        n_box += 1
                        n_bytes += PACKED_ROW_BYTES
                reg_pos = -1
                if t < INF32:
                    done = False
                    break
        if with_stats:
            store_counts(counters, r, n_steps, n_steps, n_box, n_prim, 0, n_bytes)
            store_backtracks(counters, r, 0, n_back, n_lookups, targets)
        store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
    return 0


#: ``kernel_for(query, with_stats, parallel)``: the compiled variants of this traversal.
trace_kernel = body_kernels(no_scratch, cpu_inline(trace_rays_py))


@register_traversal("bvh2.perfect_hash")
def trace_bvh2_perfect_hash(
    bvh: Bvh2, mesh: TriangleMesh, options: PerfectHashOptions, cache: LayoutCache
) -> TracePlan:
    """Stackless ordered traversal, keys + bit trail + perfect hash: O(1) backtracking.

    Trace rays through a binary BVH with backtracking in constant time.

    Hits are bit-identical to ``bvh2.stack``'s with every combination of the
    building-block switches (all on by default).

    References
    ----------
    Binder & Keller 2016, Efficient Stackless Hierarchy Traversal on GPUs with Backtracking in
    Constant Time.
    """
    check_trail_depth(bvh, cache, "bvh2.perfect_hash")
    packed = packed_layout(bvh, mesh, cache)
    keyed = keyed_layout(packed, cache)
    return TracePlan(trace_kernel, keyed.arrays(options.switches()))


# -- building block 5: pause and resume ----------------------------------------------------------


@cpu_kernel(parallel=True)
def _resume_kernel(
    bvh, origin, direction, tmin, tmax, st_node, st_prow, st_key, st_trail, st_pos, st_status,
    hit_t, hit_prim, hit_u, hit_v,
):  # fmt: skip
    """Continue every unfinished ray's traversal up to its next hit in ``[tmin, tmax]``.

    The interval never shrinks (every hit is wanted), so postponed nodes need no
    re-check. A ray pauses inside a leaf just after an accepted triangle
    (``st_pos`` is the next triangle to test) and finishes when its trail is empty.
    """
    n_rays = origin.shape[0]
    refs = bvh.inner_ref
    box = bvh.inner_box
    table = bvh.hash_table
    disp = bvh.hash_disp
    for r in prange(n_rays):
        if st_status[r] == FINISHED:
            continue
        (
            _valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_top, _pad,
            box_lo, box_hi, entry, _prim, _u, _v,
        ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        if st_status[r] == FRESH:
            # Start: unless the root box is missed, begin at the root.
            if entry == INF32:
                st_status[r] = FINISHED
                continue
            st_node[r] = bvh.root_ref[0]
            st_prow[r] = -1
            st_key[r] = 1
            st_trail[r] = 0
            st_pos[r] = -1
        node = st_node[r]
        prow = st_prow[r]
        key = st_key[r]
        trail = st_trail[r]
        pos = st_pos[r]
        found = False
        while True:
            if node >= 0:
                # Inner row: descend into the nearer hit child, postpone the other.
                t0 = box_entry(
                    box, node, 0, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, box_lo, box_hi
                )
                t1 = box_entry(
                    box, node, 6, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, box_lo, box_hi
                )
                if t0 < INF32 or t1 < INF32:
                    swap = t1 < t0
                    trail <<= 1
                    if t0 < INF32 and t1 < INF32:
                        trail |= 1
                    key = 2 * key + (1 if swap else 0)
                    prow = node
                    node = refs[node, 13] if swap else refs[node, 12]
                    pos = -1
                    continue
            else:
                # Leaf: resume at `pos`; pause right after the next accepted triangle.
                first = bvh.leaf_first[~node]
                last = first + bvh.leaf_count[~node]
                start = pos if pos >= 0 else first
                for i in range(start, last):
                    t, u, v = ray_triangle(
                        bvh.tri, i, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_top
                    )
                    if t < INF32:
                        hit_t[r] = t
                        hit_prim[r] = bvh.tri_prim[i]
                        hit_u[r] = u
                        hit_v[r] = v
                        pos = i + 1
                        found = True
                        break
                if found:
                    break
            # Backtrack to the deepest postponed node (spare room or one hash lookup).
            if trail == 0:
                st_status[r] = FINISHED
                break
            n = trailing_zeros(trail)
            key = (key >> n) ^ 1
            trail = (trail >> n) ^ 1
            if n == 0:
                row = prow
            elif n == 1:
                row = refs[prow, 14]
            elif n == 2:
                row = refs[prow, 15]
            else:
                row = hash_row(table, disp, key >> 1)
            node = refs[row, 12 + (key & 1)]
            prow = row
            pos = -1
        if found:
            st_status[r] = PAUSED
            st_node[r] = node
            st_prow[r] = prow
            st_key[r] = key
            st_trail[r] = trail
            st_pos[r] = pos


class TraversalState:
    """Paused traversals, one per ray: each :meth:`next_hits` call resumes them.

    Building block 5 of Binder & Keller 2016: the state of a constant-time traversal
    is its node, parent row, key and bit trail (plus the position inside a leaf), so
    it can stop at a hit and continue from there later instead of from the root.
    Every triangle hit within ``[tmin, tmax]`` is reported in traversal order (near
    subtrees first, so roughly front to back, but not sorted): once per leaf the ray
    enters that references it, so exactly once unless the tree references a triangle
    from several leaves (``n_refs > n_prims``: spatial splits, pre-splitting), where
    :meth:`all_hits` removes the repeats.

    Use :func:`start_traversal` or ``Accel.traversal_state`` to make one.
    """

    def __init__(self, keyed: KeyedBvh2, rays: RayBatch):
        self.rays = rays
        self._arrays = keyed.arrays(0)
        n = rays.n_rays
        self._node = np.zeros(n, dtype=np.int32)
        self._prow = np.zeros(n, dtype=np.int32)
        self._key = np.zeros(n, dtype=np.int64)
        self._trail = np.zeros(n, dtype=np.int64)
        self._pos = np.zeros(n, dtype=np.int32)
        self._status = np.zeros(n, dtype=np.int8)

    @property
    def done(self) -> np.ndarray:
        """``(n,)`` bool: rays whose traversal is finished (no hit left)."""
        return self._status == FINISHED  # type: ignore[no-any-return]

    def next_hits(self) -> HitBatch:
        """Resume every unfinished ray up to its next hit; a miss marks a finished ray.

        Returns
        -------
        HitBatch
            The next hit of each ray in traversal order (``prim = -1`` once finished).
        """
        hits = HitBatch.empty(self.rays.n_rays)
        if self.rays.n_rays:
            with parallel_section():
                _resume_kernel(
                    self._arrays, self.rays.origin, self.rays.direction, self.rays.tmin,
                    self.rays.tmax, self._node, self._prow, self._key, self._trail, self._pos,
                    self._status, hits.t, hits.prim, hits.u, hits.v,
                )  # fmt: skip
        return hits

    def all_hits(
        self, max_rounds: int | None = None
    ) -> tuple[IntArray, FloatArray, IntArray, FloatArray, FloatArray]:
        """Resume until every ray is finished; return every hit sorted by ray, ``t``, prim.

        Parameters
        ----------
        max_rounds : int, optional
            Stop after this many :meth:`next_hits` calls (default: until done).

        Returns
        -------
        ray, t, prim, u, v : (n_hits,) arrays
            One entry per triangle hit within the interval, sorted by ray, then ``t``,
            then primitive id (a triangle referenced from several leaves that
            :meth:`next_hits` met more than once is listed once).
        """
        parts: list[tuple[np.ndarray, ...]] = []
        rounds = 0
        while not self.done.all() and (max_rounds is None or rounds < max_rounds):
            hits = self.next_hits()
            rows = np.flatnonzero(hits.prim >= 0)
            parts.append((rows, hits.t[rows], hits.prim[rows], hits.u[rows], hits.v[rows]))
            rounds += 1
        if not parts:
            empty_i = np.zeros(0, dtype=np.int32)
            empty_f = np.zeros(0, dtype=np.float32)
            return empty_i, empty_f, empty_i, empty_f, empty_f
        ray = np.concatenate([p[0] for p in parts]).astype(np.int32)
        t = np.concatenate([p[1] for p in parts])
        prim = np.concatenate([p[2] for p in parts])
        u = np.concatenate([p[3] for p in parts])
        v = np.concatenate([p[4] for p in parts])
        order = np.lexsort((prim, t, ray))
        ray, t, prim, u, v = ray[order], t[order], prim[order], u[order], v[order]
        # A triangle in several leaves (spatial splits, pre-splitting) is met once per
        # leaf entered, with the same t: keep the first of each (ray, prim) run.
        first = np.ones(ray.shape[0], dtype=bool)
        first[1:] = (ray[1:] != ray[:-1]) | (prim[1:] != prim[:-1]) | (t[1:] != t[:-1])
        return ray[first], t[first], prim[first], u[first], v[first]


@register_pausable("bvh2.perfect_hash")
@with_sections(BVH_QUERY_PARAMETERS)
def start_traversal(
    bvh: Bvh2, mesh: TriangleMesh, rays: RayBatch, cache: dict[str, Any] | None = None
) -> TraversalState:
    """Return a :class:`TraversalState` for ``rays``, positioned before the first hit."""
    check_trail_depth(bvh, cache, "traversal_state")
    packed = packed_layout(bvh, mesh, cache)
    return TraversalState(keyed_layout(packed, cache), rays)
