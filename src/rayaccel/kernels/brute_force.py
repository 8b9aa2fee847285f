"""Brute-force ray casting: every ray against every triangle (the test oracle).

It uses exactly the watertight triangle test of :mod:`rayaccel.kernels.triangle`,
so an acceleration structure that is correct must return the same closest hit on
every ray (same triangle except at exact ties of ``t``). Closest hit keeps the
first triangle (lowest index) among equal ``t``; any-hit stops at the first hit.
Cost is O(rays × triangles): meant for tests and validation on subsets.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.kernels.triangle import ray_triangle, ray_triangle_setup
from rayaccel.queries import QUERY_ANY, QUERY_CLOSEST


@functools.cache
def _brute_force_kernel(query: int) -> Any:
    @cpu_kernel(parallel=True)
    def kernel(tri, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v):
        """Test every triangle ``tri (F, 9) float32`` against every ray; write the hits."""
        _ = query
        for r in prange(origin.shape[0]):
            dx = direction[r, 0]
            dy = direction[r, 1]
            dz = direction[r, 2]
            t_lo = tmin[r]
            t_hi = tmax[r]
            # Degenerate rays miss by definition.
            if not (t_lo <= t_hi) or (dx == 0 and dy == 0 and dz == 0):
                continue
            if not (np.isfinite(dx) and np.isfinite(dy) and np.isfinite(dz)):
                continue
            kx, ky, kz, Sx, Sy, Sz = ray_triangle_setup(dx, dy, dz)
            okx = origin[r, kx]
            oky = origin[r, ky]
            okz = origin[r, kz]
            # Inclusive tmax: nudge it one ulp up since the triangle test's bound is strict.
            best = np.nextafter(t_hi, np.float32(np.inf))
            best_prim = -1
            best_u = np.float32(0.0)
            best_v = np.float32(0.0)
            for p in range(tri.shape[0]):
                t, u, v = ray_triangle(tri, p, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, best)
                if t < best:
                    best = t
                    best_prim = p
                    best_u = u
                    best_v = v
                    if query == QUERY_ANY:
                        break
            if best_prim >= 0:
                hit_t[r] = best
                hit_prim[r] = best_prim
                hit_u[r] = best_u
                hit_v[r] = best_v

    return kernel


def brute_force_trace(
    tri: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    tmin: np.ndarray,
    tmax: np.ndarray,
    query: int = QUERY_CLOSEST,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Trace rays against all triangles.

    Parameters
    ----------
    tri : (F, 9) float32
        Triangle corners, one row per triangle.
    origin, direction : (n, 3) float32
        Ray origins and directions (not necessarily unit length).
    tmin, tmax : (n,) float32
        Ray intervals.
    query : int
        ``QUERY_CLOSEST`` or ``QUERY_ANY``.

    Returns
    -------
    t : (n,) float32, prim : (n,) int32, u, v : (n,) float32
        ``inf`` / ``-1`` / 0 on a miss.
    """
    n = origin.shape[0]
    hit_t = np.full(n, np.inf, dtype=np.float32)
    hit_prim = np.full(n, -1, dtype=np.int32)
    hit_u = np.zeros(n, dtype=np.float32)
    hit_v = np.zeros(n, dtype=np.float32)
    _brute_force_kernel(int(query))(
        tri, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v
    )
    return hit_t, hit_prim, hit_u, hit_v
