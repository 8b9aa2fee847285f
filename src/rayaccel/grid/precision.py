"""Float64 meshes in a float32 grid: the cell margins already hold the float64 triangles.

A mesh with ``precision="float64"`` (huge coordinates: geospatial, CAD) is intersected
in float64, but its grid is the one every builder makes over the float32 rounding of
the vertices. At ``1e7`` a float32 ulp ``u`` is 1 and a float64 triangle may stick out of
its rounded twin by ``u/2`` on every axis (a point of the float64 triangle is the same
barycentric combination of corners each within ``u/2``). Nothing is added at build time,
because the grids' own margins are already wider than that, for ``grid.uniform``, its
skipping variants (``grid.distance``, ``grid.macro_regions``, ``grid.mipmap``) and
``grid.two_level``:

1. *Box.* :func:`rayaccel.grid.builders.uniform.grid_box` moves the scene box at least
   one float32 step outward, so (the argument of :mod:`rayaccel.bvh.precision`) every
   float64 corner, hence every float64 triangle, lies inside the grid box.
2. *Cells.* A triangle is listed in every cell whose box, widened by the margin ``M``
   of :func:`~rayaccel.grid.layouts.uniform.cell_margin` (the two-level leaves: the
   smaller of their own and the top cell's), its float32 triangle overlaps. ``M``
   includes ``2^-21·(|lo_a| + |hi_a|) >= 4·2^-23·X_a >= 4u`` on each axis, ``X_a`` the
   largest magnitude in the box, ``u`` the float32 ulp there. The builder computes the
   widened box in float32 (``lo + z·size - M``: up to three roundings, ``1.5u``); the
   float64 walk computes the cell's planes from the same float32 ``lo`` and ``size``,
   in float64 for the uniform grid (:func:`~rayaccel.grid.layouts.uniform.trace_layout`
   stores them in the rows' precision), and by the builder's own float32 operations for
   the two-level grid's top-cell origins and leaf planes (each within ``1u`` of the
   builder's, a fused multiply-add being the only difference). So where the walk is in
   a cell, the ray point lies within float64 rounding of that cell's planes, and every
   point within ``M - 2u >= 2u > u/2`` of it lies in the builder's widened box. A float64
   hit point ``P`` on ``T`` in the cell the walk is in therefore has a point of the
   float32 ``T`` within ``u/2``, inside the widened box: ``T`` is listed there.
3. *Walks.* The DDA keeps every hit, whichever cell it lies in (a mailboxed triangle
   was tested once and its hit kept; the hit interval only shrinks), and ends only once
   the current cell's exit lies beyond the closest hit plus the culling pad
   (:mod:`rayaccel.grid.traverse.dda`). So the cell holding ``P`` is walked before the
   walk ends, and by (2.) it lists ``T``.

``grid.irregular`` is refused for float64 meshes (:data:`FLOAT64_REFUSED`): its walk
enters cells through a lattice of voxels whose planes round differently from the
two-level leaves its lists come from, and that difference has not been bounded against
the margins with the float64 triangles' ``u/2`` added.

:func:`check_conservative` is what ``Accel.validate`` checks for a float64 grid.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.errors import StructureInvariantError
from rayaccel.grid.layouts.two_level import TwoLevelGrid
from rayaccel.grid.layouts.uniform import UniformGrid
from rayaccel.kernels.overlap import triangle_box_overlap
from rayaccel.scene.mesh import TriangleMesh

#: Grid builders that refuse float64 meshes, and why.
FLOAT64_REFUSED = {
    "grid.irregular": (
        "its walk enters cells by a voxel lattice whose rounding against the two-level "
        "leaves' margins is not bounded for float64 triangles yet"
    ),
}


@cpu_kernel(parallel=True)
def _first_unlisted(tri, lo, size, res, cell_start, prim_index):
    """Return, per triangle, a cell its float64 version overlaps but that does not list it.

    Cells are the plain boxes ``lo + k·size`` (float64, not widened); -1 where none. The
    overlap test is the full separating axis test, the triangle's plane included:
    :func:`~rayaccel.kernels.overlap.touches` leaves that axis out and so names cells the
    triangle's plane passes by, which the builder rightly does not list. Where float64
    rounding of a sliver's normal makes the plane axis separate falsely, a cell goes
    unchecked; it never raises falsely.
    """
    n = tri.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    for p in prange(n):
        c_lo = np.empty(3, dtype=np.float64)
        c_hi = np.empty(3, dtype=np.float64)
        k0 = np.empty(3, dtype=np.int64)
        k1 = np.empty(3, dtype=np.int64)
        for a in range(3):
            t_lo = min(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
            t_hi = max(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
            k0[a] = max(np.int64(np.floor((t_lo - lo[a]) / size[a])) - 1, 0)
            k1[a] = min(np.int64(np.floor((t_hi - lo[a]) / size[a])) + 1, res[a] - 1)
        for z in range(k0[2], k1[2] + 1):
            for y in range(k0[1], k1[1] + 1):
                for x in range(k0[0], k1[0] + 1):
                    c_lo[0] = lo[0] + x * size[0]
                    c_hi[0] = lo[0] + (x + 1) * size[0]
                    c_lo[1] = lo[1] + y * size[1]
                    c_hi[1] = lo[1] + (y + 1) * size[1]
                    c_lo[2] = lo[2] + z * size[2]
                    c_hi[2] = lo[2] + (z + 1) * size[2]
                    if not triangle_box_overlap(tri, p, c_lo, c_hi):
                        continue
                    cell = x + res[0] * (y + res[1] * z)
                    first = cell_start[cell]
                    last = cell_start[cell + 1]
                    at = first + np.searchsorted(prim_index[first:last], p)
                    if at >= last or prim_index[at] != p:
                        out[p] = cell
                        break
                if out[p] >= 0:
                    break
            if out[p] >= 0:
                break
    return out


def check_conservative(grid: UniformGrid | TwoLevelGrid, mesh: TriangleMesh) -> None:
    """Raise :class:`StructureInvariantError` unless ``grid`` holds ``mesh``'s float64 triangles.

    Checks that every float64 corner lies in the grid box and that every triangle is
    listed in each (top) cell whose plain box its float64 version overlaps.
    """
    top = grid.top if isinstance(grid, TwoLevelGrid) else grid
    tri = mesh.triangles64()
    corners = tri.reshape(-1, 3)
    if (corners < top.lo).any() or (corners > top.hi).any():
        raise StructureInvariantError("grid: a float64 triangle sticks out of the grid box")
    size = ((top.hi - top.lo) / top.res).astype(np.float32).astype(np.float64)
    unlisted = _first_unlisted(
        tri, top.lo.astype(np.float64), size, top.res.astype(np.int64), top.cell_start,
        top.prim_index,
    )  # fmt: skip
    if (unlisted >= 0).any():
        p = int(np.argmax(unlisted >= 0))
        raise StructureInvariantError(
            f"grid: float64 triangle {p} overlaps cell {int(unlisted[p])} but is not listed there"
        )
