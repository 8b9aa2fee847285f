"""The steps grid walks share: the start cell, a cell's exit plane, leaving a box of cells.

Also the walks' per-worker scratch, the mailbox ring (:func:`make_mailbox`), emptied
with the direction's axis steps at the start of a walk (:func:`walk_start`), the test of
a cell's triangles through it (:func:`intersect_cell`), the 3D-DDA's entry into a
lattice and its step to the next cell (:func:`enter_lattice`, :func:`next_cell`), and the
store of a walk's counters (:func:`store_walk_counters`).

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

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.counters import Counter
from rayaccel.kernels.triangle import ray_triangle
from rayaccel.trace.skeleton import store_counts

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
    # f >= 0, so truncating is the floor: one instruction, where numba's math.floor of
    # a float32 calls a C helper (and CUDA has no np.floor); every grid step converts two.
    return np.int32(f)


def exit_plane_py(lo, size, o, inv, cell, step):
    """Distance to the plane a ray leaves ``cell`` through on one axis (inf if no step)."""
    if step > 0:
        return (lo + np.float32(cell + 1) * size - o) * inv
    if step < 0:
        return (lo + np.float32(cell) * size - o) * inv
    return INF32


start_cell = cpu_inline(start_cell_py)
exit_plane = cpu_inline(exit_plane_py)

#: What :func:`next_cell` did: stepped into the next cell, stopped because the closest hit
#: lies before the cell's exit (with the culling pad), or left the lattice.
MOVED = 0
HIT_BEFORE_EXIT = 1
LEFT_LATTICE = 2


def axis_steps_py(dx, dy, dz):
    """Return the cell step of a direction on each axis: +1, -1, or 0 for a zero component."""
    return (
        1 if dx > 0 else (-1 if dx < 0 else 0),
        1 if dy > 0 else (-1 if dy < 0 else 0),
        1 if dz > 0 else (-1 if dz < 0 else 0),
    )


def walk_start_py(direction, r, mailbox, n_mail):
    """Return ray ``r``'s direction and axis steps, and empty the first ``n_mail`` mailbox slots.

    Returns ``(dx, dy, dz, step_x, step_y, step_z, slot)``, ``slot`` the mailbox slot
    the walk writes next (0).
    """
    dx = direction[r, 0]
    dy = direction[r, 1]
    dz = direction[r, 2]
    for m in range(n_mail):
        mailbox[m] = -1
    step_x, step_y, step_z = axis_steps(dx, dy, dz)
    return dx, dy, dz, step_x, step_y, step_z, 0


walk_start = cpu_inline(walk_start_py)


def enter_lattice_py(
    t, ox, oy, oz, dx, dy, dz, ix, iy, iz, step_x, step_y, step_z,
    lox, loy, loz, sx, sy, sz, vx, vy, vz, rx, ry, rz,
):  # fmt: skip
    """Return the cell of the ray's point at ``t`` and the distances to its exit planes.

    The lattice starts at ``lo``, has cells of size ``s`` (reciprocals ``v``) and ``r``
    cells per axis. Returns ``(cx, cy, cz, tnx, tny, tnz)`` (:func:`start_cell`,
    :func:`exit_plane`).
    """
    cx = start_cell(ox + t * dx, lox, vx, rx, dx)
    cy = start_cell(oy + t * dy, loy, vy, ry, dy)
    cz = start_cell(oz + t * dz, loz, vz, rz, dz)
    return (
        cx, cy, cz,
        exit_plane(lox, sx, ox, ix, cx, step_x),
        exit_plane(loy, sy, oy, iy, cy, step_y),
        exit_plane(loz, sz, oz, iz, cz, step_z),
    )  # fmt: skip


def next_cell_py(
    cx, cy, cz, tnx, tny, tnz, step_x, step_y, step_z, rx, ry, rz,
    lox, loy, loz, sx, sy, sz, ox, oy, oz, ix, iy, iz, t_stop,
):  # fmt: skip
    """Step the 3D-DDA on the axis of the nearest exit plane (ties: x, then y, then z).

    Stops (:data:`HIT_BEFORE_EXIT`) instead when that exit lies at or beyond ``t_stop``
    (the closest hit plus the culling pad): no later cell can hold a nearer hit. Returns
    ``(state, t_exit, cx, cy, cz, tnx, tny, tnz)``: the state (:data:`MOVED`,
    :data:`HIT_BEFORE_EXIT`, :data:`LEFT_LATTICE`), the distance at which the ray left
    the cell, the new cell and its exit distances (lattice as :func:`enter_lattice`).
    """
    if tnx <= tny and tnx <= tnz:
        if tnx >= t_stop:
            return HIT_BEFORE_EXIT, tnx, cx, cy, cz, tnx, tny, tnz
        cx += step_x
        if cx < 0 or cx >= rx:
            return LEFT_LATTICE, tnx, cx, cy, cz, tnx, tny, tnz
        return MOVED, tnx, cx, cy, cz, exit_plane(lox, sx, ox, ix, cx, step_x), tny, tnz
    if tny <= tnz:
        if tny >= t_stop:
            return HIT_BEFORE_EXIT, tny, cx, cy, cz, tnx, tny, tnz
        cy += step_y
        if cy < 0 or cy >= ry:
            return LEFT_LATTICE, tny, cx, cy, cz, tnx, tny, tnz
        return MOVED, tny, cx, cy, cz, tnx, exit_plane(loy, sy, oy, iy, cy, step_y), tnz
    if tnz >= t_stop:
        return HIT_BEFORE_EXIT, tnz, cx, cy, cz, tnx, tny, tnz
    cz += step_z
    if cz < 0 or cz >= rz:
        return LEFT_LATTICE, tnz, cx, cy, cz, tnx, tny, tnz
    return MOVED, tnz, cx, cy, cz, tnx, tny, exit_plane(loz, sz, oz, iz, cz, step_z)


def distance_box_py(cx, cy, cz, k, rx, ry, rz):
    """Return the box of cells ``(bx0, by0, bz0, bx1, by1, bz1)`` within ``k`` of cell ``c``.

    The empty cube around an empty cell whose distance-field value is ``k + 1``,
    clipped to the ``r``-cell grid.
    """
    return (
        max(cx - k, 0), max(cy - k, 0), max(cz - k, 0),
        min(cx + k, rx - 1), min(cy + k, ry - 1), min(cz + k, rz - 1),
    )  # fmt: skip


axis_steps = cpu_inline(axis_steps_py)
enter_lattice = cpu_inline(enter_lattice_py)
next_cell = cpu_inline(next_cell_py)
distance_box = cpu_inline(distance_box_py)


def make_mailbox_py(grid):
    """Return one worker's mailbox ring (at least one slot, so the type is fixed).

    The per-worker scratch of every grid walk: ``grid.mailbox[0]`` recently tested ids.
    """
    return np.empty(max(grid.mailbox[0], 1), dtype=np.int32)


make_mailbox = cpu_inline(make_mailbox_py)


def intersect_cell_py(
    tri, tri_prim, first, last, mailbox, n_mail, slot, okx, oky, okz, kx, ky, kz,
    Sx, Sy, Sz, t_lo, t_hit, best_prim, best_u, best_v, n_tested, n_skipped, stop_at_first,
):  # fmt: skip
    """Test a cell's triangles ``first:last``, skipping ids in the ring mailbox.

    Each tested id enters the ring at ``slot`` (``n_mail`` entries; none when 0): a
    triangle spans several cells, and testing it again could not change the hit, since
    the hit interval only shrinks. Otherwise as
    :func:`rayaccel.trace.leaf.intersect_leaf`. Returns ``(t_hit, prim, u, v, slot,
    n_tested, n_skipped)``, the last two the ray's running counts of triangles tested
    and of tests the mailbox saved (unused counts compile away).
    """
    for i in range(first, last):
        p = tri_prim[i]
        seen = False
        for m in range(n_mail):
            if mailbox[m] == p:
                seen = True
                break
        if seen:
            n_skipped += 1
            continue
        if n_mail > 0:
            mailbox[slot] = p
            slot += 1
            if slot == n_mail:
                slot = 0
        t, u, v = ray_triangle(tri, i, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit)
        n_tested += 1
        if t < t_hit:
            t_hit = t
            best_prim = p
            best_u = u
            best_v = v
            if stop_at_first:
                break
    return t_hit, best_prim, best_u, best_v, slot, n_tested, n_skipped


intersect_cell = cpu_inline(intersect_cell_py)


def store_walk_counters_py(
    counters, r, steps, cells, empty, prims, mailbox_hits, vertical, n_bytes
):
    """Store a grid walk's counters of ray ``r`` (every grid traversal counts the same ones)."""
    store_counts(counters, r, steps, 0, 0, prims, 0, n_bytes)
    counters[r, Counter.CELLS] = cells
    counters[r, Counter.EMPTY_CELLS] = empty
    counters[r, Counter.MAILBOX_HITS] = mailbox_hits
    counters[r, Counter.VERTICAL_STEPS] = vertical


store_walk_counters = cpu_inline(store_walk_counters_py)


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
