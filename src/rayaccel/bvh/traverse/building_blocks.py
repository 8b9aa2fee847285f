"""Inline building blocks shared by every ``bvh2`` traversal kernel.

Every stackless traversal of ``bvh2`` must return exactly the hits of the ordered
stack traversal (``bvh2.stack``, :mod:`rayaccel.bvh.traverse.stack`). They therefore
share with it, through these helpers, the per-ray set-up (reciprocal direction,
near/far plane offsets, watertight shear constants, the culling pad of
:mod:`rayaccel.kernels.aabb`), the two-child box test on a packed 64-byte row and the
leaf loop (strict ``t < t_hit`` acceptance); the child order (nearer entry first, ties
to child 0) is the same rule in each kernel. Keeping them here, inlined into
each kernel, guarantees the arithmetic is literally the same.

These helpers are CPU traversal glue (they call other inlined helpers), not leaf
numerics: the CUDA mirrors will have their own.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline, keep_branch, next_up_float32
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, STACK_SIZE
from rayaccel.errors import TraversalOverflowError
from rayaccel.kernels.aabb import culling_pad, ray_box_entry, ray_box_exit
from rayaccel.kernels.triangle import ray_triangle, ray_triangle_setup

INF32 = np.float32(np.inf)
ONE32 = np.float32(1.0)


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
    t_hit = next_up_float32(tmax[r])
    valid = (
        t_lo <= tmax[r]
        and not (dx == 0 and dy == 0 and dz == 0)
        and np.isfinite(dx)
        and np.isfinite(dy)
        and np.isfinite(dz)
        and np.isfinite(ox)
        and np.isfinite(oy)
        and np.isfinite(oz)
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


def box_entry_py(box, row, col, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, lo, hi):
    """Entry distance of the interleaved box at ``box[row, col:col + 6]``, or inf."""
    return ray_box_entry(
        ox, oy, oz, ix, iy, iz,
        box[row, col + nx], box[row, col + ny], box[row, col + nz],
        box[row, col + fx], box[row, col + fy], box[row, col + fz],
        lo, hi,
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


def box_exit_py(box, row, col, ox, oy, oz, ix, iy, iz, fx, fy, fz):
    """Exit distance (2-ulp enlarged, NaN ignored) of the box at ``box[row, col:col + 6]``."""
    return ray_box_exit(
        ox, oy, oz, ix, iy, iz, box[row, col + fx], box[row, col + fy], box[row, col + fz]
    )


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


def pick_py(first, a, b):
    """``a if first else b``, kept a branch (:func:`rayaccel._jit.keep_branch`).

    For a traversal's next node: as a select it would wait for the box test that
    decides it; as a branch the CPU predicts it and fetches the node at once.
    """
    if first:
        keep_branch()
        return a
    keep_branch()
    return b


ray_prologue = cpu_inline(ray_prologue_py)
box_entry = cpu_inline(box_entry_py)
root_entry = cpu_inline(root_entry_py)
box_exit = cpu_inline(box_exit_py)
intersect_leaf = cpu_inline(intersect_leaf_py)
pick = cpu_inline(pick_py)


def check_trail_depth(bvh: Any, cache: dict[str, Any] | None, key: str) -> None:
    """Raise ``TraversalOverflowError`` if ``bvh`` is deeper than a 64-bit trail can follow.

    Builders bound the depth by ``MAX_DEPTH`` (56), within every trail's bits; only a
    hand-made tree can be deeper. The depth is memoised in ``cache``.
    """
    depth = cache.get("bvh2.depth") if cache is not None else None
    if depth is None:
        depth = bvh.depth()
        if cache is not None:
            cache["bvh2.depth"] = depth
    if depth > MAX_DEPTH:
        raise TraversalOverflowError(
            f"{key}: the tree is {depth} levels deep, deeper than MAX_DEPTH = {MAX_DEPTH}; "
            f"its per-level trail holds at most {MAX_DEPTH} levels of a {STACK_SIZE}-bit word"
        )
