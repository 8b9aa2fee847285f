"""The leaf loop: test a range of triangles and keep the nearest hit (or stop at the first).

Every family stores triangles in leaf (or cell) order as the ``(n, 9)`` rows of
:meth:`rayaccel.scene.mesh.TriangleMesh.hit_rows` gathered by a reference array, and
tests a range of them with the watertight test of Woop, Benthin, Wald 2013. A
triangle replaces the current hit only when strictly nearer, which fixes the winner
of an exact tie to the first one tested.
"""

from __future__ import annotations

from rayaccel._jit import cpu_inline
from rayaccel.kernels.triangle import ray_triangle


def intersect_leaf_py(
    tri, tri_prim, first, last, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz,
    t_lo, t_hit, best_prim, best_u, best_v, stop_at_first,
):  # fmt: skip
    """Test triangles ``first:last``; return ``(t_hit, prim, u, v, n_tested)``.

    A triangle replaces the current hit only when strictly nearer, so the first one
    found wins an exact tie (the rule of ``bvh2.stack``). ``stop_at_first`` ends the
    loop at the first accepted hit (any-hit queries).
    """
    for i in range(first, last):
        t, u, v = ray_triangle(tri, i, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit)
        if t < t_hit:
            t_hit = t
            best_prim = tri_prim[i]
            best_u = u
            best_v = v
            if stop_at_first:
                return t_hit, best_prim, best_u, best_v, i - first + 1
    return t_hit, best_prim, best_u, best_v, last - first


intersect_leaf = cpu_inline(intersect_leaf_py)
