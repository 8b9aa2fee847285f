"""Point–triangle numerics: the closest point on a triangle and a triangle's solid angle.

:func:`closest_point_triangle_py` is Ericson's Voronoi-region test (*Real-Time
Collision Detection*, 2005, §5.1.5): the query point is classified against the
regions of the three vertices, the three edges and the face with a handful of dot
products, and projected onto the feature whose region holds it. It returns the
barycentrics of the closest point in the convention of the ray hits
(``(1-u-v)·A + u·B + v·C``) and its squared distance. Degenerate (zero-area)
triangles fall into a vertex or an edge region, so they need no special case.

:func:`triangle_solid_angle_py` is the signed solid angle a triangle subtends at a
point (Van Oosterom & Strackee 1983), ``2·atan2(a·(b×c), |a||b||c| + (a·b)|c| +
(a·c)|b| + (b·c)|a|)`` with ``a, b, c`` the corners relative to the point. Summed over
a mesh and divided by 4π it is the generalised winding number of Jacobson, Kavan
and Sorkine-Hornung 2013: 1 inside a closed, outward-oriented mesh, 0 outside, and a
smooth value in between for open meshes.

Both work in float64 on float32 corners (a row ``[Ax, Ay, Az, Bx, By, Bz, Cx, Cy,
Cz]`` of the ``(n, 9)`` leaf-order triangle array every family stores), so the
distance of a query point near a large-coordinate mesh keeps its digits.

References
----------
C. Ericson, *Real-Time Collision Detection*, Morgan Kaufmann 2005, §5.1.5.
A. Van Oosterom, J. Strackee, "The Solid Angle of a Plane Triangle", IEEE Trans.
Biomed. Eng. 30(2), 1983.
A. Jacobson, L. Kavan, O. Sorkine-Hornung, "Robust Inside-Outside Segmentation using
Generalized Winding Numbers", ACM TOG 32(4), 2013.
"""

from __future__ import annotations

import math

from rayaccel._jit import cpu_inline


def corner_py(tri, row, k):
    """Return corner ``k`` (0: A, 1: B, 2: C) of triangle ``row`` of ``tri (n, 9)``, as floats."""
    return float(tri[row, 3 * k]), float(tri[row, 3 * k + 1]), float(tri[row, 3 * k + 2])


def corner_minus_py(tri, row, k, ox, oy, oz):
    """Return corner ``k`` of triangle ``row`` minus the point ``o``, in float64."""
    return (
        float(tri[row, 3 * k]) - ox,
        float(tri[row, 3 * k + 1]) - oy,
        float(tri[row, 3 * k + 2]) - oz,
    )


def edge_dots_py(abx, aby, abz, acx, acy, acz, qx, qy, qz):
    """Return ``(AB·q, AC·q)``: a vector's dot products with a triangle's two edges from A."""
    return abx * qx + aby * qy + abz * qz, acx * qx + acy * qy + acz * qz


corner = cpu_inline(corner_py)
corner_minus = cpu_inline(corner_minus_py)
edge_dots = cpu_inline(edge_dots_py)


def closest_point_triangle_py(tri, row, px, py, pz):
    """Return ``(d2, u, v)``: squared distance and barycentrics of the closest point.

    Parameters
    ----------
    tri : (n, 9) float32 array
        Triangle corners ``A, B, C`` per row.
    row : int
        Row of ``tri``.
    px, py, pz : float64
        Query point.

    Returns
    -------
    d2 : float64
        Squared distance from the point to the triangle.
    u, v : float64
        Barycentrics of the closest point: ``(1-u-v)·A + u·B + v·C``.
    """
    ax, ay, az = corner(tri, row, 0)
    abx, aby, abz = corner_minus(tri, row, 1, ax, ay, az)
    acx, acy, acz = corner_minus(tri, row, 2, ax, ay, az)
    apx = px - ax
    apy = py - ay
    apz = pz - az
    u = 0.0
    v = 0.0
    # Vertex region of A.
    d1, d2 = edge_dots(abx, aby, abz, acx, acy, acz, apx, apy, apz)
    if d1 <= 0.0 and d2 <= 0.0:
        u = 0.0
        v = 0.0
    else:
        # Vertex region of B: the dot products with BP = AP - AB.
        d3, d4 = edge_dots(abx, aby, abz, acx, acy, acz, apx - abx, apy - aby, apz - abz)
        vc = d1 * d4 - d3 * d2
        if d3 >= 0.0 and d4 <= d3:
            u = 1.0
            v = 0.0
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            # Edge region of AB.
            u = d1 / (d1 - d3)
            v = 0.0
        else:
            # Vertex region of C: the dot products with CP = AP - AC.
            d5, d6 = edge_dots(abx, aby, abz, acx, acy, acz, apx - acx, apy - acy, apz - acz)
            vb = d5 * d2 - d1 * d6
            va = d3 * d6 - d5 * d4
            if d6 >= 0.0 and d5 <= d6:
                u = 0.0
                v = 1.0
            elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                # Edge region of AC.
                u = 0.0
                v = d2 / (d2 - d6)
            elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
                # Edge region of BC.
                w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                u = 1.0 - w
                v = w
            else:
                # Face region: project onto the plane.
                denom = 1.0 / (va + vb + vc)
                u = vb * denom
                v = vc * denom
    # Squared distance to the closest point A + u·AB + v·AC.
    qx = apx - u * abx - v * acx
    qy = apy - u * aby - v * acy
    qz = apz - u * abz - v * acz
    return qx * qx + qy * qy + qz * qz, u, v


def triangle_solid_angle_py(tri, row, px, py, pz):
    """Return the signed solid angle (steradians) triangle ``row`` subtends at the point.

    Positive when the point sees the triangle's back (counter-clockwise corners
    around an outward normal seen from inside), so a closed outward-oriented mesh
    sums to ``4π`` at an inside point and ``0`` outside. Zero at a point on the
    triangle's plane (and for degenerate triangles).
    """
    ax, ay, az = corner_minus(tri, row, 0, px, py, pz)
    bx, by, bz = corner_minus(tri, row, 1, px, py, pz)
    cx, cy, cz = corner_minus(tri, row, 2, px, py, pz)
    la = math.sqrt(ax * ax + ay * ay + az * az)
    lb = math.sqrt(bx * bx + by * by + bz * bz)
    lc = math.sqrt(cx * cx + cy * cy + cz * cz)
    det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
    ab = ax * bx + ay * by + az * bz
    ac = ax * cx + ay * cy + az * cz
    bc = bx * cx + by * cy + bz * cz
    denom = la * lb * lc + ab * lc + ac * lb + bc * la
    return 2.0 * math.atan2(det, denom)


closest_point_triangle = cpu_inline(closest_point_triangle_py)
triangle_solid_angle = cpu_inline(triangle_solid_angle_py)
