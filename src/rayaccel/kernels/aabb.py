"""Robust ray/box slab test (Williams et al. 2005; Ize 2013, "Robust BVH Ray Traversal").

The ray is given by its origin and its *correctly rounded* reciprocal direction
``inv = 1/d`` (IEEE: ``1/+0 = +inf``, ``1/-0 = -inf``). For each axis the caller
passes the box plane the ray meets first (``near``: the low plane when
``inv >= 0``, else the high plane) and the one it leaves through (``far``), so no
per-axis swap is needed (Williams' sign trick).

Robustness (Ize 2013): slab distances are computed as ``(plane - o) * inv`` and
only the exit distance is enlarged by two float32 ulps (``|t|·2^-22``), which
closes every false miss caused by rounding; a false hit merely visits one more
node. A ray lying exactly in a slab plane with a zero direction component gives
``0 * inf = NaN``; the comparisons below treat NaN as "no constraint", so such a
ray is kept (conservative).

Boxes versus the triangle test: the watertight test computes a hit's ``t`` along
another path than the slab distances, and its rounding error grows with the
distance of the triangle's corners from the ray origin (a huge ground triangle hit
at a grazing angle is off by hundreds of ulps of ``t``). A traversal that culls
boxes against the exact ray interval then loses hits at exactly ``tmin`` or
``tmax``. Traversals therefore cull against the interval widened by
:func:`culling_pad_py`, an absolute slack proportional to the extent of the scene
along the ray's dominant axis, computed once per ray. The exact interval is still
enforced by the triangle test, so results are unchanged; only nodes within the
slack beyond the closest hit are visited more.

``ray_box_entry_py`` returns the entry distance, or ``inf`` when the box is
missed within ``[tmin, tmax]``. It is written in plain Python so the same source
compiles for the CPU (``ray_box_entry``) and, later, for CUDA.
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import cpu_inline

#: Exit distances grow by this relative amount (2 ulp in float32, 1 + 2^-22), Ize 2013 §3.
TWO_ULP = np.float32(2.0**-22)
INF = np.float32(np.inf)
#: Culling slack in units of the scene's extent along the ray (16 float32 ulps). The
#: triangle test's error is a few ulps of its corners' distance from the origin.
INTERVAL_SLACK = np.float32(2.0**-20)


def culling_pad_py(o_kz, Sz, lo_kz, hi_kz):
    """Return the absolute slack added to both ends of the culling interval.

    Parameters
    ----------
    o_kz : float32
        Ray origin on the dominant axis of the direction (``kz`` of the triangle setup).
    Sz : float32
        ``1 / d[kz]`` from the triangle setup.
    lo_kz, hi_kz : float32
        The root box on that axis.
    """
    return max(abs(lo_kz - o_kz), abs(hi_kz - o_kz)) * abs(Sz) * INTERVAL_SLACK


def ray_box_entry_py(
    ox, oy, oz, ix, iy, iz, near_x, near_y, near_z, far_x, far_y, far_z, tmin, tmax
):
    """Return the distance at which the ray enters the box, or ``inf`` if it misses.

    Parameters
    ----------
    ox, oy, oz : float32
        Ray origin.
    ix, iy, iz : float32
        Reciprocal ray direction (``±inf`` for zero components).
    near_x, near_y, near_z, far_x, far_y, far_z : float32
        Box planes selected by the sign of each ``inv`` component.
    tmin, tmax : float32
        The ray interval (``tmax`` is the current closest hit).

    Returns
    -------
    float32
        ``max(tmin, entry)`` when ``entry <= exit`` within the interval, else ``inf``.
    """
    # Entry distance per slab.
    t0x = (near_x - ox) * ix
    t0y = (near_y - oy) * iy
    t0z = (near_z - oz) * iz
    # Intersect the slabs; a NaN comparison is false, so NaN never tightens the interval.
    entry = tmin
    if t0x > entry:
        entry = t0x
    if t0y > entry:
        entry = t0y
    if t0z > entry:
        entry = t0z
    # Exit: the nearest far plane (NaN ignored), enlarged by 2 ulp as Ize prescribes.
    leave = ray_box_exit(ox, oy, oz, ix, iy, iz, far_x, far_y, far_z)
    if tmax < leave:
        leave = tmax
    if entry <= leave:
        return entry
    return INF


def ray_box_exit_py(ox, oy, oz, ix, iy, iz, far_x, far_y, far_z):
    """Return the distance at which the ray leaves the box.

    That is the nearest far plane (NaN ignored), enlarged by 2 ulp exactly as in
    :func:`ray_box_entry_py`, whose arguments of the same names these are; ``inf``
    when every component of the direction is zero.
    """
    t1x = (far_x - ox) * ix
    t1y = (far_y - oy) * iy
    t1z = (far_z - oz) * iz
    leave = INF
    if t1x < leave:
        leave = t1x
    if t1y < leave:
        leave = t1y
    if t1z < leave:
        leave = t1z
    return leave + abs(leave) * TWO_ULP


ray_box_entry = cpu_inline(ray_box_entry_py)
ray_box_exit = cpu_inline(ray_box_exit_py)
culling_pad = cpu_inline(culling_pad_py)
