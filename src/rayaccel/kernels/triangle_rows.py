"""Triangle rows for the intersection kernels: made from a mesh, gathered by a reference array.

Every traversal layout holds its triangles as ``(n, 9)`` rows (three corners) in its
own reference order, so a leaf or cell streams contiguous memory
(:mod:`rayaccel.trace.leaf`). :func:`hit_rows` makes the mesh's rows in one parallel
pass: the corners gathered from the vertex array, and a triangle whose doubled area is
below the rows' smallest normal number collapsed to its first corner
(:meth:`rayaccel.scene.mesh.TriangleMesh.hit_rows` says why). :func:`gather_rows` puts
rows into a structure's reference order.

The area test is compiled without fast-math contraction (``exact=True``): its cross
product then rounds as numpy's does, so a float64 triangle is called degenerate
exactly when the unfused products say so, on every machine.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel


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
