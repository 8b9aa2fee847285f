# mypy: ignore-errors
# (Warp's stubs describe its kernel language for Python callers, not for code inside kernels.)
"""Warp kernels of the ``warp`` peer: one ray per thread through ``wp.mesh_query_ray``.

Imported only by :class:`rayaccel.bench.peers.WarpPeer` once ``warp`` imports:
Warp compiles module-level ``@wp.kernel`` functions (to C++ for the CPU, to PTX
for CUDA) on their first launch and caches the result per user.
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def closest_hits(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmax: wp.array(dtype=wp.float32),
    t_out: wp.array(dtype=wp.float32),
    prim_out: wp.array(dtype=wp.int32),
) -> None:
    """Closest hit of ray ``tid`` within ``[0, tmax]``: ``t`` and face, or ``inf``/``-1``."""
    tid = wp.tid()
    query = wp.mesh_query_ray(mesh, origins[tid], directions[tid], tmax[tid])
    if query.result:
        t_out[tid] = query.t
        prim_out[tid] = query.face
    else:
        t_out[tid] = wp.inf
        prim_out[tid] = -1


@wp.kernel
def any_hits(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    tmax: wp.array(dtype=wp.float32),
    hit_out: wp.array(dtype=wp.int32),
) -> None:
    """Whether ray ``tid`` hits anything within ``[0, tmax]`` (Warp's any-hit query)."""
    tid = wp.tid()
    hit = wp.mesh_query_ray_anyhit(mesh, origins[tid], directions[tid], tmax[tid])
    hit_out[tid] = wp.int32(hit)
