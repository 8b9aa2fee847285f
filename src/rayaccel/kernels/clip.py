"""Triangle clipping: the exact bounds of the parts of a triangle inside a plane or a box.

A triangle's bounding box overestimates the space it covers when the triangle is
large or diagonal. Builders that cut space rather than primitives therefore clip:

- :func:`split_triangle_bounds_py` — cut a triangle by an axis-aligned plane and
  return the boxes of the two parts. Each part's box is the box of the triangle's
  vertices on that side plus the points where its edges cross the plane (a vertex
  on the plane belongs to both sides). This is the "split clipping" of spatial-split
  BVHs (Stich, Friedrich, Dietrich 2009, "Spatial Splits in Bounding Volume
  Hierarchies", HPG, §4.4: a reference is split by intersecting the triangle with
  the plane, not its box) and of triangle pre-splitting (Karras & Aila 2013, §5.9).
  Crossing points are computed in float64 and rounded outward to float32 by
  ``|v|·2.4e-7`` (two float32 ulps), so each box contains its part; the boxes are
  clamped to the box of the part being split (a reference may already be a part).
- :func:`clip_triangle_box_py` — Sutherland–Hodgman clipping of the triangle
  against the six planes of a closed box (Sutherland & Hodgman 1974, "Reentrant
  Polygon Clipping", CACM 17(1)), giving the polygon of the triangle inside the box.
  Its bounds (:func:`polygon_bounds_py`) are the "perfect split" bounds of kd-tree
  construction (Havran 2000, PhD thesis §4.5; Wald & Havran 2006, "On building fast
  kd-trees for ray tracing, and on doing that in O(N log N)", §4.4), and its area is
  the end-point overlap metric's clipped area (:mod:`rayaccel.bvh.metrics`).

Closed half-spaces throughout: a point exactly on a plane is inside, so a triangle
that only touches a box clips to a degenerate polygon (a point or a segment, its
vertices repeated), not to nothing. :func:`clip_triangle_box_py` uses nothing but
``+ - * /`` and comparisons on the values it is given, so called with arrays of
:class:`fractions.Fraction` it clips exactly (the tests use it so, as the oracle of
:mod:`rayaccel.kernels.overlap`).

The ``*_py`` functions are plain Python (oracles, and the source of CUDA versions);
the unsuffixed names are their inlined CPU forms.
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import cpu_inline

#: Outward rounding of a float64 crossing point to float32: ``|v|`` times this (2 ulps).
ROUND_OUT = 2.4e-7


def split_triangle_bounds_py(tri, prim, ref_box, axis, pos, left_box, right_box):
    """Write the boxes of a triangle's parts below and above ``x[axis] = pos``, within a box.

    Parameters
    ----------
    tri : (F, 3, 3) float32 ndarray
        Triangle corners.
    prim : int
        Triangle to split.
    ref_box : (6,) float32 ndarray
        ``[lo, hi]`` of the part of the triangle being split (its own bounds for a
        whole triangle; a clipped part's box for a part, as spatial-split references
        and pre-split pieces are): both results are intersected with it.
    axis : int
        0, 1 or 2.
    pos : float64
        Plane position (a float32 value).
    left_box, right_box : (6,) float32 ndarray
        Output ``[lo.x, lo.y, lo.z, hi.x, hi.y, hi.z]`` of the part with
        ``x[axis] <= pos`` and of the part with ``x[axis] >= pos``. A side the
        triangle does not reach within ``ref_box`` collapses to a flat box on the
        axes where the intersection is empty.

    Notes
    -----
    Vertices on a side grow that side's box; an edge strictly crossing the plane adds
    its crossing point, in float64 and rounded outward by :data:`ROUND_OUT`, to both.
    The plane then caps each side (``left hi[axis] <= pos <= right lo[axis]``), and
    both boxes are clamped to ``ref_box``. One function, not a clip and a clamp: this
    runs once per bin plane and reference in SBVH's chopped binning, and every inlined
    call level costs reference-count updates of its array arguments.
    """
    for k in range(3):
        left_box[k] = np.inf
        left_box[3 + k] = -np.inf
        right_box[k] = np.inf
        right_box[3 + k] = -np.inf
    for e in range(3):
        f = (e + 1) % 3
        p0 = np.float64(tri[prim, e, axis])
        p1 = np.float64(tri[prim, f, axis])
        # The vertex itself goes to its side(s).
        if p0 <= pos:
            for k in range(3):
                left_box[k] = min(left_box[k], tri[prim, e, k])
                left_box[3 + k] = max(left_box[3 + k], tri[prim, e, k])
        if p0 >= pos:
            for k in range(3):
                right_box[k] = min(right_box[k], tri[prim, e, k])
                right_box[3 + k] = max(right_box[3 + k], tri[prim, e, k])
        # An edge crossing the plane adds its crossing point to both sides, rounded outward.
        if (p0 < pos < p1) or (p1 < pos < p0):
            t = (pos - p0) / (p1 - p0)
            for k in range(3):
                v = tri[prim, e, k] + t * (np.float64(tri[prim, f, k]) - tri[prim, e, k])
                pad = abs(v) * ROUND_OUT
                left_box[k] = min(left_box[k], np.float32(v - pad))
                left_box[3 + k] = max(left_box[3 + k], np.float32(v + pad))
                right_box[k] = min(right_box[k], np.float32(v - pad))
                right_box[3 + k] = max(right_box[3 + k], np.float32(v + pad))
    # The plane bounds each side exactly; both stay inside the part's box.
    left_box[3 + axis] = min(left_box[3 + axis], np.float32(pos))
    right_box[axis] = max(right_box[axis], np.float32(pos))
    for k in range(3):
        left_box[k] = max(left_box[k], ref_box[k])
        left_box[3 + k] = min(left_box[3 + k], ref_box[3 + k])
        right_box[k] = max(right_box[k], ref_box[k])
        right_box[3 + k] = min(right_box[3 + k], ref_box[3 + k])
        if left_box[k] > left_box[3 + k]:
            left_box[3 + k] = left_box[k]
        if right_box[k] > right_box[3 + k]:
            right_box[3 + k] = right_box[k]


def clip_triangle_box_py(tri, prim, lo, hi, poly, scratch, min_vertices):
    """Clip triangle ``prim`` to the closed box ``[lo, hi]``; return the polygon's vertex count.

    Parameters
    ----------
    tri : (F, 3, 3) ndarray
        Triangle corners (float32; any number type for an exact clip).
    prim : int
        Row of ``tri`` to clip.
    lo, hi : (3,) ndarray
        Box corners.
    poly, scratch : (k, 3) ndarray
        Work buffers (float64 on the CPU), ``k >= 9``: each plane adds at most one
        vertex to a convex polygon; rounding may add more, which are dropped past
        ``k`` (metrics use 32). The clipped polygon is returned in ``poly``.
    min_vertices : int
        Stop as soon as fewer vertices remain (3: only polygons with an area
        matter; 1: any contact matters).

    Returns
    -------
    int
        ``m``: the polygon is ``poly[:m]``, in order. ``m < min_vertices`` means the
        clip stopped early and ``poly`` holds nothing useful.

    Notes
    -----
    Planes are taken in the order x >= lo.x, x <= hi.x, y >= lo.y, ... Sutherland–Hodgman
    keeps a vertex with signed distance ``d >= 0`` and adds the crossing point
    ``p_i + d_i/(d_i − d_j)·(p_j − p_i)`` for an edge whose ends are on different sides.
    A plane with every vertex inside would return the polygon unchanged, so it is
    skipped (a triangle straddling one kd split plane is cut by one or two planes).
    """
    for v in range(3):
        for k in range(3):
            poly[v, k] = tri[prim, v, k]
    m = 3
    src = poly
    dst = scratch
    swapped = False
    for plane in range(6):
        axis = plane // 2
        keep_above = plane % 2 == 0
        value = lo[axis] if keep_above else hi[axis]
        cut = False
        for i in range(m):
            if (src[i, axis] < value) if keep_above else (src[i, axis] > value):
                cut = True
                break
        if not cut:
            continue
        # One Sutherland–Hodgman pass: src[:m] -> dst[:n_dst].
        n_dst = 0
        for i in range(m):
            j = i + 1 if i + 1 < m else 0
            di = src[i, axis] - value
            dj = src[j, axis] - value
            if not keep_above:
                di = -di
                dj = -dj
            if di >= 0 and n_dst < dst.shape[0]:
                for k in range(3):
                    dst[n_dst, k] = src[i, k]
                n_dst += 1
            if (di >= 0) != (dj >= 0) and n_dst < dst.shape[0]:
                t = di / (di - dj)
                for k in range(3):
                    dst[n_dst, k] = src[i, k] + t * (src[j, k] - src[i, k])
                n_dst += 1
        m = n_dst
        if m < min_vertices:
            return m
        src, dst = dst, src
        swapped = not swapped
    if swapped:
        for i in range(m):
            for k in range(3):
                poly[i, k] = src[i, k]
    return m


def polygon_bounds_py(poly, m, lo, hi, out, abs_pad):
    """Write the box of polygon ``poly[:m]`` into ``out[0:6]``, rounded outward, within a box.

    Each coordinate ``v`` is padded by ``|v|·ROUND_OUT + abs_pad``. The relative term
    covers the rounding to float32; ``abs_pad`` covers the float64 error of the
    crossing points, which is relative to the *operands* (the triangle's and the box's
    coordinates), not to the result: a crossing that should be 0 can come out as 5e-26,
    and a pad relative to that alone would leave the true point outside the box.
    Callers pass about ``2^-40`` times the scene's largest coordinate.

    Parameters
    ----------
    poly : (k, 3) float64 ndarray
        A polygon from :func:`clip_triangle_box_py` (``m >= 1``).
    m : int
        Its vertex count (the value :func:`clip_triangle_box_py` returned).
    lo, hi : (3,) float32 ndarray
        The box it was clipped to: the bounds are intersected with it, since the
        outward rounding may step just outside.
    out : (6,) float32 ndarray
        ``[lo.x, lo.y, lo.z, hi.x, hi.y, hi.z]``.
    abs_pad : float
        The absolute part of the padding (see above).
    """
    for k in range(3):
        out[k] = np.inf
        out[3 + k] = -np.inf
    for i in range(m):
        for k in range(3):
            v = poly[i, k]
            pad = abs(v) * ROUND_OUT + abs_pad
            out[k] = min(out[k], np.float32(v - pad))
            out[3 + k] = max(out[3 + k], np.float32(v + pad))
    for k in range(3):
        out[k] = max(out[k], lo[k])
        out[3 + k] = min(out[3 + k], hi[k])


def polygon_area_py(poly, m):
    """Return the area of the planar polygon ``poly[:m]`` (0 for ``m < 3``).

    Half the norm of the summed cross products of a fan from vertex 0.
    """
    cx = 0.0
    cy = 0.0
    cz = 0.0
    for i in range(1, m - 1):
        ux = poly[i, 0] - poly[0, 0]
        uy = poly[i, 1] - poly[0, 1]
        uz = poly[i, 2] - poly[0, 2]
        vx = poly[i + 1, 0] - poly[0, 0]
        vy = poly[i + 1, 1] - poly[0, 1]
        vz = poly[i + 1, 2] - poly[0, 2]
        cx += uy * vz - uz * vy
        cy += uz * vx - ux * vz
        cz += ux * vy - uy * vx
    return 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)


split_triangle_bounds = cpu_inline(split_triangle_bounds_py)
clip_triangle_box = cpu_inline(clip_triangle_box_py)
polygon_bounds = cpu_inline(polygon_bounds_py)
polygon_area = cpu_inline(polygon_area_py)
