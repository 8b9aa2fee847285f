"""The per-ray constants every traversal computes once, before its first step.

Reciprocal direction and the near/far plane offsets into interleaved boxes (Williams
et al. 2005), the watertight triangle test's shear constants (Woop, Benthin, Wald
2013), the culling pad that keeps the slab tests conservative for the watertight
test (:func:`rayaccel.kernels.aabb.culling_pad`), the hit interval, and the entry
distance of the scene box. Every family computes them with these functions, so their
hits are the oracle's bit for bit.

Boxes are interleaved ``(lo_x, hi_x, lo_y, hi_y, lo_z, hi_z)``; the near plane of
axis ``a`` is column ``2a`` when the direction is non-negative on ``a`` and
``2a + 1`` otherwise. The offsets ``nx, ny, nz`` and ``fx, fy, fz`` encode that choice
so a kernel reads ``box[row, col + nx]`` without a branch.

Precision: the functions are generic. Float64 rays (``precision="float64"``) compile
float64 specialisations: every per-ray constant, the hit interval and the slab
distances against the float32 boxes are then float64, and ``t_hit`` starts one float64
ulp above ``tmax`` (:func:`rayaccel.kernels.real.next_up`). The culling pad keeps its
float32-sized slack (``2^-20`` of the scene's extent), far above float64 rounding, so it
stays conservative.
"""

from __future__ import annotations

import math

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.kernels.aabb import culling_pad, ray_box_entry
from rayaccel.kernels.real import next_up
from rayaccel.kernels.triangle import ray_triangle_setup

ONE32 = np.float32(1.0)
ZERO32 = np.float32(0.0)
INF32 = np.float32(np.inf)


def ray_prologue_py(origin, direction, tmin, tmax, r, root_box):
    """Return the per-ray constants of ray ``r`` (see the module docstring).

    Returns
    -------
    tuple
        ``(valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, kx, ky, kz, Sx, Sy,
        Sz, okx, oky, okz, t_lo, t_hit, pad)``. ``valid`` is False for degenerate rays
        (zero or non-finite direction or origin, empty interval), which miss; the other
        values are then meaningless. ``t_hit`` starts one ulp above ``tmax`` because
        the triangle test's upper bound is strict (tmax is inclusive).
    """
    ox = origin[r, 0]
    oy = origin[r, 1]
    oz = origin[r, 2]
    dx = direction[r, 0]
    dy = direction[r, 1]
    dz = direction[r, 2]
    t_lo = tmin[r]
    t_hit = next_up(tmax[r])
    valid = (
        t_lo <= tmax[r]
        and not (dx == 0 and dy == 0 and dz == 0)
        and math.isfinite(dx)
        and math.isfinite(dy)
        and math.isfinite(dz)
        and math.isfinite(ox)
        and math.isfinite(oy)
        and math.isfinite(oz)
    )
    # Reciprocal direction and the near/far plane offsets of the interleaved boxes.
    ix = ONE32 / dx
    iy = ONE32 / dy
    iz = ONE32 / dz
    nx = 0 if ix >= 0 else 1
    ny = 2 if iy >= 0 else 3
    nz = 4 if iz >= 0 else 5
    fx = 1 - nx
    fy = 5 - ny
    fz = 9 - nz
    # Watertight shear constants and the culling pad (computed as in bvh2.stack).
    kx, ky, kz, Sx, Sy, Sz = ray_triangle_setup(dx, dy, dz)
    okx = origin[r, kx]
    oky = origin[r, ky]
    okz = origin[r, kz]
    pad = culling_pad(okz, Sz, root_box[2 * kz], root_box[2 * kz + 1])
    return (
        valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
        kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
    )  # fmt: skip


def root_entry_py(root_box, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, lo, hi):
    """:func:`box_entry_py` of the root box, stored as a flat ``(6,)`` interleaved array.

    (Reshaping it to one row inside a kernel costs numba a runtime call and a reference
    count round trip per ray.)
    """
    return ray_box_entry(
        ox, oy, oz, ix, iy, iz, root_box[nx], root_box[ny], root_box[nz],
        root_box[fx], root_box[fy], root_box[fz], lo, hi,
    )  # fmt: skip


def ray_start_py(origin, direction, tmin, tmax, r, root_box):
    """Return ray ``r``'s constants, culling interval, root entry and empty hit.

    Returns
    -------
    tuple
        The 25 values of :func:`ray_prologue_py`, then ``(box_lo, box_hi, entry,
        best_prim, best_u, best_v)``: boxes are culled against the slightly widened
        interval ``[t_lo - pad, t_hit + pad]`` (aabb.py); ``entry`` is where the ray
        enters ``root_box`` within it (:func:`root_entry_py`, the one root box test of
        a traversal), inf for a miss or a degenerate ray; and the hit so far is none
        (``-1, 0, 0``).
    """
    (
        valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
        kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
    ) = ray_prologue(origin, direction, tmin, tmax, r, root_box)  # fmt: skip
    box_lo = t_lo - pad
    box_hi = t_hit + pad
    # Tested whatever the ray, then masked: a branch around the test would keep
    # ``root_box`` referenced across it, a reference count update per ray.
    entry = root_entry(root_box, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, box_lo, box_hi)
    if not valid:
        entry = INF32
    return (
        valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
        kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
        box_lo, box_hi, entry, -1, ZERO32, ZERO32,
    )  # fmt: skip


ray_prologue = cpu_inline(ray_prologue_py)
root_entry = cpu_inline(root_entry_py)
ray_start = cpu_inline(ray_start_py)
