"""Pieces shared by the top-down BVH builders.

Builders work on a temporary node pool in which every inner node's two children
are allocated as an adjacent pair, but where parallel subtree builds may leave
unused slots. :func:`compact_to_canonical` renumbers the reachable nodes in
depth-first order (root 0, siblings adjacent), which is the canonical
:class:`~rayaccel.bvh.layouts.bvh2.Bvh2` and keeps a subtree's nodes close in memory.

References are 32-byte rows ``[lo, id bits, hi, 0]`` (:func:`triangle_ref_rows`,
:func:`ref_rows`) that the binned and spatial splits partition in place;
:func:`ref_range_bounds` gives a range's box and doubled-centroid box. The depth
bound (:func:`depth_forces_median`) is what every top-down split function obeys.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._hugepages import empty_huge
from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.bvh.builders.refs import BuildRefs, check_refs, remove_leaf_duplicates
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2
from rayaccel.dtypes import INDEX, REAL, FloatArray
from rayaccel.scene.mesh import TriangleMesh


@cpu_kernel(parallel=True)
def primitive_bounds(triangles):
    """Return ``(lo, hi, centroid)``, each ``(F, 3)`` float32, of ``triangles (F, 3, 3)``.

    The centroid is the centre of the triangle's box (what binning uses).
    """
    n = triangles.shape[0]
    lo = empty_huge((n, 3), np.float32)
    hi = empty_huge((n, 3), np.float32)
    centroid = empty_huge((n, 3), np.float32)
    for i in prange(n):
        for a in range(3):
            x0 = triangles[i, 0, a]
            x1 = triangles[i, 1, a]
            x2 = triangles[i, 2, a]
            low = min(x0, min(x1, x2))
            high = max(x0, max(x1, x2))
            lo[i, a] = low
            hi[i, a] = high
            centroid[i, a] = np.float32(0.5) * low + np.float32(0.5) * high
    return lo, hi, centroid


@cpu_inline
def _corner_extent(vertices, faces, i, a):
    """Return the smallest and largest coordinate ``a`` of triangle ``i``'s corners."""
    x0 = vertices[faces[i, 0], a]
    x1 = vertices[faces[i, 1], a]
    x2 = vertices[faces[i, 2], a]
    return min(x0, min(x1, x2)), max(x0, max(x1, x2))


@cpu_kernel(parallel=True)
def triangle_bounds(vertices, faces):
    """Return ``(lo, hi)``, each ``(F, 3)`` float32: the box of every triangle of a mesh.

    Reads the corners through ``faces`` (no ``(F, 3, 3)`` copy of the corners).
    """
    n = faces.shape[0]
    lo = empty_huge((n, 3), np.float32)
    hi = empty_huge((n, 3), np.float32)
    for i in prange(n):
        for a in range(3):
            lo[i, a], hi[i, a] = _corner_extent(vertices, faces, i, a)
    return lo, hi


@cpu_kernel(parallel=True)
def triangle_ref_rows(vertices, faces):
    """Return the ``(F, 8)`` float32 reference rows ``[lo, id, hi, 0]`` of a mesh's triangles.

    Column 3 holds the triangle id as int32 bits; the top-down builders partition
    these 32-byte rows in place.
    """
    n = faces.shape[0]
    refs = empty_huge((n, 8), np.float32)
    ids = refs.view(np.int32)
    for i in prange(n):
        for a in range(3):
            refs[i, a], refs[i, 4 + a] = _corner_extent(vertices, faces, i, a)
        ids[i, 3] = i
        refs[i, 7] = 0
    return refs


def ref_rows(refs: BuildRefs) -> np.ndarray:
    """Return the ``(m, 8)`` float32 reference rows of pre-built ``refs``.

    Same row layout as :func:`triangle_ref_rows`: ``[lo, prim id bits, hi, 0]``.
    """
    rows = np.zeros((refs.n_refs, 8), dtype=np.float32)
    rows[:, 0:3] = refs.lo
    rows[:, 4:7] = refs.hi
    rows.view(np.int32)[:, 3] = refs.prim
    return rows


def _ref_range_bounds_py(refs, begin, end, out):
    """Write the box ``out[0:6]`` and doubled-centroid box ``out[6:12]`` of ``refs[begin:end]``.

    ``refs`` are reference rows (:func:`triangle_ref_rows`); a row's doubled centroid
    is ``lo + hi``, the binning key of the top-down builders.
    """
    for a in range(3):
        out[a] = np.inf
        out[3 + a] = -np.inf
        out[6 + a] = np.inf
        out[9 + a] = -np.inf
    for i in range(begin, end):
        for a in range(3):
            out[a] = min(out[a], refs[i, a])
            out[3 + a] = max(out[3 + a], refs[i, 4 + a])
            c = refs[i, a] + refs[i, 4 + a]
            out[6 + a] = min(out[6 + a], c)
            out[9 + a] = max(out[9 + a], c)


ref_range_bounds = cpu_inline(_ref_range_bounds_py)


def reference_boxes(
    mesh: TriangleMesh, refs: BuildRefs | None, builder: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``(lo, hi, prim)`` of the references a builder builds over.

    One reference per triangle (its box, computed in parallel) when ``refs`` is None,
    else the checked pre-built ``refs`` (``+presplit``); errors name ``builder``.
    """
    if refs is None:
        lo, hi = triangle_bounds(mesh.vertices, mesh.faces)
        return lo, hi, np.arange(mesh.n_triangles, dtype=np.int32)
    lo, hi, prim = check_refs(refs, mesh, builder)
    return lo, hi, prim


def _ceil_log2_py(n):
    """Return the smallest ``k`` with ``2**k >= n`` (0 for n <= 1)."""
    k = 0
    while (1 << k) < n:
        k += 1
    return k


ceil_log2 = cpu_inline(_ceil_log2_py)


def depth_forces_median(depth, count, max_leaf_size):
    """Return whether a node must be split by the balanced median to keep depth bounded.

    A median split halves the count, so a node of ``count`` primitives needs at most
    ``ceil_log2(ceil(count / max_leaf_size))`` more levels; we switch to median splits
    while that still fits under ``MAX_DEPTH`` with one level to spare.
    """
    leaves = (count + max_leaf_size - 1) // max_leaf_size
    return depth + ceil_log2(leaves) >= MAX_DEPTH - 1


depth_forces_median = cpu_inline(depth_forces_median)


@cpu_kernel(parallel=True)
def _compact_kernel(t_lo, t_hi, t_first, t_count, n_used_hint):
    """Renumber reachable pool nodes depth-first; return canonical arrays.

    The walk carries each node's new id on its stack, so it writes the new
    ``first``/``count`` at once and needs no old-to-new map of the whole pool
    (filling that map and writing it at scattered places took about a quarter of this
    kernel's time on the kitchen).
    """
    n_out = max(n_used_hint, 1)
    order = empty_huge(n_out, np.int32)
    first = empty_huge(n_out, np.int32)
    count = empty_huge(n_out, np.int32)
    # Depth-first walk; a pair of children gets consecutive new ids when its parent is numbered.
    stack_old = np.empty(2 * MAX_DEPTH + 4, dtype=np.int32)
    stack_new = np.empty(2 * MAX_DEPTH + 4, dtype=np.int32)
    stack_old[0] = 0
    stack_new[0] = 0
    sp = 1
    order[0] = 0
    next_id = 1
    while sp > 0:
        sp -= 1
        old = stack_old[sp]
        new = stack_new[sp]
        n = t_count[old]
        count[new] = n
        if n == 0:
            left = t_first[old]
            first[new] = next_id
            order[next_id] = left
            order[next_id + 1] = left + 1
            stack_old[sp] = left + 1
            stack_new[sp] = next_id + 1
            stack_old[sp + 1] = left
            stack_new[sp + 1] = next_id
            sp += 2
            next_id += 2
        else:
            first[new] = t_first[old]
    lo = empty_huge((next_id, 3), np.float32)
    hi = empty_huge((next_id, 3), np.float32)
    # Gather the boxes in the new order (independent rows: parallel).
    for new in prange(next_id):
        old = order[new]
        for a in range(3):
            lo[new, a] = t_lo[old, a]
            hi[new, a] = t_hi[old, a]
    return lo, hi, first[:next_id], count[:next_id]


def compact_to_canonical(
    t_lo: FloatArray,
    t_hi: FloatArray,
    t_first: np.ndarray,
    t_count: np.ndarray,
    prim_index: np.ndarray,
    n_prims: int,
    n_used: int,
) -> Bvh2:
    """Turn a node pool rooted at slot 0 into a canonical :class:`Bvh2`.

    Leaves keep their ``first`` offsets into ``prim_index``; a builder whose leaves
    are not in depth-first order of ``prim_index`` must reorder it itself. With more
    references than primitives (pre-split input), a leaf's repeated primitives are
    dropped (:func:`rayaccel.bvh.builders.refs.remove_leaf_duplicates`).
    """
    lo, hi, first, count = _compact_kernel(t_lo, t_hi, t_first, t_count, max(n_used, 1))
    return canonical_bvh2(lo, hi, first, count, prim_index, n_prims)


def canonical_bvh2(
    lo: np.ndarray,
    hi: np.ndarray,
    first: np.ndarray,
    count: np.ndarray,
    prim_index: np.ndarray,
    n_prims: int,
) -> Bvh2:
    """Return the :class:`Bvh2` of a builder's canonical arrays, any leaf's repeats dropped.

    The arrays become contiguous float32/int32; with more references than primitives
    (pre-split input) a leaf's repeated primitives are dropped
    (:func:`rayaccel.bvh.builders.refs.remove_leaf_duplicates`).
    """
    bvh = Bvh2(
        node_lo=np.ascontiguousarray(lo, dtype=REAL),
        node_hi=np.ascontiguousarray(hi, dtype=REAL),
        node_first=np.ascontiguousarray(first, dtype=INDEX),
        node_count=np.ascontiguousarray(count, dtype=INDEX),
        prim_index=np.ascontiguousarray(prim_index, dtype=INDEX),
        n_prims=n_prims,
    )
    return remove_leaf_duplicates(bvh)
