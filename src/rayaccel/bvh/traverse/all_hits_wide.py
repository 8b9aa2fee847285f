"""Every hit along every ray in one pass over the 8-wide form of a binary BVH.

The all-hits form of ``bvh2.wide`` (Wald, Benthin, Boulos 2008; Dammertz, Hanika,
Keller 2008): what trimesh's ``multiple_hits=True`` and Open3D's
``list_intersections`` return, each triangle a ray crosses within ``[tmin, tmax]``,
once, sorted by ``t``. A closest-hit traversal shrinks its interval at each hit; this
one keeps the whole interval, so nothing is culled behind a hit and the visiting order
does not matter: an unordered stack walk of the wide rows
(:mod:`rayaccel.bvh.layouts.wide`, the layout ``bvh2.wide`` derives and caches as
``"bvh2.wide8"``), eight child boxes per vector slab test
(:mod:`rayaccel.kernels.aabb_wide`), with the per-ray set-up, culling pad and
watertight triangle test every ``bvh2`` traversal shares, so every hit is bit for bit
the hit a closest-hit traversal would report.

One pass, no counting walk: rays run in chunks of
:data:`rayaccel.trace.skeleton.RAY_CHUNK` taken from a shared counter by one worker per
thread (:mod:`rayaccel._work`). A worker collects its chunk's hits in its own growing
buffers, sorts each ray's hits by ``t`` then triangle (insertion sort for the usual
few, heapsort beyond), drops a triangle met again (spatial splits and pre-splitting
reference a triangle from several leaves; the repeats have the same ``t``, so sorting
makes them neighbours), then reserves room for the chunk in the shared output with
one atomic add and copies it there. The chunks land in the order the workers finish
them; a last copy puts them in ray order. The output is allocated with room
for :data:`HITS_PER_RAY` hits per ray (untouched pages cost nothing); a batch with more
hits runs once more into output of the exact size the first run counted. Results are
identical for every thread count.

Compared with the two-pass all-hits walk of the binary tree
(:mod:`rayaccel.bvh.traverse.all_hits`): one walk instead of two, and a third of the
traversal steps per walk (8-wide rows). trimesh's drop-in (:mod:`rayaccel.trimesh`)
uses it; docs/performance.md has the measurement.
"""

from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
from numba import prange
from numba.cpython.unsafe.numbers import trailing_zeros

from rayaccel._docstrings import with_sections
from rayaccel._jit import atomic_fetch_add, cpu_inline, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2
from rayaccel.bvh.layouts.wide import ref_column
from rayaccel.bvh.traverse.all_hits import BVH_QUERY_PARAMETERS, empty_hits, sort_hits
from rayaccel.bvh.traverse.all_hits import INSERTION_SORT_MAX as INSERTION_SORT_MAX
from rayaccel.bvh.traverse.building_blocks import lane_planes
from rayaccel.bvh.traverse.wide import wide_bvh
from rayaccel.config import parallel_section
from rayaccel.dtypes import Int64Array, IntArray, RealArray
from rayaccel.errors import TraversalOverflowError
from rayaccel.kernels.aabb_wide import slab_test8
from rayaccel.kernels.triangle import ray_triangle
from rayaccel.rays.batch import RayBatch
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.run import PARALLEL_MIN_RAYS
from rayaccel.trace.skeleton import RAY_CHUNK

INF32 = np.float32(np.inf)
#: Children per wide row (the layout ``bvh2.wide`` uses by default).
WIDTH = 8
_REF_COL = ref_column(WIDTH)
#: Stack entries: a row pushes at most ``WIDTH`` children, of which one is popped at once.
STACK_ENTRIES = (WIDTH - 1) * MAX_DEPTH + WIDTH + 1
#: Room reserved per ray in the first run (a batch with more hits runs again).
HITS_PER_RAY = 16
#: First size of a worker's chunk buffers (they double when full).
CHUNK_BUFFER = 256


def sort_unique_py(t, prim, u, v, begin, end):
    """Sort hits ``begin:end`` by ``t`` then triangle, drop repeated triangles; return the count.

    A triangle referenced from several leaves is tested with the same arithmetic each
    time, so its repeats have the same ``t`` and sort next to each other.
    """
    n = end - begin
    sort_hits(t, prim, u, v, begin, end)
    # Keep the first of each run of one triangle.
    kept = min(n, 1)
    for i in range(begin + 1, end):
        if prim[i] != prim[begin + kept - 1]:
            if i != begin + kept:
                t[begin + kept] = t[i]
                prim[begin + kept] = prim[i]
                u[begin + kept] = u[i]
                v[begin + kept] = v[i]
            kept += 1
    return kept


sort_unique = cpu_inline(sort_unique_py)


def walk_chunk_py(
    bvh, origin, direction, tmin, tmax, begin, end, stack, lane_t,
    buf_t, buf_prim, buf_u, buf_v, counts,
):  # fmt: skip
    """List every hit of rays ``begin:end`` in the buffers; return ``(n, overflowed, full)``.

    ``n`` hits are buffered, each ray's sorted and without repeats, and ``counts[r]``
    holds each ray's count. ``full`` says the buffers ran out of room before the last
    ray (the caller grows them and walks the chunk again: growing them here, in the
    loop, would make numba count references to them at every step). ``overflowed``
    counts rays that overflowed the stack.
    """
    box = bvh.box
    refs = bvh.ref
    size = buf_t.shape[0]
    n = 0
    overflowed = 0
    for r in range(begin, end):
        start = n
        # The whole interval stays open: no hit culls anything.
        (
            _valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
            kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_top, _pad,
            box_lo, box_hi, entry, _prim, _u, _v,
        ) = ray_start(origin, direction, tmin, tmax, r, bvh.root_box)  # fmt: skip
        near_x, far_x, near_y, far_y, near_z, far_z = lane_planes(WIDTH, nx, ny, nz, fx, fy, fz)
        sp = 0
        if entry < INF32:
            stack[0] = bvh.root_ref[0]
            sp = 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if node >= 0:
                # Inner row: push every hit child (the order does not matter).
                mask = slab_test8(
                    box, node, near_x, far_x, near_y, far_y, near_z, far_z,
                    ox, oy, oz, ix, iy, iz, box_lo, box_hi, lane_t,
                )  # fmt: skip
                if sp + WIDTH > STACK_ENTRIES:
                    overflowed += 1
                    break
                while mask != 0:
                    j = trailing_zeros(mask)
                    mask &= mask - 1
                    stack[sp] = refs[node, _REF_COL + j]
                    sp += 1
            else:
                # Leaf: every triangle hit in the interval goes to the buffers.
                leaf = ~node
                first = bvh.leaf_first[leaf]
                last = first + bvh.leaf_count[leaf]
                for i in range(first, last):
                    t, u, v = ray_triangle(
                        bvh.tri, i, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_top
                    )
                    if t < INF32:
                        if n == size:
                            return n, overflowed, True
                        buf_t[n] = t
                        buf_prim[n] = bvh.tri_prim[i]
                        buf_u[n] = u
                        buf_v[n] = v
                        n += 1
        # This ray's hits in order, each triangle once.
        kept = sort_unique(buf_t, buf_prim, buf_u, buf_v, start, n)
        n = start + kept
        counts[r] = kept
    return n, overflowed, False


walk_chunk = cpu_inline(walk_chunk_py)


@cpu_kernel()
def _chunk_worker(
    bvh, origin, direction, tmin, tmax, counter, counts, chunk_start, chunk_count, used,
    out_t, out_prim, out_u, out_v,
):  # fmt: skip
    """One worker: take chunks of rays from ``counter`` and list every hit of each ray.

    Writes ``counts[r]`` for each ray of a chunk, then reserves ``chunk_count[chunk]``
    entries at ``chunk_start[chunk]`` of the ``out_*`` arrays (an atomic add on
    ``used[0]``) and copies the chunk's hits there when they fit. Returns the number of
    rays that overflowed the stack (0 for any tree a builder makes).
    """
    n_rays = origin.shape[0]
    n_chunks = (n_rays + RAY_CHUNK - 1) // RAY_CHUNK
    capacity = out_t.shape[0]
    stack = np.empty(STACK_ENTRIES, dtype=np.int32)
    lane_t = np.empty(WIDTH, dtype=np.float32)
    size = CHUNK_BUFFER
    buf_t = np.empty(size, dtype=out_t.dtype)
    buf_prim = np.empty(size, dtype=np.int32)
    buf_u = np.empty(size, dtype=out_t.dtype)
    buf_v = np.empty(size, dtype=out_t.dtype)
    overflowed = 0
    while True:
        chunk = next_item(counter, n_chunks)
        if chunk < 0:
            break
        begin = chunk * RAY_CHUNK
        end = min(n_rays, begin + RAY_CHUNK)
        while True:
            n, stack_overflows, full = walk_chunk(
                bvh, origin, direction, tmin, tmax, begin, end, stack, lane_t,
                buf_t, buf_prim, buf_u, buf_v, counts,
            )  # fmt: skip
            if not full:
                break
            # Out of room: grow the buffers and walk the chunk again.
            size *= 2
            buf_t = np.empty(size, dtype=out_t.dtype)
            buf_prim = np.empty(size, dtype=np.int32)
            buf_u = np.empty(size, dtype=out_t.dtype)
            buf_v = np.empty(size, dtype=out_t.dtype)
        overflowed += stack_overflows
        # Reserve the chunk's room in the shared output and copy it there if it fits.
        position = atomic_fetch_add(used, 0, np.int64(n))
        chunk_start[chunk] = position
        chunk_count[chunk] = n
        if position + n <= capacity:
            for k in range(n):
                out_t[position + k] = buf_t[k]
                out_prim[position + k] = buf_prim[k]
                out_u[position + k] = buf_u[k]
                out_v[position + k] = buf_v[k]
    return overflowed


@functools.cache
def _all_hits_kernel(parallel: bool) -> Any:
    """Return the kernel running one :func:`_chunk_worker` per thread (or one, serial)."""

    @cpu_kernel(parallel=parallel)
    def kernel(
        bvh, origin, direction, tmin, tmax, counts, chunk_start, chunk_count, used,
        out_t, out_prim, out_u, out_v, n_threads,
    ):  # fmt: skip
        _ = parallel
        n_chunks = (origin.shape[0] + RAY_CHUNK - 1) // RAY_CHUNK
        counter = new_counter()
        overflowed = 0
        for _worker in prange(worker_count(n_chunks, n_threads, parallel)):
            overflowed += _chunk_worker(
                bvh, origin, direction, tmin, tmax, counter, counts, chunk_start,
                chunk_count, used, out_t, out_prim, out_u, out_v,
            )  # fmt: skip
        return overflowed

    return kernel


@cpu_kernel()
def _gather_kernel(chunk_start, chunk_count, splits, src_t, src_prim, src_u, src_v,
                   out_t, out_prim, out_u, out_v):  # fmt: skip
    """Copy each chunk's hits from where its worker put them to its rays' place.

    Serial: a copy of the hits, far cheaper than the walk, and not worth a parallel
    launch.
    """
    for chunk in range(chunk_start.shape[0]):
        source = chunk_start[chunk]
        target = splits[chunk * RAY_CHUNK]
        for k in range(chunk_count[chunk]):
            out_t[target + k] = src_t[source + k]
            out_prim[target + k] = src_prim[source + k]
            out_u[target + k] = src_u[source + k]
            out_v[target + k] = src_v[source + k]


@with_sections(BVH_QUERY_PARAMETERS)
def list_all_hits_wide(
    bvh: Bvh2, mesh: TriangleMesh, rays: RayBatch, cache: dict[str, Any] | None = None
) -> tuple[Int64Array, RealArray, IntArray, RealArray, RealArray]:
    """Return every hit of every ray in ``[tmin, tmax]``, by ray, then ``t``, then triangle.

    The rays are in the mesh's precision (float64 rays for a float64 mesh); the wide
    layout is memoised as ``"bvh2.wide8"``, shared with ``bvh2.wide``.

    Returns
    -------
    splits : (n_rays + 1,) int64
        Ray ``r``'s hits are entries ``splits[r]:splits[r + 1]``.
    t : (n_hits,) float32 (float64 for float64 rays)
    prim : (n_hits,) int32
        Each triangle at most once per ray.
    u, v : (n_hits,) float32 (float64 for float64 rays)
        Barycentrics of each hit: ``(1-u-v)·A + u·B + v·C``.

    Raises
    ------
    TraversalOverflowError
        A ray overflowed the traversal stack (only a hand-made tree deeper than
        ``MAX_DEPTH`` can).
    """
    n = rays.n_rays
    splits = np.zeros(n + 1, dtype=np.int64)
    if n == 0:
        return (splits, *empty_hits(0, rays.precision))
    arrays = wide_bvh(bvh, mesh, cache, WIDTH).arrays()
    n_chunks = (n + RAY_CHUNK - 1) // RAY_CHUNK
    counts = np.zeros(n, dtype=np.int32)
    chunk_start = np.zeros(n_chunks, dtype=np.int64)
    chunk_count = np.zeros(n_chunks, dtype=np.int64)
    parallel = n >= PARALLEL_MIN_RAYS
    kernel = _all_hits_kernel(parallel)
    capacity = HITS_PER_RAY * n
    while True:
        used = np.zeros(1, dtype=np.int64)
        buffers = empty_hits(capacity, rays.precision)
        args = (
            arrays, rays.origin, rays.direction, rays.tmin, rays.tmax, counts, chunk_start,
            chunk_count, used, *buffers, numba.get_num_threads(),
        )  # fmt: skip
        if parallel:
            with parallel_section():
                overflowed = kernel(*args)
        else:
            overflowed = kernel(*args)
        if overflowed:
            raise TraversalOverflowError(
                f"{overflowed} rays overflowed the all-hits stack; the tree is deeper than "
                "MAX_DEPTH"
            )
        if used[0] <= capacity:
            break
        # More hits than room: run again into output of the exact size.
        capacity = int(used[0])
    np.cumsum(counts, out=splits[1:])
    out = empty_hits(int(splits[-1]), rays.precision)
    _gather_kernel(chunk_start, chunk_count, splits, *buffers, *out)
    return (splits, *out)
