"""Exact triangle/box overlap by the separating axis theorem (Akenine-Möller 2001).

Akenine-Möller 2001, "Fast 3D Triangle-Box Overlap Testing" (Journal of Graphics
Tools 6(1)). Two convex polyhedra are disjoint exactly when their projections on
some axis are disjoint, and for a triangle and an axis-aligned box it suffices to
try 13 axes:

1. the three box face normals ``x, y, z`` (the triangle's bounds against the box);
2. the triangle's normal ``n = e0 × e1`` (the triangle's plane against the box: the
   box's projection radius is ``h · |n|``);
3. the nine cross products ``u_i × e_j`` of a box axis and a triangle edge.

Fewer suffice when the triangle's extent along some box axis ``a`` lies within the
box's: the triangle then meets the box exactly when its projection along ``a`` meets
the box's face rectangle, a 2D test on the two other face axes and the three axes
``a × e_j``; with two such axes the third axis's interval test decides. A grid's
candidate cells often hold a triangle's whole extent along one or two axes, and their
tests then end after the face axes or three edge axes.

Grids use it to list the cells a triangle really touches rather than every cell of
its bounding box (cell/primitive pairs), as do kd-tree and octree builders.

Conventions: the box is *closed* and so is the triangle, so a triangle that only
touches the box (a vertex on a face, an edge along an edge, the plane through a
corner) overlaps it: an axis separates only when the projections are strictly
apart. Degenerate triangles (repeated vertices, collinear corners) and flat boxes
(``lo == hi`` on some axis) are handled by the same 13 axes: a zero axis never
separates, and the remaining ones still cover a segment or a point.

Arithmetic is float64 on the triangle moved to the box's centre, as in the paper.
For float32 input it is exact whenever the products involved fit in 53 bits (e.g.
coordinates on a coarse dyadic grid, which the tests use for touching cases);
otherwise a decision is affected only for contacts within float64 rounding
(~1e-16 relative), far below float32 resolution. Three projections are computed on
every edge axis (the paper skips the one equal to another in exact arithmetic),
which keeps the test symmetric in the vertices under rounding.

The ``*_py`` function is plain Python (the oracle, and the source of the CUDA
version); :func:`triangle_box_overlap` is its inlined CPU form.
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import cpu_inline


def edge_axis_separates_py(es, et, v0s, v0t, v1s, v1t, v2s, v2t, r):
    """Return whether a box-axis × edge axis separates the triangle from the box.

    The axis has components ``-et`` and ``es`` on the two box axes ``s, t`` it does not
    lie along (``e`` the edge), so corner ``i`` projects to ``es·v_it - et·v_is``; the
    box's projection radius is ``r``. Strictly apart only: touching never separates.
    """
    p0 = es * v0t - et * v0s
    p1 = es * v1t - et * v1s
    p2 = es * v2t - et * v2s
    return min(p0, p1, p2) > r or max(p0, p1, p2) < -r


edge_axis_separates = cpu_inline(edge_axis_separates_py)


def separating_axes_py(tri, prim, lo, hi, plane_axis):
    """Return False when one of the separating axes parts triangle ``prim`` and ``[lo, hi]``.

    The 12 axes of the box faces and box axis × triangle edge, and the triangle's normal
    when ``plane_axis`` (a compile-time constant where it is inlined).
    """
    return separating_axes_of_box(tri, prim, lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], plane_axis)


def separating_axes_of_box_py(tri, prim, lo_x, lo_y, lo_z, hi_x, hi_y, hi_z, plane_axis):
    """:func:`separating_axes_py` with the box's corners as six scalars.

    A caller that makes many boxes (a grid's cells) keeps their corners in registers
    instead of writing them to a small array the compiler must assume other arrays
    may alias.
    """
    # Box centre and half extents; the triangle moved so the box is centred at 0.
    cx = 0.5 * (np.float64(lo_x) + hi_x)
    cy = 0.5 * (np.float64(lo_y) + hi_y)
    cz = 0.5 * (np.float64(lo_z) + hi_z)
    hx = 0.5 * (np.float64(hi_x) - lo_x)
    hy = 0.5 * (np.float64(hi_y) - lo_y)
    hz = 0.5 * (np.float64(hi_z) - lo_z)
    v0x = tri[prim, 0, 0] - cx
    v0y = tri[prim, 0, 1] - cy
    v0z = tri[prim, 0, 2] - cz
    v1x = tri[prim, 1, 0] - cx
    v1y = tri[prim, 1, 1] - cy
    v1z = tri[prim, 1, 2] - cz
    v2x = tri[prim, 2, 0] - cx
    v2y = tri[prim, 2, 1] - cy
    v2z = tri[prim, 2, 2] - cz
    # Axes 1-3: the box face normals, i.e. the triangle's bounds against the box.
    x_lo = min(v0x, v1x, v2x)
    x_hi = max(v0x, v1x, v2x)
    y_lo = min(v0y, v1y, v2y)
    y_hi = max(v0y, v1y, v2y)
    z_lo = min(v0z, v1z, v2z)
    z_hi = max(v0z, v1z, v2z)
    if x_lo > hx or x_hi < -hx or y_lo > hy or y_hi < -hy or z_lo > hz or z_hi < -hz:
        return False
    # Axes the triangle's bounds lie within: a test in fewer dimensions decides.
    x_in = x_lo >= -hx and x_hi <= hx
    y_in = y_lo >= -hy and y_hi <= hy
    z_in = z_lo >= -hz and z_hi <= hz
    n_in = np.int64(x_in) + np.int64(y_in) + np.int64(z_in)
    if n_in >= 2:
        return True
    all_axes = n_in == 0
    # Axes 4-12: box axis × triangle edge, for the edges e0 = v1-v0, e1 = v2-v1, e2 = v0-v2.
    for e in range(3):
        if e == 0:
            ex = v1x - v0x
            ey = v1y - v0y
            ez = v1z - v0z
        elif e == 1:
            ex = v2x - v1x
            ey = v2y - v1y
            ez = v2z - v1z
        else:
            ex = v0x - v2x
            ey = v0y - v2y
            ez = v0z - v2z
        # x × e = (0, -ez, ey)
        r = hy * abs(ez) + hz * abs(ey)
        if (all_axes or x_in) and edge_axis_separates(ey, ez, v0y, v0z, v1y, v1z, v2y, v2z, r):
            return False
        # y × e = (ez, 0, -ex)
        r = hx * abs(ez) + hz * abs(ex)
        if (all_axes or y_in) and edge_axis_separates(ez, ex, v0z, v0x, v1z, v1x, v2z, v2x, r):
            return False
        # z × e = (-ey, ex, 0)
        r = hx * abs(ey) + hy * abs(ex)
        if (all_axes or z_in) and edge_axis_separates(ex, ey, v0x, v0y, v1x, v1y, v2x, v2y, r):
            return False
    if not plane_axis or not all_axes:
        return True
    # Axis 13: the triangle's normal; the plane n·x = n·v0 against the box's radius.
    e0x = v1x - v0x
    e0y = v1y - v0y
    e0z = v1z - v0z
    e1x = v2x - v1x
    e1y = v2y - v1y
    e1z = v2z - v1z
    nx = e0y * e1z - e0z * e1y
    ny = e0z * e1x - e0x * e1z
    nz = e0x * e1y - e0y * e1x
    d = nx * v0x + ny * v0y + nz * v0z
    r = hx * abs(nx) + hy * abs(ny) + hz * abs(nz)
    return not abs(d) > r


separating_axes_of_box = cpu_inline(separating_axes_of_box_py)
separating_axes = cpu_inline(separating_axes_py)


def triangle_box_overlap_py(tri, prim, lo, hi):
    """Return whether triangle ``prim`` and the closed box ``[lo, hi]`` share a point.

    Parameters
    ----------
    tri : (F, 3, 3) float32 ndarray
        Triangle corners.
    prim : int
        Row of ``tri`` to test.
    lo, hi : (3,) float32 ndarray
        Box corners, ``lo <= hi`` (equal on an axis for a flat box).

    Returns
    -------
    bool
        True when they overlap or touch (see the module docstring).
    """
    return separating_axes(tri, prim, lo, hi, True)


triangle_box_overlap = cpu_inline(triangle_box_overlap_py)


def touches_py(tri, p, lo, hi):
    """Return whether triangle ``p`` may touch the closed box ``[lo, hi]`` (float64).

    The separating axis test above on the box faces and the nine box-axis × edge axes,
    without the triangle's plane, whose float64 rounding is not bounded for slivers (its
    normal is a rounded cross product): a superset of the exact answer, never a subset
    beyond float64 rounding. Float64 meshes in float32 kd-trees list their triangles by
    it (:mod:`rayaccel.kdtree.precision`).
    """
    return separating_axes(tri, p, lo, hi, False)


touches = cpu_inline(touches_py)
