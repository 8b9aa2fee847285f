"""Watertight ray/triangle intersection (Woop, Benthin, Wald 2013, JCGT 2(1)).

The ray is transformed so that its direction becomes the unit +z axis: the
dominant axis ``kz`` of the direction becomes z, the other two are permuted to
keep the winding, and a shear maps the direction onto z. Each vertex is then
reduced to 2D sheared coordinates, and the three 2D edge functions ``U, V, W``
decide the hit with no epsilon: a point on a shared edge is classified the same
way from both triangles, so no ray slips between them. The paper recomputes an
edge function in float64 when its float32 value is exactly zero; we always
evaluate the three edge functions in float64, where the products of float32
operands are exact. That makes every sign exact and keeps the test watertight
even when the compiler fuses multiply-adds (``fastmath`` ``contract``), which
would otherwise break the antisymmetry of ``Cx*By - Cy*Bx`` in float32 and open
cracks along shared edges. The remaining arithmetic (shear, ``t``) stays float32.

Float64 rows and rays (``precision="float64"``) compile the same code in float64
(:mod:`rayaccel.kernels.real`): the shear and ``t`` are float64 and the edge functions'
products round, as in Embree's and pbrt's double-precision builds. They are emitted
without FMA contraction, so a shared edge's function is still exactly antisymmetric and
the test stays watertight; only a sign within a rounding error of zero can be wrong,
which moves a hit to the neighbouring triangle rather than losing it.

Two functions: :func:`ray_triangle_setup_py` computes the per-ray constants
``(kx, ky, kz, Sx, Sy, Sz)`` once; :func:`ray_triangle_py` tests one triangle
stored as a row ``[Ax, Ay, Az, Bx, By, Bz, Cx, Cy, Cz]`` of a float32 array. The
hit distance is accepted when ``tmin <= t < tmax`` (strict upper bound, so the
first triangle found wins an exact tie). Zero-area and degenerate triangles have
``det == 0`` and are never hit. Both compile for the CPU below and serve as the
oracle's test (tests use the very same function).
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.kernels.real import as_real_like, edge_function

F32_ONE = np.float32(1.0)
F32_ZERO = np.float32(0.0)
F32_INF = np.float32(np.inf)


def ray_triangle_setup_py(dx, dy, dz):
    """Return the per-ray shear constants ``(kx, ky, kz, Sx, Sy, Sz)``.

    Parameters
    ----------
    dx, dy, dz : float32
        Ray direction; must not be all zero (callers skip such rays).

    Returns
    -------
    kx, ky, kz : int
        Axis permutation: ``kz`` is the dominant axis of ``|d|``.
    Sx, Sy, Sz : float32
        Shear ``d[kx]/d[kz]``, ``d[ky]/d[kz]`` and scale ``1/d[kz]``.
    """
    ax = abs(dx)
    ay = abs(dy)
    az = abs(dz)
    # Dominant axis becomes z.
    kz = 0
    dkz = dx
    if ay > ax and ay >= az:
        kz = 1
        dkz = dy
    elif az > ax and az > ay:
        kz = 2
        dkz = dz
    kx = kz + 1
    if kx == 3:
        kx = 0
    ky = kx + 1
    if ky == 3:
        ky = 0
    # Swap kx and ky to preserve the winding when the dominant component is negative.
    if dkz < F32_ZERO:
        kx, ky = ky, kx
    dkx = dx if kx == 0 else (dy if kx == 1 else dz)
    dky = dx if ky == 0 else (dy if ky == 1 else dz)
    Sx = dkx / dkz
    Sy = dky / dkz
    Sz = F32_ONE / dkz
    return kx, ky, kz, Sx, Sy, Sz


def ray_triangle_py(tri, row, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, tmin, tmax):
    """Intersect one triangle; return ``(t, u, v)`` with ``t = inf`` on a miss.

    Parameters
    ----------
    tri : (n, 9) float32 array
        Triangle corners ``A, B, C`` per row.
    row : int
        Row of ``tri`` to test.
    okx, oky, okz : float32
        Ray origin permuted by ``(kx, ky, kz)``.
    kx, ky, kz, Sx, Sy, Sz
        Constants from :func:`ray_triangle_setup_py`.
    tmin, tmax : float32
        Accept hits with ``tmin <= t < tmax``.

    Returns
    -------
    t, u, v : float32
        Distance and barycentrics of the hit (``(1-u-v)·A + u·B + v·C``).
    """
    # Vertices relative to the ray origin, in the permuted frame. Unsigned indices:
    # numba then adds no wraparound of negative ones to the row's address.
    i = np.uint64(row)
    x = np.uint64(kx)
    y = np.uint64(ky)
    z = np.uint64(kz)
    b_at = np.uint64(3)  # B's columns
    c_at = np.uint64(6)  # C's columns
    Akx = tri[i, x] - okx
    Aky = tri[i, y] - oky
    Akz = tri[i, z] - okz
    Bkx = tri[i, b_at + x] - okx
    Bky = tri[i, b_at + y] - oky
    Bkz = tri[i, b_at + z] - okz
    Ckx = tri[i, c_at + x] - okx
    Cky = tri[i, c_at + y] - oky
    Ckz = tri[i, c_at + z] - okz
    # Shear so the ray runs along +z.
    Ax = Akx - Sx * Akz
    Ay = Aky - Sy * Akz
    Bx = Bkx - Sx * Bkz
    By = Bky - Sy * Bkz
    Cx = Ckx - Sx * Ckz
    Cy = Cky - Sy * Ckz
    # Scaled barycentrics: 2D edge functions in float64. Products of two float32 are
    # exact there, so each sign is exact and a shared edge's function is exactly
    # antisymmetric, with or without FMA contraction; float64 rows round both products
    # alike (see the module docstring).
    U64 = edge_function(Cx, By, Cy, Bx)
    V64 = edge_function(Ax, Cy, Ay, Cx)
    W64 = edge_function(Bx, Ay, By, Ax)
    # Edge test without backface culling.
    if (U64 < 0.0 or V64 < 0.0 or W64 < 0.0) and (U64 > 0.0 or V64 > 0.0 or W64 > 0.0):
        return F32_INF, F32_ZERO, F32_ZERO
    if U64 + V64 + W64 == 0.0:
        return F32_INF, F32_ZERO, F32_ZERO
    U = as_real_like(U64, Cx)
    V = as_real_like(V64, Cx)
    W = as_real_like(W64, Cx)
    det = U + V + W
    # Scaled hit distance; divide once.
    T = U * (Sz * Akz) + V * (Sz * Bkz) + W * (Sz * Ckz)
    rcp = F32_ONE / det
    t = T * rcp
    if t >= tmin and t < tmax:
        return t, V * rcp, W * rcp
    return F32_INF, F32_ZERO, F32_ZERO


def triangle_edges64_py(tri, p):
    """Return the edges ``B - A`` and ``C - A`` of triangle ``p`` of ``tri (F, 3, 3)``, in float64.

    As six floats ``(e1x, e1y, e1z, e2x, e2y, e2z)``, exact for float32 corners: the
    form for areas and normals that must not round (slivers, the builders' tests).
    """
    return (
        np.float64(tri[p, 1, 0]) - tri[p, 0, 0],
        np.float64(tri[p, 1, 1]) - tri[p, 0, 1],
        np.float64(tri[p, 1, 2]) - tri[p, 0, 2],
        np.float64(tri[p, 2, 0]) - tri[p, 0, 0],
        np.float64(tri[p, 2, 1]) - tri[p, 0, 1],
        np.float64(tri[p, 2, 2]) - tri[p, 0, 2],
    )


def cross3_py(ax, ay, az, bx, by, bz):
    """Return the cross product ``a × b`` of two vectors given by their components."""
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


ray_triangle_setup = cpu_inline(ray_triangle_setup_py)
ray_triangle = cpu_inline(ray_triangle_py)
triangle_edges64 = cpu_inline(triangle_edges64_py)
cross3 = cpu_inline(cross3_py)
