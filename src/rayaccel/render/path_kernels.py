"""The path tracer's kernels: counter-based random numbers, jittered camera rays, shading.

:mod:`rayaccel.render.path` drives them (the light transport is described there).
Random numbers are a hash of ``(seed, sample, depth)`` (:func:`pass_key`), the pixel
and a dimension, through splitmix64's finaliser (Steele, Lea & Flood 2014, "Fast
splittable pseudorandom number generators", OOPSLA), so an image does not depend on
the thread count or on the order in which paths are shaded.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel


@cpu_inline
def _mix(x):
    """splitmix64's finaliser (Steele, Lea & Flood 2014) on a uint64."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@cpu_inline
def _uniform(key, pixel, dim):
    """Return a uniform double in [0, 1) for a per-pass key, a pixel and a dimension."""
    h = _mix(key ^ (np.uint64(pixel) * np.uint64(0x9E3779B97F4A7C15)))
    h = _mix(h + np.uint64(dim))
    return np.float64(h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


def pass_key(seed: int, sample: int, depth: int) -> np.uint64:
    """Return the hash key of one (seed, sample, depth)."""
    mask = (1 << 64) - 1
    x = seed * 0x9E3779B97F4A7C15 + sample * 0xD1B54A32D192ED03 + depth * 0x8CB92BA72F3D8DD7
    x &= mask
    for shift, mult in ((30, 0xBF58476D1CE4E5B9), (27, 0x94D049BB133111EB)):
        x = ((x ^ (x >> shift)) * mult) & mask
    key: np.uint64 = np.uint64(x ^ (x >> 31))
    return key


@cpu_kernel(parallel=True)
def camera_directions(frame, half_w, half_h, width, height, key, out):
    """Jittered unit directions through every pixel (row-major, row 0 at the top)."""
    for k in prange(width * height):
        row = k // width
        col = k - row * width
        x = (2.0 * (col + _uniform(key, k, 0)) / width - 1.0) * half_w
        y = (1.0 - 2.0 * (row + _uniform(key, k, 1)) / height) * half_h
        dx = frame[0, 0] + x * frame[1, 0] + y * frame[2, 0]
        dy = frame[0, 1] + x * frame[1, 1] + y * frame[2, 1]
        dz = frame[0, 2] + x * frame[1, 2] + y * frame[2, 2]
        inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        out[k, 0] = dx * inv
        out[k, 1] = dy * inv
        out[k, 2] = dz * inv


@cpu_kernel(parallel=True)
def shade_hits(
    tri, albedo, emission, l_tri, l_emit, l_cdf, l_area,
    origin, direction, t, prim, u, v, pixel, throughput,
    key, add_emission, roulette, epsilon,
    radiance, s_origin, s_dir, s_contrib, s_ok, n_origin, n_dir, n_thr, n_ok,
):  # fmt: skip
    """Shade one depth of paths: emission, a light sample and a bounce per hit.

    Writes per path ``i``: the shadow ray (``s_ok[i]`` when one is needed) and its
    contribution if unoccluded; the bounce ray and its throughput (``n_ok[i]`` when
    the path goes on). Adds emission seen directly (``add_emission``) to
    ``radiance[pixel[i]]``; each pixel has one path per pass, so no two iterations
    write one row.
    """
    n_lights = l_cdf.shape[0]
    for i in prange(prim.shape[0]):
        s_ok[i] = False
        n_ok[i] = False
        f = prim[i]
        if f < 0:
            continue
        px = pixel[i]
        # Hit point from the barycentrics, geometric normal facing the ray.
        e1x = np.float64(tri[f, 1, 0]) - tri[f, 0, 0]
        e1y = np.float64(tri[f, 1, 1]) - tri[f, 0, 1]
        e1z = np.float64(tri[f, 1, 2]) - tri[f, 0, 2]
        e2x = np.float64(tri[f, 2, 0]) - tri[f, 0, 0]
        e2y = np.float64(tri[f, 2, 1]) - tri[f, 0, 1]
        e2z = np.float64(tri[f, 2, 2]) - tri[f, 0, 2]
        px_ = tri[f, 0, 0] + u[i] * e1x + v[i] * e2x
        py_ = tri[f, 0, 1] + u[i] * e1y + v[i] * e2y
        pz_ = tri[f, 0, 2] + u[i] * e1z + v[i] * e2z
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length == 0.0:
            continue
        nx /= length
        ny /= length
        nz /= length
        if nx * direction[i, 0] + ny * direction[i, 1] + nz * direction[i, 2] > 0.0:
            nx = -nx
            ny = -ny
            nz = -nz
        t0 = throughput[i, 0]
        t1 = throughput[i, 1]
        t2 = throughput[i, 2]
        if add_emission:
            radiance[px, 0] += t0 * emission[f, 0]
            radiance[px, 1] += t1 * emission[f, 1]
            radiance[px, 2] += t2 * emission[f, 2]
        off = epsilon * max(1.0, abs(px_), abs(py_), abs(pz_))
        ox = px_ + off * nx
        oy = py_ + off * ny
        oz = pz_ + off * nz
        # Next-event estimation: a light by power, a point uniformly on it.
        r = _uniform(key, px, 0)
        lo = 0
        hi = n_lights - 1
        while lo < hi:
            mid = (lo + hi) // 2
            if l_cdf[mid] <= r:
                lo = mid + 1
            else:
                hi = mid
        light = lo
        p_light = l_cdf[light] - (l_cdf[light - 1] if light > 0 else 0.0)
        su = np.sqrt(_uniform(key, px, 1))
        b1 = su * (1.0 - _uniform(key, px, 2))
        b2 = su * _uniform(key, px, 2)
        b0 = 1.0 - b1 - b2
        qx = b0 * l_tri[light, 0, 0] + b1 * l_tri[light, 1, 0] + b2 * l_tri[light, 2, 0]
        qy = b0 * l_tri[light, 0, 1] + b1 * l_tri[light, 1, 1] + b2 * l_tri[light, 2, 1]
        qz = b0 * l_tri[light, 0, 2] + b1 * l_tri[light, 1, 2] + b2 * l_tri[light, 2, 2]
        dx = qx - ox
        dy = qy - oy
        dz = qz - oz
        dist2 = dx * dx + dy * dy + dz * dz
        if dist2 > 0.0 and p_light > 0.0:
            dist = np.sqrt(dist2)
            cos_s = (nx * dx + ny * dy + nz * dz) / dist
            a1x = l_tri[light, 1, 0] - l_tri[light, 0, 0]
            a1y = l_tri[light, 1, 1] - l_tri[light, 0, 1]
            a1z = l_tri[light, 1, 2] - l_tri[light, 0, 2]
            a2x = l_tri[light, 2, 0] - l_tri[light, 0, 0]
            a2y = l_tri[light, 2, 1] - l_tri[light, 0, 1]
            a2z = l_tri[light, 2, 2] - l_tri[light, 0, 2]
            lnx = a1y * a2z - a1z * a2y
            lny = a1z * a2x - a1x * a2z
            lnz = a1x * a2y - a1y * a2x
            cos_l = abs(lnx * dx + lny * dy + lnz * dz) / (dist * 2.0 * l_area[light])
            if cos_s > 0.0 and cos_l > 0.0:
                # L_e · (albedo / π) · cos_s · cos_l / dist² / (p_light / area)
                g = cos_s * cos_l / dist2 * l_area[light] / (p_light * np.pi)
                s_contrib[i, 0] = t0 * albedo[f, 0] * l_emit[light, 0] * g
                s_contrib[i, 1] = t1 * albedo[f, 1] * l_emit[light, 1] * g
                s_contrib[i, 2] = t2 * albedo[f, 2] * l_emit[light, 2] * g
                s_origin[i, 0] = ox
                s_origin[i, 1] = oy
                s_origin[i, 2] = oz
                s_dir[i, 0] = dx
                s_dir[i, 1] = dy
                s_dir[i, 2] = dz
                s_ok[i] = True
        # Bounce: cosine-weighted direction about the normal (Malley's method).
        r1 = _uniform(key, px, 3)
        r2 = _uniform(key, px, 4)
        radius = np.sqrt(r1)
        phi = 2.0 * np.pi * r2
        lx = radius * np.cos(phi)
        ly = radius * np.sin(phi)
        lz = np.sqrt(max(0.0, 1.0 - r1))
        if abs(nx) > 0.5:
            ax, ay, az = 0.0, 1.0, 0.0
        else:
            ax, ay, az = 1.0, 0.0, 0.0
        # tangent = normalize(a × n), bitangent = n × tangent
        tx = ay * nz - az * ny
        ty = az * nx - ax * nz
        tz = ax * ny - ay * nx
        tl = np.sqrt(tx * tx + ty * ty + tz * tz)
        tx /= tl
        ty /= tl
        tz /= tl
        bx = ny * tz - nz * ty
        by = nz * tx - nx * tz
        bz = nx * ty - ny * tx
        t0 *= albedo[f, 0]
        t1 *= albedo[f, 1]
        t2 *= albedo[f, 2]
        if roulette:
            q = min(1.0, max(t0, t1, t2))
            if _uniform(key, px, 5) >= q:
                continue
            t0 /= q
            t1 /= q
            t2 /= q
        if max(t0, t1, t2) <= 0.0:
            continue
        n_origin[i, 0] = ox
        n_origin[i, 1] = oy
        n_origin[i, 2] = oz
        n_dir[i, 0] = lx * tx + ly * bx + lz * nx
        n_dir[i, 1] = lx * ty + ly * by + lz * ny
        n_dir[i, 2] = lx * tz + ly * bz + lz * nz
        n_thr[i, 0] = t0
        n_thr[i, 1] = t1
        n_thr[i, 2] = t2
        n_ok[i] = True
