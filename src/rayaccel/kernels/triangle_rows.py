"""A mesh's triangles as arrays: corners, their box, and the rows the intersection tests read.

Parallel passes over the face array, each giving the same array as the numpy fancy
indexing it stands for (see docs/performance.md for why they are kernels):

- :func:`triangle_corners`: the ``(F, 3, 3)`` corners ``vertices[faces]`` that builders
  read (:meth:`rayaccel.scene.mesh.TriangleMesh.triangles`);
- :func:`corner_bounds`: the box of the referenced vertices (``TriangleMesh.bounds``);
- :func:`hit_rows`: the ``(F, 9)`` rows the intersection tests read, a triangle whose
  doubled area is below the rows' smallest normal number collapsed to its first corner
  (:meth:`rayaccel.scene.mesh.TriangleMesh.hit_rows` says why). The area test is compiled
  without fast-math contraction (``exact=True``), so its cross product rounds as numpy's
  and a float64 triangle is called degenerate exactly when the unfused products say so;
- :func:`gather_rows`: rows put into a structure's reference order, so that a leaf or
  cell streams contiguous memory (:mod:`rayaccel.trace.leaf`).
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel


@cpu_kernel(parallel=True)
def triangle_corners(vertices, faces):
    """Return the ``(F, 3, 3)`` corners ``vertices[faces]`` (parallel gather)."""
    n = faces.shape[0]
    corners = np.empty((n, 3, 3), dtype=vertices.dtype)
    for f in prange(n):
        for c in range(3):
            v = faces[f, c]
            for k in range(3):
                corners[f, c, k] = vertices[v, k]
    return corners


#: Work chunks of :func:`corner_bounds` (each keeps its own partial box).
BOUNDS_CHUNKS = 64


@cpu_kernel(parallel=True)
def corner_bounds(vertices, faces):
    """Return ``(lo, hi)``, the box of the vertices ``faces`` reference (float32)."""
    n = faces.shape[0]
    part_lo = np.full((BOUNDS_CHUNKS, 3), np.inf, dtype=np.float32)
    part_hi = np.full((BOUNDS_CHUNKS, 3), -np.inf, dtype=np.float32)
    step = (n + BOUNDS_CHUNKS - 1) // BOUNDS_CHUNKS
    for chunk in prange(BOUNDS_CHUNKS):
        for f in range(chunk * step, min(n, (chunk + 1) * step)):
            for c in range(3):
                v = faces[f, c]
                for k in range(3):
                    x = vertices[v, k]
                    part_lo[chunk, k] = min(part_lo[chunk, k], x)
                    part_hi[chunk, k] = max(part_hi[chunk, k], x)
    lo = np.empty(3, dtype=np.float32)
    hi = np.empty(3, dtype=np.float32)
    for k in range(3):
        lo[k] = part_lo[:, k].min()
        hi[k] = part_hi[:, k].max()
    return lo, hi


@cpu_kernel(parallel=True, exact=True)
def hit_rows(vertices, faces, floor):
    """Return the ``(F, 9)`` corner rows of ``faces``, degenerate triangles collapsed.

    Parameters
    ----------
    vertices : (V, 3) float32 or float64
        Corner positions; the rows take their dtype.
    faces : (F, 3) int32
        Vertex indices, validated by the mesh.
    floor : float
        The smallest normal number of the rows' precision: a triangle whose doubled
        area (the sum of the float64 cross product's magnitudes) is not at least this
        is collapsed to its first corner.
    """
    n = faces.shape[0]
    rows = np.empty((n, 9), dtype=vertices.dtype)
    for f in prange(n):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        e0x = np.float64(vertices[b, 0]) - np.float64(vertices[a, 0])
        e0y = np.float64(vertices[b, 1]) - np.float64(vertices[a, 1])
        e0z = np.float64(vertices[b, 2]) - np.float64(vertices[a, 2])
        e1x = np.float64(vertices[c, 0]) - np.float64(vertices[a, 0])
        e1y = np.float64(vertices[c, 1]) - np.float64(vertices[a, 1])
        e1z = np.float64(vertices[c, 2]) - np.float64(vertices[a, 2])
        doubled_area = (
            abs(e0y * e1z - e0z * e1y) + abs(e0z * e1x - e0x * e1z) + abs(e0x * e1y - e0y * e1x)
        )
        if not doubled_area >= floor:
            b = a
            c = a
        for k in range(3):
            rows[f, k] = vertices[a, k]
            rows[f, 3 + k] = vertices[b, k]
            rows[f, 6 + k] = vertices[c, k]
    return rows


@cpu_kernel(parallel=True)
def gather_rows(rows, index):
    """Return ``rows[index]`` (parallel gather)."""
    out = np.empty((index.shape[0], rows.shape[1]), dtype=rows.dtype)
    for i in prange(index.shape[0]):
        for k in range(rows.shape[1]):
            out[i, k] = rows[index[i], k]
    return out
