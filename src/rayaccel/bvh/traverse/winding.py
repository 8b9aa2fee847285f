"""Generalised winding numbers of query points: brute force and hierarchical (Barill 2018).

The generalised winding number of a point ``q`` with respect to a triangle mesh is
``w(q) = Σ Ω_i(q) / 4π``, the signed solid angles of its triangles
(:func:`rayaccel.kernels.point_triangle.triangle_solid_angle_py`; Jacobson, Kavan,
Sorkine-Hornung 2013). For a closed, consistently outward-oriented mesh it is 1
inside and 0 outside; for an open or self-intersecting mesh it varies smoothly
between, and ``w > 1/2`` is the robust inside test the paper proposes.

:func:`winding_numbers_brute` sums every triangle for every point: O(F) per point,
the oracle. :func:`winding_numbers` is the fast winding number of Barill, Dickson,
Schmidt, Levin and Jacobson 2018 on a binary BVH, with the first-order (dipole)
expansion: each node stores the area-weighted normal sum ``N = Σ a_i n_i`` of its
triangles, their area-weighted centroid ``c`` and the radius ``r`` of a ball around
``c`` holding its box. A node whose centre is farther than ``β·r`` from the query
contributes ``N·(c - q) / (4π |c - q|³)`` (the far field of its triangles as one
dipole); nearer nodes are opened, and leaves are summed exactly. With ``β = 2`` (the
paper's default) the error is a few thousandths far from the surface, and exact
wherever the query is near the surface (those triangles are summed exactly), which
is where an inside/outside decision is decided. Cost O(log F) per point.

The dipole sums need each triangle once, so the hierarchy is built on a tree whose
leaves do not repeat triangles (``n_refs == n_prims``).

References
----------
A. Jacobson, L. Kavan, O. Sorkine-Hornung, "Robust Inside-Outside Segmentation using
Generalized Winding Numbers", ACM TOG 32(4), 2013.
G. Barill, N. Dickson, R. Schmidt, D. I. W. Levin, A. Jacobson, "Fast Winding Numbers
for Soups and Clouds", ACM TOG 37(4), 2018.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.layouts.bvh2 import STACK_SIZE, Bvh2
from rayaccel.config import parallel_section
from rayaccel.kernels.point_triangle import triangle_solid_angle
from rayaccel.trace.run import memoised_layout

#: Far-field acceptance: a node is one dipole when its centre is beyond BETA radii.
BETA = 2.0
#: Query points per work item.
POINT_CHUNK = 64
#: Below this many points the query runs on the calling thread.
PARALLEL_MIN_POINTS = 1024
FOUR_PI = 4.0 * math.pi


@dataclass(frozen=True, slots=True, eq=False)
class DipoleTree:
    """Per-node far-field data of a ``bvh2`` (see the module docstring).

    Attributes
    ----------
    normal : (n_nodes, 3) float64
        Area-weighted normal sum ``Σ a_i n_i`` (half the sum of corner cross products).
    centre : (n_nodes, 3) float64
        Area-weighted centroid of the node's triangles (box centre if their area is 0).
    radius : (n_nodes,) float64
        Distance from ``centre`` to the farthest corner of the node's box.
    """

    normal: np.ndarray
    centre: np.ndarray
    radius: np.ndarray

    def nbytes(self) -> int:
        """Return the size in bytes (56 per node)."""
        return int(self.normal.nbytes + self.centre.nbytes + self.radius.nbytes)


@cpu_kernel()
def _dipole_kernel(
    node_lo, node_hi, node_first, node_count, prim_index, tri, normal, centre, radius
):
    """Fill every node's dipole data bottom-up (children always follow their parent)."""
    n = node_count.shape[0]
    area = np.zeros(n, dtype=np.float64)
    for node in range(n - 1, -1, -1):
        nx = 0.0
        ny = 0.0
        nz = 0.0
        cx = 0.0
        cy = 0.0
        cz = 0.0
        total = 0.0
        if node_count[node] > 0:
            # Leaf: half cross products and area-weighted centroids of its triangles.
            for k in range(node_first[node], node_first[node] + node_count[node]):
                p = prim_index[k]
                ax = float(tri[p, 0])
                ay = float(tri[p, 1])
                az = float(tri[p, 2])
                ux = float(tri[p, 3]) - ax
                uy = float(tri[p, 4]) - ay
                uz = float(tri[p, 5]) - az
                vx = float(tri[p, 6]) - ax
                vy = float(tri[p, 7]) - ay
                vz = float(tri[p, 8]) - az
                hx = 0.5 * (uy * vz - uz * vy)
                hy = 0.5 * (uz * vx - ux * vz)
                hz = 0.5 * (ux * vy - uy * vx)
                a = math.sqrt(hx * hx + hy * hy + hz * hz)
                nx += hx
                ny += hy
                nz += hz
                cx += a * (ax + (ux + vx) / 3.0)
                cy += a * (ay + (uy + vy) / 3.0)
                cz += a * (az + (uz + vz) / 3.0)
                total += a
        else:
            # Inner node: sums of its two children.
            for child in range(node_first[node], node_first[node] + 2):
                nx += normal[child, 0]
                ny += normal[child, 1]
                nz += normal[child, 2]
                cx += area[child] * centre[child, 0]
                cy += area[child] * centre[child, 1]
                cz += area[child] * centre[child, 2]
                total += area[child]
        normal[node, 0] = nx
        normal[node, 1] = ny
        normal[node, 2] = nz
        area[node] = total
        if total > 0.0:
            centre[node, 0] = cx / total
            centre[node, 1] = cy / total
            centre[node, 2] = cz / total
        else:
            for a in range(3):
                centre[node, a] = 0.5 * (float(node_lo[node, a]) + float(node_hi[node, a]))
        # Radius: the farthest box corner from the centre bounds every triangle.
        r2 = 0.0
        for a in range(3):
            d = max(abs(float(node_lo[node, a]) - centre[node, a]),
                    abs(float(node_hi[node, a]) - centre[node, a]))  # fmt: skip
            r2 += d * d
        radius[node] = math.sqrt(r2)


def dipole_tree(bvh: Bvh2, tri: np.ndarray, cache: dict[str, Any] | None) -> DipoleTree:
    """Return the dipole data of ``bvh`` over triangle rows ``tri``, memoised in ``cache``.

    Raises
    ------
    ValueError
        The tree references a triangle from several leaves (the sums would count it twice);
        :func:`rayaccel.bvh.geometry.query_bvh` never passes such a tree.
    """
    if bvh.n_refs != bvh.n_prims:
        raise ValueError("dipole_tree: the tree repeats triangles (n_refs > n_prims)")

    def make() -> DipoleTree:
        n = bvh.n_nodes
        out = DipoleTree(
            np.zeros((n, 3), dtype=np.float64),
            np.zeros((n, 3), dtype=np.float64),
            np.zeros(n, dtype=np.float64),
        )
        # Float64 corners for every mesh (float32 ones widened): one compiled signature.
        _dipole_kernel(
            bvh.node_lo, bvh.node_hi, bvh.node_first, bvh.node_count, bvh.prim_index,
            np.ascontiguousarray(tri, dtype=np.float64), out.normal, out.centre, out.radius,
        )  # fmt: skip
        return out

    return memoised_layout(cache, "bvh2.dipoles", make)


@functools.cache
def _winding_kernel(hierarchical: bool, parallel: bool) -> Any:
    """Return the winding-number kernel: hierarchical or brute force, serial or parallel."""

    @cpu_kernel(parallel=parallel)
    def kernel(bvh, normal, centre, radius, tri, points, beta, out, n_threads):
        """Write each point's generalised winding number to ``out``."""
        _ = (hierarchical, parallel)
        n_points = points.shape[0]
        n_chunks = (n_points + POINT_CHUNK - 1) // POINT_CHUNK
        counter = new_counter()
        for _worker in prange(worker_count(n_chunks, n_threads, parallel)):
            stack = np.empty(STACK_SIZE, dtype=np.int32)
            while True:
                chunk = next_item(counter, n_chunks)
                if chunk < 0:
                    break
                for q in range(chunk * POINT_CHUNK, min(n_points, (chunk + 1) * POINT_CHUNK)):
                    px = points[q, 0]
                    py = points[q, 1]
                    pz = points[q, 2]
                    total = 0.0
                    if not hierarchical:
                        for p in range(tri.shape[0]):
                            total += triangle_solid_angle(tri, p, px, py, pz)
                        out[q] = total / FOUR_PI
                        continue
                    stack[0] = 0
                    sp = 1
                    while sp > 0:
                        sp -= 1
                        node = stack[sp]
                        dx = centre[node, 0] - px
                        dy = centre[node, 1] - py
                        dz = centre[node, 2] - pz
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 > (beta * radius[node]) ** 2:
                            # Far: the node's triangles as one dipole at its centre.
                            dot = normal[node, 0] * dx + normal[node, 1] * dy + normal[node, 2] * dz
                            total += dot / (d2 * math.sqrt(d2))
                        elif bvh.node_count[node] > 0:
                            # Near leaf: exact solid angles.
                            first = bvh.node_first[node]
                            for k in range(first, first + bvh.node_count[node]):
                                total += triangle_solid_angle(tri, bvh.prim_index[k], px, py, pz)
                        else:
                            # Near inner node: open it.
                            stack[sp] = bvh.node_first[node]
                            stack[sp + 1] = bvh.node_first[node] + 1
                            sp += 2
                    out[q] = total / FOUR_PI

    return kernel


def winding_numbers(
    bvh: Bvh2,
    tri: np.ndarray,
    points: np.ndarray,
    cache: dict[str, Any] | None = None,
    *,
    beta: float = BETA,
) -> np.ndarray:
    """Return ``(n,)`` float64 fast winding numbers (Barill et al. 2018) of ``points``.

    Parameters
    ----------
    bvh : Bvh2
        A tree that references each triangle once (``n_refs == n_prims``).
    tri : (F, 9) float32
        Triangle rows of the mesh (:meth:`rayaccel.scene.mesh.TriangleMesh.hit_rows`).
    points : (n, 3) float64, C-contiguous
    cache : dict, optional
        Memo for the dipole data (an ``Accel`` passes its own).
    beta : float
        Far-field acceptance ratio (larger: more accurate, slower).
    """
    dipoles = dipole_tree(bvh, tri, cache)
    return _run(True, bvh, dipoles, tri, points, beta)


def winding_numbers_brute(tri: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Return ``(n,)`` float64 exact winding numbers, summing every triangle (O(F) per point)."""
    n = 1
    empty = DipoleTree(np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n))
    bvh = Bvh2(
        np.zeros((1, 3), dtype=np.float32), np.zeros((1, 3), dtype=np.float32),
        np.zeros(1, dtype=np.int32), np.zeros(1, dtype=np.int32), np.zeros(0, dtype=np.int32), 0,
    )  # fmt: skip
    return _run(False, bvh, empty, tri, points, BETA)


def _run(
    hierarchical: bool, bvh: Bvh2, dipoles: DipoleTree, tri: np.ndarray, points: np.ndarray,
    beta: float,
) -> np.ndarray:  # fmt: skip
    n = points.shape[0]
    out = np.zeros(n, dtype=np.float64)
    if n == 0:
        return out
    parallel = n >= PARALLEL_MIN_POINTS
    kernel = _winding_kernel(hierarchical, parallel)
    args = (
        bvh.arrays(), dipoles.normal, dipoles.centre, dipoles.radius, tri, points,
        float(beta), out, numba.get_num_threads(),
    )  # fmt: skip
    if parallel:
        with parallel_section():
            kernel(*args)
    else:
        kernel(*args)
    return out
