"""The steps grid walks share: the start cell, a cell's exit plane, leaving a box of cells.

Also the walks' per-worker scratch, the mailbox ring (:func:`make_mailbox`).

Inline helpers (``rayaccel._jit.cpu_inline``) of the uniform, two-level and irregular
grid traversals. A walk over a lattice of equal cells (the uniform grid, a top grid,
the irregular grid's voxels) starts in the cell of its entry point, biased against the
ray direction (:func:`start_cell`), and leaves a box of cells (one cell, an empty
region, an irregular cell's expanded box) at the nearest of its three exit planes
(:func:`leave_box`). Re-entering beyond a box is exact on the exit axis and clamped
into the box on the others (Pérard-Gayot et al. 2017), so a walk never lands past a
cell it has not visited, and never steps against the ray direction.
"""

from __future__ import annotations

import math

import numpy as np

from rayaccel._jit import cpu_inline

INF32 = np.float32(np.inf)
#: The start cell is biased this fraction of a cell against the direction.
START_BIAS = np.float32(2.0**-12)


def start_cell_py(p, lo, inv_size, res, d):
    """Cell of coordinate ``p`` on one axis, biased against ``d``, clamped to the grid."""
    f = (p - lo) * inv_size
    if d > 0:
        f -= START_BIAS
    elif d < 0:
        f += START_BIAS
    f = min(max(f, np.float32(0.0)), np.float32(res - 1))
    return np.int32(math.floor(f))


def exit_plane_py(lo, size, o, inv, cell, step):
    """Distance to the plane a ray leaves ``cell`` through on one axis (inf if no step)."""
    if step > 0:
        return (lo + np.float32(cell + 1) * size - o) * inv
    if step < 0:
        return (lo + np.float32(cell) * size - o) * inv
    return INF32


start_cell = cpu_inline(start_cell_py)
exit_plane = cpu_inline(exit_plane_py)


def make_mailbox_py(grid):
    """Return one worker's mailbox ring (at least one slot, so the type is fixed).

    The per-worker scratch of every grid walk: ``grid.mailbox[0]`` recently tested ids.
    """
    return np.empty(max(grid.mailbox[0], 1), dtype=np.int32)


make_mailbox = cpu_inline(make_mailbox_py)


def toward_py(new, old, step):
    """Return ``new`` on one axis, never behind ``old`` along ``step`` (``old`` if no step)."""
    if step > 0:
        return max(new, old)
    if step < 0:
        return min(new, old)
    return old


toward = cpu_inline(toward_py)


def cell_in_box_py(p, lo, inv_size, res, d, b0, b1):
    """:func:`start_cell` of coordinate ``p``, clamped into the box's ``[b0, b1]``."""
    return min(max(np.int64(start_cell(p, lo, inv_size, res, d)), b0), b1)


cell_in_box = cpu_inline(cell_in_box_py)


def leave_box_py(
    bx0, by0, bz0, bx1, by1, bz1, cx, cy, cz, step_x, step_y, step_z,
    lo, size, inv_size, res, ox, oy, oz, ix, iy, iz, dx, dy, dz, t_stop,
):  # fmt: skip
    """Leave the box of cells ``[b0, b1]`` (inclusive) that holds cell ``c``.

    ``lo``, ``size``, ``inv_size``, ``res`` describe the lattice (``(3,)`` arrays).
    Returns ``(moved, t_box, cx, cy, cz)``: the distance to the box's exit and the cell
    beyond it, or ``moved`` False when the exit lies at or beyond ``t_stop`` or
    outside the lattice (the walk ends).
    """
    far_x = bx1 if step_x > 0 else bx0
    far_y = by1 if step_y > 0 else by0
    far_z = bz1 if step_z > 0 else bz0
    tbx = exit_plane(lo[0], size[0], ox, ix, far_x, step_x)
    tby = exit_plane(lo[1], size[1], oy, iy, far_y, step_y)
    tbz = exit_plane(lo[2], size[2], oz, iz, far_z, step_z)
    t_box = min(tbx, tby, tbz)
    nxc = np.int64(cx)
    nyc = np.int64(cy)
    nzc = np.int64(cz)
    if t_box >= t_stop:
        return False, t_box, nxc, nyc, nzc
    if tbx <= tby and tbx <= tbz:
        nxc = np.int64(far_x + step_x)
        if nxc < 0 or nxc >= res[0]:
            return False, t_box, nxc, nyc, nzc
        nyc = cell_in_box(oy + t_box * dy, lo[1], inv_size[1], res[1], dy, by0, by1)
        nzc = cell_in_box(oz + t_box * dz, lo[2], inv_size[2], res[2], dz, bz0, bz1)
    elif tby <= tbz:
        nyc = np.int64(far_y + step_y)
        if nyc < 0 or nyc >= res[1]:
            return False, t_box, nxc, nyc, nzc
        nxc = cell_in_box(ox + t_box * dx, lo[0], inv_size[0], res[0], dx, bx0, bx1)
        nzc = cell_in_box(oz + t_box * dz, lo[2], inv_size[2], res[2], dz, bz0, bz1)
    else:
        nzc = np.int64(far_z + step_z)
        if nzc < 0 or nzc >= res[2]:
            return False, t_box, nxc, nyc, nzc
        nxc = cell_in_box(ox + t_box * dx, lo[0], inv_size[0], res[0], dx, bx0, bx1)
        nyc = cell_in_box(oy + t_box * dy, lo[1], inv_size[1], res[1], dy, by0, by1)
    return (
        True, t_box,
        toward(nxc, np.int64(cx), step_x),
        toward(nyc, np.int64(cy), step_y),
        toward(nzc, np.int64(cz), step_z),
    )  # fmt: skip


leave_box = cpu_inline(leave_box_py)
