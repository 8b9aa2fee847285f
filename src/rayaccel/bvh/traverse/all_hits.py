"""Every hit along every ray, in two passes over a binary BVH: count, prefix sum, fill.

What Open3D's ``count_intersections``/``list_intersections`` and trimesh's
``multiple_hits=True`` return: each triangle a ray crosses within ``[tmin, tmax]``,
once. A closest-hit traversal shrinks its interval at each hit; this one keeps the
whole interval, so no subtree is culled behind a hit and the order of the walk does
not matter (an unordered stack traversal over the packed rows of
:mod:`rayaccel.bvh.layouts.bvh2`, Aila & Laine 2009, with the per-ray set-up, box
tests and watertight triangle test every ``bvh2`` traversal shares, so a hit found
here is exactly the hit the closest-hit traversals would report).

Pass 1 counts the hits of each ray; an exclusive prefix sum gives each ray its slice
of the output (``ray_splits``, CSR); pass 2 walks again and writes the hits of each
ray into a per-worker buffer, sorts them by ``t`` then primitive id (insertion sort
for the usual few hits, heapsort beyond), and copies them to the ray's slice. Two
walks cost less than growing per-ray lists, and the output is allocated once at its
exact size, identical for every thread count.

Duplicates: spatial-split builders (``bvh2.sbvh``) and pre-splitting
(``+presplit``) reference a triangle from several leaves, so a ray can meet it
several times. Both passes then keep a *mailbox* per worker (Amanatides & Woo 1987):
``mailbox[prim]`` holds the last ray that tested ``prim``, and a reference whose
triangle that ray already tested is skipped. Counts are therefore exact in the
first pass; the mailbox costs 4 bytes per triangle per worker and is only made
when ``n_refs > n_prims``.

Rays run in chunks of :data:`rayaccel.trace.skeleton.RAY_CHUNK` taken from a shared
counter by one worker per thread (:mod:`rayaccel._work`).

References
----------
T. Aila, S. Laine, "Understanding the Efficiency of Ray Traversal on GPUs", HPG 2009.
J. Amanatides, A. Woo, "A Fast Voxel Traversal Algorithm for Ray Tracing",
Eurographics 1987 (mailboxing).
"""

from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
from numba import prange

from rayaccel._docstrings import with_sections
from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.layouts.bvh2 import STACK_SIZE, Bvh2
from rayaccel.bvh.traverse.building_blocks import INF32, box_entry
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.config import parallel_section
from rayaccel.dtypes import FloatArray, Int64Array, IntArray
from rayaccel.kernels.triangle import ray_triangle
from rayaccel.rays.batch import RayBatch
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.run import PARALLEL_MIN_RAYS
from rayaccel.trace.skeleton import RAY_CHUNK

#: Hits of one ray sorted by insertion sort up to this many; heapsort beyond.
INSERTION_SORT_MAX = 24


def hit_before_py(t, prim, i, j):
    """Whether hit ``i`` sorts before hit ``j``: by ``t``, then primitive id."""
    return t[i] < t[j] or (t[i] == t[j] and prim[i] < prim[j])


hit_before = cpu_inline(hit_before_py)


def swap_hits_py(t, prim, u, v, i, j):
    """Swap hits ``i`` and ``j`` of the four parallel buffers."""
    t[i], t[j] = t[j], t[i]
    prim[i], prim[j] = prim[j], prim[i]
    u[i], u[j] = u[j], u[i]
    v[i], v[j] = v[j], v[i]


swap_hits = cpu_inline(swap_hits_py)


def sift_down_py(t, prim, u, v, base, root, end):
    """Restore the max-heap below ``root`` of the heap ``base + [0, end)`` (heapsort)."""
    while True:
        child = 2 * root + 1
        if child >= end:
            return
        if child + 1 < end and hit_before(t, prim, base + child, base + child + 1):
            child += 1
        if hit_before(t, prim, base + root, base + child):
            swap_hits(t, prim, u, v, base + root, base + child)
            root = child
        else:
            return


sift_down = cpu_inline(sift_down_py)


def sort_hits_py(t, prim, u, v, begin, end):
    """Sort hits ``begin:end`` of the buffers by ``t`` then primitive id, in place.

    Insertion sort for the usual few hits (up to :data:`INSERTION_SORT_MAX`), heapsort
    beyond. Also the sort of :mod:`rayaccel.bvh.traverse.all_hits_wide`.
    """
    n = end - begin
    if n <= INSERTION_SORT_MAX:
        for i in range(begin + 1, end):
            j = i
            while j > begin and hit_before(t, prim, j, j - 1):
                swap_hits(t, prim, u, v, j, j - 1)
                j -= 1
        return
    for root in range(n // 2 - 1, -1, -1):
        sift_down(t, prim, u, v, begin, root, n)
    for last in range(n - 1, 0, -1):
        swap_hits(t, prim, u, v, begin, begin + last)
        sift_down(t, prim, u, v, begin, 0, last)


sort_hits = cpu_inline(sort_hits_py)


@functools.cache
def _all_hits_kernel(fill: bool, parallel: bool) -> Any:
    """Return the counting (``fill=False``) or filling pass, serial or parallel."""

    @cpu_kernel(parallel=parallel)
    def kernel(
        bvh, origin, direction, tmin, tmax, n_mailbox, counts, splits,
        out_t, out_prim, out_u, out_v, max_hits, n_threads,
    ):  # fmt: skip
        """Count (``counts[r]``) or write (``out_*[splits[r]:splits[r + 1]]``) every hit."""
        _ = (fill, parallel)
        n_rays = origin.shape[0]
        n_chunks = (n_rays + RAY_CHUNK - 1) // RAY_CHUNK
        counter = new_counter()
        # Unpack the layout once: each field read inside the loops would be a new
        # reference (two atomic reference-count updates per read).
        box = bvh.inner_box
        refs = bvh.inner_ref
        leaf_first = bvh.leaf_first
        leaf_count = bvh.leaf_count
        tri = bvh.tri
        tri_prim = bvh.tri_prim
        root_box = bvh.root_box
        root = bvh.root_ref[0]
        for _worker in prange(worker_count(n_chunks, n_threads, parallel)):
            # Per-worker scratch: the stack, the mailbox and the sort buffers.
            stack = np.empty(STACK_SIZE, dtype=np.int32)
            mailbox = np.full(n_mailbox, -1, dtype=np.int32)
            buf_t = np.empty(max_hits, dtype=out_t.dtype)
            buf_prim = np.empty(max_hits, dtype=np.int32)
            buf_u = np.empty(max_hits, dtype=out_t.dtype)
            buf_v = np.empty(max_hits, dtype=out_t.dtype)
            while True:
                chunk = next_item(counter, n_chunks)
                if chunk < 0:
                    break
                for r in range(chunk * RAY_CHUNK, min(n_rays, (chunk + 1) * RAY_CHUNK)):
                    # The whole interval stays open: no hit culls anything.
                    (
                        _valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                        kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_top, _pad,
                        box_lo, box_hi, entry, _prim, _u, _v,
                    ) = ray_start(origin, direction, tmin, tmax, r, root_box)  # fmt: skip
                    n_hits = 0
                    node = root
                    sp = 0
                    done = entry == INF32
                    while not done:
                        if node >= 0:
                            # Inner row: go to a hit child, push the other if hit too.
                            t0 = box_entry(
                                box, node, 0, ox, oy, oz, ix, iy, iz, nx, ny, nz,
                                fx, fy, fz, box_lo, box_hi,
                            )  # fmt: skip
                            t1 = box_entry(
                                box, node, 6, ox, oy, oz, ix, iy, iz, nx, ny, nz,
                                fx, fy, fz, box_lo, box_hi,
                            )  # fmt: skip
                            if t0 < INF32:
                                if t1 < INF32:
                                    stack[sp] = refs[node, 13]
                                    sp += 1
                                node = refs[node, 12]
                                continue
                            if t1 < INF32:
                                node = refs[node, 13]
                                continue
                        else:
                            # Leaf: every triangle hit in the interval counts, once.
                            first = leaf_first[~node]
                            last = first + leaf_count[~node]
                            for i in range(first, last):
                                prim = tri_prim[i]
                                if n_mailbox > 0:
                                    if mailbox[prim] == r:
                                        continue
                                    mailbox[prim] = r
                                t, u, v = ray_triangle(
                                    tri, i, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz,
                                    t_lo, t_top,
                                )  # fmt: skip
                                if t < INF32:
                                    if fill:
                                        buf_t[n_hits] = t
                                        buf_prim[n_hits] = prim
                                        buf_u[n_hits] = u
                                        buf_v[n_hits] = v
                                    n_hits += 1
                        # Pop the next postponed subtree.
                        if sp == 0:
                            done = True
                        else:
                            sp -= 1
                            node = stack[sp]
                    if fill:
                        # Sort the ray's hits by t then primitive, copy to its slice.
                        sort_hits(buf_t, buf_prim, buf_u, buf_v, 0, n_hits)
                        base = splits[r]
                        for k in range(n_hits):
                            out_t[base + k] = buf_t[k]
                            out_prim[base + k] = buf_prim[k]
                            out_u[base + k] = buf_u[k]
                            out_v[base + k] = buf_v[k]
                    else:
                        counts[r] = n_hits

    return kernel


def _run(
    fill: bool,
    arrays: Any,
    rays: RayBatch,
    n_mailbox: int,
    counts: IntArray,
    splits: Int64Array,
    out: tuple[FloatArray, IntArray, FloatArray, FloatArray],
    max_hits: int,
) -> None:
    parallel = rays.n_rays >= PARALLEL_MIN_RAYS
    kernel = _all_hits_kernel(fill, parallel)
    args = (
        arrays, rays.origin, rays.direction, rays.tmin, rays.tmax, n_mailbox, counts, splits,
        *out, max_hits, numba.get_num_threads(),
    )  # fmt: skip
    if parallel:
        with parallel_section():
            kernel(*args)
    else:
        kernel(*args)


def empty_hits(n: int, precision: str) -> tuple[FloatArray, IntArray, FloatArray, FloatArray]:
    """Return ``n`` uninitialised hits ``t, prim, u, v``: ``t, u, v`` in the rays' precision."""
    real = np.float64 if precision == "float64" else np.float32
    return (
        np.empty(n, dtype=real),
        np.empty(n, dtype=np.int32),
        np.empty(n, dtype=real),
        np.empty(n, dtype=real),
    )


#: The parameters of the BVH's whole-batch queries (all hits, counts, pausable traversal).
BVH_QUERY_PARAMETERS = """\
Parameters
----------
bvh : Bvh2
mesh : TriangleMesh
    The mesh ``bvh`` was built over.
rays : RayBatch
cache : dict, optional
    Memo for the derived layouts (an ``Accel`` passes its own).
"""


@with_sections(BVH_QUERY_PARAMETERS)
def count_all_hits(
    bvh: Bvh2, mesh: TriangleMesh, rays: RayBatch, cache: dict[str, Any] | None = None
) -> IntArray:
    """Return ``(n_rays,)`` int32: how many triangles each ray hits in ``[tmin, tmax]``.

    Each triangle is counted once per ray, even where the tree references it from
    several leaves (see the module docstring).
    """
    counts = np.zeros(rays.n_rays, dtype=np.int32)
    if rays.n_rays == 0:
        return counts
    arrays = packed_layout(bvh, mesh, cache).arrays()
    n_mailbox = bvh.n_prims if bvh.n_refs > bvh.n_prims else 0
    splits = np.zeros(1, dtype=np.int64)
    _run(False, arrays, rays, n_mailbox, counts, splits, empty_hits(0, rays.precision), 0)
    return counts


@with_sections(BVH_QUERY_PARAMETERS)
def list_all_hits(
    bvh: Bvh2, mesh: TriangleMesh, rays: RayBatch, cache: dict[str, Any] | None = None
) -> tuple[Int64Array, FloatArray, IntArray, FloatArray, FloatArray]:
    """Return every hit of every ray in ``[tmin, tmax]``, by ray, then ``t``, then primitive.

    Returns
    -------
    splits : (n_rays + 1,) int64
        Ray ``r``'s hits are entries ``splits[r]:splits[r + 1]`` (Open3D's ``ray_splits``).
    t : (n_hits,) float32 (float64 for float64 rays)
    prim : (n_hits,) int32
    u, v : (n_hits,) float32 (float64 for float64 rays)
        Barycentrics of each hit: ``(1-u-v)·A + u·B + v·C``.
    """
    n = rays.n_rays
    counts = np.zeros(n, dtype=np.int32)
    splits = np.zeros(n + 1, dtype=np.int64)
    if n == 0:
        return (splits, *empty_hits(0, rays.precision))
    arrays = packed_layout(bvh, mesh, cache).arrays()
    n_mailbox = bvh.n_prims if bvh.n_refs > bvh.n_prims else 0
    _run(False, arrays, rays, n_mailbox, counts, splits, empty_hits(0, rays.precision), 0)
    np.cumsum(counts, out=splits[1:])
    out = empty_hits(int(splits[-1]), rays.precision)
    _run(True, arrays, rays, n_mailbox, counts, splits, out, int(counts.max()))
    return (splits, *out)
