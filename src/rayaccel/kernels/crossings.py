"""One hit per surface crossing: merging the repeats of a crossing at a shared edge or vertex.

The watertight ray/triangle test (:mod:`rayaccel.kernels.triangle`, Woop, Benthin,
Wald 2013) never lets a ray slip between triangles: a ray through a shared edge or a
vertex hits every triangle around that point. For a list of all hits that is one
crossing of the surface reported several times (trimesh #2504/#2524). Two hits of one
ray on triangles that share an edge are the same crossing exactly when the triangles'
third corners lie strictly on opposite sides of the plane through the edge and the
ray: projected along the ray the two triangles then meet only on the edge, so the ray
hits both only where it passes through it. A vertex joins its fan edge by edge
(union-find). When the third corners lie on one side, the ray touches a ridge or a
valley: it enters and leaves the solid there, and both hits stay, which keeps the
parity of the count right. The test is exact float64 geometry on the mesh's own
vertices (corners are shared when their indices or their coordinates are equal) and
does not depend on the winding of the faces; a tolerance only picks the pairs worth
testing (hits of one ray at nearly the same distance). A face listed twice (the same
three corners) is one surface too: its two hits are one crossing.

:func:`frame_kernel` moves rays into a structure's frame (origins relative to a centre,
unit directions, in the structure's precision); :func:`crossings_kernel` marks the hits to keep and
counts them; :func:`hit_points_kernel` writes the kept hits with their points, where
each ray meets its triangle's plane, in float64. :mod:`rayaccel.trimesh` runs them.
They are serial: each is one light pass over the rays (well under a tenth of the
all-hits walk they follow), and a parallel launch can cost more than that on a busy
machine.
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.kernels.triangle import cross3

#: Hits of one ray within this fraction of the scene's size (plus the origin's offset
#: from the centre and the distance) are compared as possible repeats of one crossing.
CROSSING_SPAN = 1e-4
#: A hit closer than this fraction of the scene's size lies on the ray's origin.
ON_SURFACE = 1e-6
#: ``flags`` bits of :func:`crossings_kernel`.
FLAG_VERTEX = 1
FLAG_ON_SURFACE = 2


def same_corner_py(vertices, a, b):
    """Whether vertex indices ``a`` and ``b`` are one corner (same index or same point)."""
    return a == b or (
        vertices[a, 0] == vertices[b, 0]
        and vertices[a, 1] == vertices[b, 1]
        and vertices[a, 2] == vertices[b, 2]
    )


same_corner = cpu_inline(same_corner_py)


def side_py(vertices, nx, ny, nz, origin, point):
    """``n · (point - origin)`` for vertices ``point`` and ``origin`` (a signed side)."""
    return (
        nx * (vertices[point, 0] - vertices[origin, 0])
        + ny * (vertices[point, 1] - vertices[origin, 1])
        + nz * (vertices[point, 2] - vertices[origin, 2])
    )


side = cpu_inline(side_py)


def one_crossing_py(vertices, faces, p, q, dx, dy, dz):
    """Whether hits of one ray on triangles ``p`` and ``q`` are one crossing of the surface.

    Yes when ``p`` and ``q`` have the same three corners (a duplicated face), or share
    exactly two corners (same index or same coordinates) with their third corners
    strictly on opposite sides of the plane through the shared edge and the direction
    ``d``: their projections along the ray then meet only on the edge, so the ray hits
    both only where it passes through the edge.
    """
    # Bit i of used_p (j of used_q): corner i of p (j of q) is shared.
    used_p = 0
    used_q = 0
    for i in range(3):
        for j in range(3):
            if (used_q >> j) & 1 == 0 and same_corner(vertices, faces[p, i], faces[q, j]):
                used_p |= 1 << i
                used_q |= 1 << j
                break
    if used_p == 7:
        return True
    if used_p != 3 and used_p != 5 and used_p != 6:
        return False
    # The shared edge e0-e1 and the corner of each triangle off it.
    e0 = faces[p, 0] if used_p & 1 else faces[p, 1]
    e1 = faces[p, 2] if used_p & 4 else faces[p, 1]
    off_p = faces[p, 0] if used_p == 6 else (faces[p, 1] if used_p == 5 else faces[p, 2])
    off_q = faces[q, 0] if used_q == 6 else (faces[q, 1] if used_q == 5 else faces[q, 2])
    ex = vertices[e1, 0] - vertices[e0, 0]
    ey = vertices[e1, 1] - vertices[e0, 1]
    ez = vertices[e1, 2] - vertices[e0, 2]
    # Normal of the plane through the edge and the ray direction.
    nx, ny, nz = cross3(ex, ey, ez, dx, dy, dz)
    side_p = side(vertices, nx, ny, nz, e0, off_p)
    side_q = side(vertices, nx, ny, nz, e0, off_q)
    return (side_p > 0.0 and side_q < 0.0) or (side_p < 0.0 and side_q > 0.0)


one_crossing = cpu_inline(one_crossing_py)


@cpu_kernel()
def crossings_kernel(
    splits, t, prim, direction, offset, vertices, faces, scale, max_hits, keep, kept, flags
):
    """Keep one hit per surface crossing of every ray (see the module docstring).

    Hits whose ``t`` lie within a small span of each other form a window (most hits
    are alone in theirs); a union-find over the window joins the hits
    :func:`one_crossing_py` calls one crossing, and each group keeps its first hit
    (lowest ``t``, then triangle).

    Parameters
    ----------
    splits : (n + 1,) int64
        Ray ``r``'s hits are ``splits[r]:splits[r + 1]``, sorted by ``t``, triangle.
    t, prim : (h,) float32 or float64, int32
        The hits (``t`` along the unit direction).
    direction : (n, 3) float64
        Unit ray directions.
    offset : (n,) float64
        Distance of each ray's origin from the centre of the structure's frame.
    vertices, faces : (V, 3) float64, (F, 3) int64
        The mesh.
    scale : float
        Size of the mesh (its bounding box diagonal).
    max_hits : int
        Keep at most this many crossings per ray (the nearest).
    keep : (h,) bool
        Out: whether each hit is kept.
    kept : (n,) int64
        Out: crossings kept per ray.
    flags : (n,) uint8
        Out: ``FLAG_VERTEX`` when three or more hits were one crossing (a vertex),
        ``FLAG_ON_SURFACE`` when a hit lies on the ray's origin.
    """
    n_rays = splits.shape[0] - 1
    for r in range(n_rays):
        begin = splits[r]
        end = splits[r + 1]
        flag = 0
        for i in range(begin, end):
            keep[i] = True
        window_end = begin
        for i in range(begin, end):
            if t[i] <= ON_SURFACE * scale:
                flag |= FLAG_ON_SURFACE
            if i < window_end:
                continue
            # The window: the hits within the span of this one.
            span = CROSSING_SPAN * (scale + offset[r] + abs(t[i]))
            window_end = i + 1
            while window_end < end and t[window_end] - t[i] <= span:
                window_end += 1
            m = window_end - i
            if m == 1:
                continue
            # Union-find over the window's pairs that are one crossing.
            parent = np.arange(m)
            for a in range(m):
                for b in range(a + 1, m):
                    if one_crossing(
                        vertices, faces, prim[i + a], prim[i + b],
                        direction[r, 0], direction[r, 1], direction[r, 2],
                    ):  # fmt: skip
                        root_a = a
                        while parent[root_a] != root_a:
                            root_a = parent[root_a]
                        root_b = b
                        while parent[root_b] != root_b:
                            root_b = parent[root_b]
                        # The earlier hit becomes the root, so each group keeps its first.
                        if root_a < root_b:
                            parent[root_b] = root_a
                        elif root_b < root_a:
                            parent[root_a] = root_b
            size = np.zeros(m, dtype=np.int64)
            for a in range(m):
                root = a
                while parent[root] != root:
                    root = parent[root]
                size[root] += 1
                if root != a:
                    keep[i + a] = False
            if size.max() >= 3:
                flag |= FLAG_VERTEX
        # The nearest max_hits crossings.
        count = 0
        for i in range(begin, end):
            if keep[i]:
                if count >= max_hits:
                    keep[i] = False
                else:
                    count += 1
        kept[r] = count
        flags[r] = flag


@cpu_kernel()
def hit_points_kernel(
    splits, keep, out_splits, prim, t, origin, direction, vertices, faces, first_ray,
    index_tri, index_ray, locations, with_locations,
):  # fmt: skip
    """Write the kept hits of each ray: triangle, ray and location (float64).

    The location is where the ray meets the triangle's plane, ``o + s·d`` with
    ``s = n·(A - o) / n·d`` in float64, or ``o + t·d`` for a ray (numerically) in
    the plane.
    """
    n_rays = splits.shape[0] - 1
    for r in range(n_rays):
        target = out_splits[r]
        ox = origin[r, 0]
        oy = origin[r, 1]
        oz = origin[r, 2]
        dx = direction[r, 0]
        dy = direction[r, 1]
        dz = direction[r, 2]
        for i in range(splits[r], splits[r + 1]):
            if not keep[i]:
                continue
            p = prim[i]
            index_tri[target] = p
            index_ray[target] = first_ray + r
            if with_locations:
                a = faces[p, 0]
                b = faces[p, 1]
                c = faces[p, 2]
                abx = vertices[b, 0] - vertices[a, 0]
                aby = vertices[b, 1] - vertices[a, 1]
                abz = vertices[b, 2] - vertices[a, 2]
                acx = vertices[c, 0] - vertices[a, 0]
                acy = vertices[c, 1] - vertices[a, 1]
                acz = vertices[c, 2] - vertices[a, 2]
                nx, ny, nz = cross3(abx, aby, abz, acx, acy, acz)
                denom = nx * dx + ny * dy + nz * dz
                s = np.float64(t[i])
                if denom != 0.0:
                    plane = (
                        nx * (vertices[a, 0] - ox)
                        + ny * (vertices[a, 1] - oy)
                        + nz * (vertices[a, 2] - oz)
                    ) / denom
                    if np.isfinite(plane):
                        s = plane
                locations[target, 0] = ox + s * dx
                locations[target, 1] = oy + s * dy
                locations[target, 2] = oz + s * dz
            target += 1


@cpu_kernel()
def frame_kernel(origin, direction, centre, local, unit, unit64, offset):
    """Move rays into a structure's frame: origins relative to a centre, unit directions.

    Parameters
    ----------
    origin, direction : (n, 3) float64
        Rays in the mesh's frame (finite; directions of any length).
    centre : (3,) float64
        Origin of the structure's frame.
    local : (n, 3) float32 or float64
        Out: ``origin - centre``, rounded to the structure's precision.
    unit, unit64 : (n, 3) float32 or float64, float64
        Out: unit directions in the structure's precision and in float64; a zero
        direction stays zero (a miss). Components are scaled by the largest first, so
        none underflows or overflows.
    offset : (n,) float64
        Out: ``|origin - centre|``.
    """
    for r in range(origin.shape[0]):
        dx = direction[r, 0]
        dy = direction[r, 1]
        dz = direction[r, 2]
        largest = max(abs(dx), abs(dy), abs(dz))
        if largest > 0.0:
            dx /= largest
            dy /= largest
            dz /= largest
            length = np.sqrt(dx * dx + dy * dy + dz * dz)
            dx /= length
            dy /= length
            dz /= length
        unit64[r, 0] = dx
        unit64[r, 1] = dy
        unit64[r, 2] = dz
        unit[r, 0] = dx
        unit[r, 1] = dy
        unit[r, 2] = dz
        lx = origin[r, 0] - centre[0]
        ly = origin[r, 1] - centre[1]
        lz = origin[r, 2] - centre[2]
        local[r, 0] = lx
        local[r, 1] = ly
        local[r, 2] = lz
        offset[r] = np.sqrt(lx * lx + ly * ly + lz * lz)
