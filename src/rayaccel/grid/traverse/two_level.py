"""DDA in DDA through a two-level grid (Kalojanov, Billeter, Slusallek 2011).

The top-level walk is :mod:`rayaccel.grid.traverse.dda`'s (clamped, biased start
cell; exit planes recomputed per step; ties x, y, z; stop when ``t_hit + pad <=``
the exit). In a non-empty top cell a second DDA walks its sub-grid from the point where
the ray entered the top cell (start leaf biased against the direction and clamped to
the sub-grid) until it leaves the sub-grid or the closest hit lies before the leaf's
exit (then the whole walk ends). The mailbox lives across both levels. With
``skip`` (``grid.skip``), an empty top cell with skip data is crossed in one jump as in
the uniform grid (the thesis's proposal: empty-space skipping on the two-level grid).

Counters: ``steps`` top and leaf steps, ``cells`` leaf cells entered (and empty top
cells), ``empty_cells`` empty ones, ``vertical_steps`` descents into a sub-grid,
``prim_tests``, ``mailbox_hits``, ``bytes``.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.counters import Counter
from rayaccel.grid.layouts.two_level import TwoLevelGrid, TwoLevelTrace, two_level_trace_layout
from rayaccel.grid.layouts.uniform import SKIP_DISTANCE, with_mailbox
from rayaccel.grid.traverse.walk import exit_plane, leave_box, make_mailbox, start_cell
from rayaccel.kernels.triangle import ray_triangle
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_prologue, root_entry
from rayaccel.trace.run import body_kernels, memoised_layout
from rayaccel.trace.skeleton import store_hit

INF32 = np.float32(np.inf)
ZERO32 = np.float32(0.0)
_CELL_BYTES = 8
_PRIM_BYTES = 40


@functools.cache
def trace_body(skip: bool) -> Any:
    """Return the per-ray body (``cpu_inline``) of DDA in DDA (``skip``: jump empty top cells)."""

    def trace_rays_py(
        grid, scratch, origin, direction, tmin, tmax, begin, end,
        hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
    ):  # fmt: skip
        """Trace rays ``begin:end`` through ``grid`` (TwoLevelTrace); return 0."""
        _ = skip
        mailbox = scratch
        n_mail = grid.mailbox[0]
        skip_kind = grid.skip_kind[0]
        cell_start = grid.cell_start
        leaf_start = grid.leaf_start
        tri = grid.tri
        tri_prim = grid.tri_prim
        rx = grid.res[0]
        ry = grid.res[1]
        rz = grid.res[2]
        lox = grid.lo[0]
        loy = grid.lo[1]
        loz = grid.lo[2]
        sx = grid.size[0]
        sy = grid.size[1]
        sz = grid.size[2]
        for r in range(begin, end):
            n_steps = 0
            n_cells = 0
            n_empty = 0
            n_prim = 0
            n_mailbox = 0
            n_vertical = 0
            n_bytes = 0
            (
                valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            ) = ray_prologue(origin, direction, tmin, tmax, r, grid.box)  # fmt: skip
            best_prim = -1
            best_u = ZERO32
            best_v = ZERO32
            if valid:
                t_start = root_entry(
                    grid.box, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz,
                    t_lo - pad, t_hit + pad,
                )  # fmt: skip
                if t_start != INF32:
                    dx = direction[r, 0]
                    dy = direction[r, 1]
                    dz = direction[r, 2]
                    for m in range(n_mail):
                        mailbox[m] = -1
                    slot = 0
                    cx = start_cell(ox + t_start * dx, lox, grid.inv_size[0], rx, dx)
                    cy = start_cell(oy + t_start * dy, loy, grid.inv_size[1], ry, dy)
                    cz = start_cell(oz + t_start * dz, loz, grid.inv_size[2], rz, dz)
                    step_x = 1 if dx > 0 else (-1 if dx < 0 else 0)
                    step_y = 1 if dy > 0 else (-1 if dy < 0 else 0)
                    step_z = 1 if dz > 0 else (-1 if dz < 0 else 0)
                    tnx = exit_plane(lox, sx, ox, ix, cx, step_x)
                    tny = exit_plane(loy, sy, oy, iy, cy, step_y)
                    tnz = exit_plane(loz, sz, oz, iz, cz, step_z)
                    t_enter = t_start
                    done = False
                    while True:
                        cell = cx + rx * (cy + ry * cz)
                        empty = cell_start[cell] == cell_start[cell + 1]
                        if with_stats:
                            n_steps += 1
                            n_bytes += _CELL_BYTES
                        if empty:
                            if with_stats:
                                n_cells += 1
                                n_empty += 1
                            if skip and skip_kind == SKIP_DISTANCE:
                                k = np.int32(grid.skip[cell, 0]) - 1
                                bx0 = max(cx - k, 0)
                                by0 = max(cy - k, 0)
                                bz0 = max(cz - k, 0)
                                bx1 = min(cx + k, rx - 1)
                                by1 = min(cy + k, ry - 1)
                                bz1 = min(cz + k, rz - 1)
                                moved, t_box, cx, cy, cz = leave_box(
                                    bx0, by0, bz0, bx1, by1, bz1, cx, cy, cz, step_x, step_y,
                                    step_z, grid.lo, grid.size, grid.inv_size, grid.res,
                                    ox, oy, oz, ix, iy, iz, dx, dy, dz, t_hit + pad,
                                )  # fmt: skip
                                if not moved:
                                    break
                                tnx = exit_plane(lox, sx, ox, ix, cx, step_x)
                                tny = exit_plane(loy, sy, oy, iy, cy, step_y)
                                tnz = exit_plane(loz, sz, oz, iz, cz, step_z)
                                t_enter = t_box
                                continue
                        else:
                            # Descend: a DDA over this top cell's sub-grid from t_enter.
                            if with_stats:
                                n_vertical += 1
                            lrx = grid.sub_res[cell, 0]
                            lry = grid.sub_res[cell, 1]
                            lrz = grid.sub_res[cell, 2]
                            lsx = grid.leaf_size[cell, 0]
                            lsy = grid.leaf_size[cell, 1]
                            lsz = grid.leaf_size[cell, 2]
                            tlx = lox + np.float32(cx) * sx
                            tly = loy + np.float32(cy) * sy
                            tlz = loz + np.float32(cz) * sz
                            base = grid.leaf_first[cell]
                            jx = start_cell(ox + t_enter * dx, tlx, grid.leaf_inv[cell, 0], lrx, dx)
                            jy = start_cell(oy + t_enter * dy, tly, grid.leaf_inv[cell, 1], lry, dy)
                            jz = start_cell(oz + t_enter * dz, tlz, grid.leaf_inv[cell, 2], lrz, dz)
                            lnx = exit_plane(tlx, lsx, ox, ix, jx, step_x)
                            lny = exit_plane(tly, lsy, oy, iy, jy, step_y)
                            lnz = exit_plane(tlz, lsz, oz, iz, jz, step_z)
                            while True:
                                leaf = base + jx + lrx * (jy + lry * jz)
                                first = leaf_start[leaf]
                                last = leaf_start[leaf + 1]
                                if with_stats:
                                    n_steps += 1
                                    n_cells += 1
                                    n_bytes += _CELL_BYTES
                                    if first == last:
                                        n_empty += 1
                                for i in range(first, last):
                                    p = tri_prim[i]
                                    seen = False
                                    for m in range(n_mail):
                                        if mailbox[m] == p:
                                            seen = True
                                            break
                                    if seen:
                                        if with_stats:
                                            n_mailbox += 1
                                        continue
                                    if n_mail > 0:
                                        mailbox[slot] = p
                                        slot += 1
                                        if slot == n_mail:
                                            slot = 0
                                    t, u, v = ray_triangle(
                                        tri, i, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit
                                    )
                                    if with_stats:
                                        n_prim += 1
                                        n_bytes += _PRIM_BYTES
                                    if t < t_hit:
                                        t_hit = t
                                        best_prim = p
                                        best_u = u
                                        best_v = v
                                        if query == QUERY_ANY:
                                            break
                                if query == QUERY_ANY and best_prim >= 0:
                                    done = True
                                    break
                                if lnx <= lny and lnx <= lnz:
                                    if lnx >= t_hit + pad:
                                        done = True
                                        break
                                    jx += step_x
                                    if jx < 0 or jx >= lrx:
                                        break
                                    lnx = exit_plane(tlx, lsx, ox, ix, jx, step_x)
                                elif lny <= lnz:
                                    if lny >= t_hit + pad:
                                        done = True
                                        break
                                    jy += step_y
                                    if jy < 0 or jy >= lry:
                                        break
                                    lny = exit_plane(tly, lsy, oy, iy, jy, step_y)
                                else:
                                    if lnz >= t_hit + pad:
                                        done = True
                                        break
                                    jz += step_z
                                    if jz < 0 or jz >= lrz:
                                        break
                                    lnz = exit_plane(tlz, lsz, oz, iz, jz, step_z)
                            if done:
                                break
                        # Next top cell.
                        if tnx <= tny and tnx <= tnz:
                            if tnx >= t_hit + pad:
                                break
                            t_enter = tnx
                            cx += step_x
                            if cx < 0 or cx >= rx:
                                break
                            tnx = exit_plane(lox, sx, ox, ix, cx, step_x)
                        elif tny <= tnz:
                            if tny >= t_hit + pad:
                                break
                            t_enter = tny
                            cy += step_y
                            if cy < 0 or cy >= ry:
                                break
                            tny = exit_plane(loy, sy, oy, iy, cy, step_y)
                        else:
                            if tnz >= t_hit + pad:
                                break
                            t_enter = tnz
                            cz += step_z
                            if cz < 0 or cz >= rz:
                                break
                            tnz = exit_plane(loz, sz, oz, iz, cz, step_z)
            if with_stats:
                counters[r, Counter.STEPS] = n_steps
                counters[r, Counter.CELLS] = n_cells
                counters[r, Counter.EMPTY_CELLS] = n_empty
                counters[r, Counter.PRIM_TESTS] = n_prim
                counters[r, Counter.MAILBOX_HITS] = n_mailbox
                counters[r, Counter.VERTICAL_STEPS] = n_vertical
                counters[r, Counter.BYTES] = n_bytes
            store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
        return 0

    return cpu_inline(trace_rays_py)




@functools.cache
def kernels_for(skip: bool) -> Any:
    """``kernel_for(query, with_stats, parallel)`` of DDA in DDA (skipping if ``skip``)."""
    return body_kernels(make_mailbox, trace_body(skip))


def two_level_layout(
    grid: TwoLevelGrid, mesh: TriangleMesh, cache: dict[str, Any] | None, mailbox: int
) -> TwoLevelTrace:
    """Return the two-level traversal layout (memoised in ``cache``) with its mailbox size."""
    layout = memoised_layout(
        cache, "grid.two_level_trace", lambda: two_level_trace_layout(grid, mesh.hit_rows())
    )
    return with_mailbox(layout, mailbox)
