"""Nearest-point queries on a binary BVH: the closest point of the mesh to each query point.

Open3D's ``compute_closest_points``, and the distance part of signed distance and
occupancy. The walk is a branch-and-bound depth-first search over the packed rows of
:mod:`rayaccel.bvh.layouts.bvh2` (both children's boxes in one 64-byte row):

* at an inner row, the squared distance from the point to each child's box is the
  lower bound of every triangle below it; children farther than the best squared
  distance found so far are pruned, the nearer is entered first (front to back by
  box distance) and the other is pushed with its bound;
* a popped subtree whose bound now exceeds the best distance is dropped unfetched;
* at a leaf, each triangle's closest point comes from Ericson's Voronoi-region test
  (:mod:`rayaccel.kernels.point_triangle`), in float64.

Bounds and distances are float64 (the float32 box corners are exact there), so the
pruning is exact: a subtree is dropped only if every triangle in it is strictly
farther than the best. Among triangles at exactly the same distance the lowest
primitive id wins, whatever the tree, so every builder returns the same triangle.
A triangle referenced from several leaves (spatial splits) is simply met again.

Points run in chunks taken from a shared counter by one worker per thread
(:mod:`rayaccel._work`); each point writes only its own outputs.

References
----------
C. Ericson, *Real-Time Collision Detection*, Morgan Kaufmann 2005, §5.1.5 (point
to triangle) and §6.5 (branch-and-bound descent of a bounding-volume hierarchy).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.layouts.bvh2 import STACK_SIZE, Bvh2
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.config import parallel_section
from rayaccel.dtypes import IntArray
from rayaccel.kernels.point_triangle import closest_point_triangle
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.run import PARALLEL_MIN_RAYS

#: Query points per work item.
POINT_CHUNK = 64
#: Below this many points the query runs on the calling thread.
PARALLEL_MIN_POINTS = PARALLEL_MIN_RAYS // 4


def point_box_d2_py(box, row, col, px, py, pz):
    """Squared float64 distance from a point to the interleaved box ``box[row, col:col+6]``."""
    d2 = 0.0
    lo = float(box[row, col])
    hi = float(box[row, col + 1])
    d = lo - px if px < lo else (px - hi if px > hi else 0.0)
    d2 += d * d
    lo = float(box[row, col + 2])
    hi = float(box[row, col + 3])
    d = lo - py if py < lo else (py - hi if py > hi else 0.0)
    d2 += d * d
    lo = float(box[row, col + 4])
    hi = float(box[row, col + 5])
    d = lo - pz if pz < lo else (pz - hi if pz > hi else 0.0)
    d2 += d * d
    return d2


point_box_d2 = cpu_inline(point_box_d2_py)


@functools.cache
def _closest_kernel(parallel: bool) -> Any:
    """Return the nearest-point kernel, serial or parallel over point chunks."""

    @cpu_kernel(parallel=parallel)
    def kernel(bvh, points, out_d2, out_prim, out_u, out_v, n_threads):
        """Write each point's squared distance, nearest primitive and its barycentrics."""
        _ = parallel
        n_points = points.shape[0]
        n_chunks = (n_points + POINT_CHUNK - 1) // POINT_CHUNK
        counter = new_counter()
        box = bvh.inner_box
        refs = bvh.inner_ref
        for _worker in prange(worker_count(n_chunks, n_threads, parallel)):
            stack_ref = np.empty(STACK_SIZE, dtype=np.int32)
            stack_d2 = np.empty(STACK_SIZE, dtype=np.float64)
            while True:
                chunk = next_item(counter, n_chunks)
                if chunk < 0:
                    break
                for q in range(chunk * POINT_CHUNK, min(n_points, (chunk + 1) * POINT_CHUNK)):
                    px = points[q, 0]
                    py = points[q, 1]
                    pz = points[q, 2]
                    best = math.inf
                    best_prim = -1
                    best_u = 0.0
                    best_v = 0.0
                    node = bvh.root_ref[0]
                    sp = 0
                    done = False
                    while not done:
                        if node >= 0:
                            # Inner row: bound both children, enter the nearer one.
                            d0 = point_box_d2(box, node, 0, px, py, pz)
                            d1 = point_box_d2(box, node, 6, px, py, pz)
                            c0 = refs[node, 12]
                            c1 = refs[node, 13]
                            if d1 < d0:
                                d0, d1 = d1, d0
                                c0, c1 = c1, c0
                            if d0 <= best:
                                if d1 <= best:
                                    stack_ref[sp] = c1
                                    stack_d2[sp] = d1
                                    sp += 1
                                node = c0
                                continue
                        else:
                            # Leaf: exact distance to each triangle; ties to the lower id.
                            first = bvh.leaf_first[~node]
                            last = first + bvh.leaf_count[~node]
                            for i in range(first, last):
                                d2, u, v = closest_point_triangle(bvh.tri, i, px, py, pz)
                                prim = bvh.tri_prim[i]
                                if d2 < best or (d2 == best and prim < best_prim):
                                    best = d2
                                    best_prim = prim
                                    best_u = u
                                    best_v = v
                        # Pop the next subtree that may still hold a nearer triangle.
                        done = True
                        while sp > 0:
                            sp -= 1
                            if stack_d2[sp] <= best:
                                node = stack_ref[sp]
                                done = False
                                break
                    out_d2[q] = best
                    out_prim[q] = best_prim
                    out_u[q] = best_u
                    out_v[q] = best_v

    return kernel


def closest_points(
    bvh: Bvh2, mesh: TriangleMesh, points: np.ndarray, cache: dict[str, Any] | None = None
) -> tuple[np.ndarray, IntArray, np.ndarray, np.ndarray]:
    """Return the nearest triangle of ``mesh`` to each point, by a BVH nearest-point walk.

    Parameters
    ----------
    bvh : Bvh2
    mesh : TriangleMesh
        The mesh ``bvh`` was built over.
    points : (n, 3) float64, C-contiguous, finite
        Query points (validated by the caller).
    cache : dict, optional
        Memo for the packed layout (an ``Accel`` passes its own).

    Returns
    -------
    d2 : (n,) float64
        Squared distance to the nearest triangle.
    prim : (n,) int32
        Its id (the lowest among triangles at exactly that distance).
    u, v : (n,) float64
        Barycentrics of the closest point on it: ``(1-u-v)·A + u·B + v·C``.
    """
    n = points.shape[0]
    d2 = np.empty(n, dtype=np.float64)
    prim: IntArray = np.empty(n, dtype=np.int32)
    u = np.empty(n, dtype=np.float64)
    v = np.empty(n, dtype=np.float64)
    if n == 0:
        return d2, prim, u, v
    arrays = packed_layout(bvh, mesh, cache).arrays()
    parallel = n >= PARALLEL_MIN_POINTS
    kernel = _closest_kernel(parallel)
    args = (arrays, points, d2, prim, u, v, numba.get_num_threads())
    if parallel:
        with parallel_section():
            kernel(*args)
    else:
        kernel(*args)
    return d2, prim, u, v


def barycentric_points(mesh: TriangleMesh, prim: IntArray, u: np.ndarray, v: np.ndarray) -> Any:
    """Return ``(n, 3)`` float64 points ``(1-u-v)·A + u·B + v·C`` on triangles ``prim``.

    The corners are the float64 ones of a float64 mesh.
    """
    vertices = mesh.vertices if mesh.vertices64 is None else mesh.vertices64
    corners = vertices[mesh.faces[prim]].astype(np.float64)
    w = (1.0 - u - v)[:, None]
    return w * corners[:, 0] + u[:, None] * corners[:, 1] + v[:, None] * corners[:, 2]
