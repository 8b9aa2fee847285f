"""The irregular grid's cell walk (Pérard-Gayot, Kalojanov, Slusallek 2017).

ALGORITHMS §7.5. The ray is clipped to the grid box (with the culling pad) and starts
in the voxel of its entry point (:func:`~rayaccel.grid.traverse.walk.start_cell` on
the virtual fine grid). Each step finds the voxel's cell by the voxel map
(:func:`~rayaccel.grid.layouts.irregular.voxel_cell`), tests the cell's triangles
(mailbox as in :mod:`~rayaccel.grid.traverse.dda`) and leaves the cell's *expanded*
box (:func:`~rayaccel.grid.traverse.walk.leave_box`): the next voxel is exact on the
exit axis and the exit point's voxel, clamped into the box, on the others. The walk
ends when the closest hit lies before the box's exit (with the culling pad), when it
leaves the grid, or at the first hit of an any-hit query. An expanded box holds only
cells whose triangles its cell lists, so the cell's tests cover the ray's whole
stretch through it.

``grid.dda`` and ``grid.skip`` both walk an irregular grid this way. Counters
(``with_stats``): ``steps`` and ``cells`` cells visited, ``empty_cells`` empty ones,
``prim_tests``, ``mailbox_hits``, ``bytes`` (12 for the voxel map and cell range, 24
for the expanded box, 40 per triangle and id read).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.grid.layouts.irregular import IrregularGrid, IrregularTrace, trace_layout, voxel_cell
from rayaccel.grid.layouts.uniform import with_mailbox
from rayaccel.grid.traverse.walk import (
    INF32,
    intersect_cell,
    leave_box,
    make_mailbox,
    start_cell,
    store_walk_counters,
    walk_start,
)
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan
from rayaccel.trace.run import body_kernels, memoised_layout
from rayaccel.trace.skeleton import store_hit

_CELL_BYTES = 36
_PRIM_BYTES = 40


def map_cell_py(grid, shift, r, step, cx, cy, cz):
    """Return the cell of voxel ``(cx, cy, cz)`` by the voxel map (:func:`voxel_cell`).

    ``r`` and ``step`` (the ray and how many cells it has entered) are unused here: they
    let a benchmark replace the map by one that records or replays each ray's cells
    (``benchmarks/bound_irregular_map.py``), so that the walk it times is this one.
    """
    return voxel_cell(cx, cy, cz, grid.top_res, shift, grid.log_dim, grid.leaf_first,
                      grid.cell_of_leaf)  # fmt: skip


map_cell = cpu_inline(map_cell_py)


@functools.cache
def walk_body(cell_lookup: Any) -> Any:
    """Return the inline per-chunk body of the walk that finds each cell by ``cell_lookup``.

    ``cell_lookup(grid, shift, r, step, cx, cy, cz)`` returns the cell holding voxel
    ``(cx, cy, cz)``; the traversal's is :func:`map_cell`.
    """

    def trace_rays_py(
        grid, scratch, origin, direction, tmin, tmax, begin, end,
        hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
    ):  # fmt: skip
        """Trace rays ``begin:end`` through ``grid`` (IrregularTrace); return 0 (no stack)."""
        mailbox = scratch
        n_mail = grid.mailbox[0]
        shift = grid.shift[0]
        for r in range(begin, end):
            n_cells = n_empty = n_prim = n_mailbox = 0
            (
                _valid, ox, oy, oz, ix, iy, iz, _nx, _ny, _nz, _fx, _fy, _fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
                _box_lo, _box_hi, t_start, best_prim, best_u, best_v,
            ) = ray_start(origin, direction, tmin, tmax, r, grid.box)  # fmt: skip
            if t_start != INF32:
                dx, dy, dz, step_x, step_y, step_z, slot = walk_start(direction, r, mailbox, n_mail)
                res = grid.fine_res
                lo = grid.lo
                inv = grid.inv_voxel
                cx = np.int64(start_cell(ox + t_start * dx, lo[0], inv[0], res[0], dx))
                cy = np.int64(start_cell(oy + t_start * dy, lo[1], inv[1], res[1], dy))
                cz = np.int64(start_cell(oz + t_start * dz, lo[2], inv[2], res[2], dz))
                step = 0
                while True:
                    cell = cell_lookup(grid, shift, r, step, cx, cy, cz)
                    step += 1
                    first = grid.cell_start[np.uint64(cell)]
                    last = grid.cell_start[np.uint64(cell + 1)]
                    if with_stats:
                        n_cells += 1
                        if first == last:
                            n_empty += 1
                    t_hit, best_prim, best_u, best_v, slot, n_prim, n_mailbox = intersect_cell(
                        grid.tri, grid.tri_prim, first, last, mailbox, n_mail, slot,
                        okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit,
                        best_prim, best_u, best_v, n_prim, n_mailbox, query == QUERY_ANY,
                    )  # fmt: skip
                    if query == QUERY_ANY and best_prim >= 0:
                        break
                    e_lo = grid.exit_lo
                    e_hi = grid.exit_hi
                    moved, _t, cx, cy, cz = leave_box(
                        e_lo[cell, 0], e_lo[cell, 1], e_lo[cell, 2], e_hi[cell, 0],
                        e_hi[cell, 1], e_hi[cell, 2], cx, cy, cz, step_x, step_y, step_z,
                        lo, grid.voxel, inv, res, ox, oy, oz, ix, iy, iz, dx, dy, dz,
                        t_hit + pad,
                    )  # fmt: skip
                    if not moved:
                        break
            if with_stats:
                # One step per cell; no vertical steps.
                n_bytes = n_cells * _CELL_BYTES + n_prim * _PRIM_BYTES
                store_walk_counters(
                    counters, r, n_cells, n_cells, n_empty, n_prim, n_mailbox, 0, n_bytes
                )
            store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
        return 0

    return cpu_inline(trace_rays_py)


trace_rays = walk_body(map_cell)
trace_kernel = body_kernels(make_mailbox, trace_rays)


def irregular_layout(
    grid: IrregularGrid, mesh: TriangleMesh, cache: dict[str, Any] | None, mailbox: int
) -> IrregularTrace:
    """Return the traversal layout of ``grid`` (memoised in ``cache``) with its mailbox size."""
    layout = memoised_layout(
        cache, "grid.irregular.trace", lambda: trace_layout(grid, mesh.hit_rows(), 0)
    )
    return with_mailbox(layout, mailbox)


def irregular_plan(
    grid: IrregularGrid, mesh: TriangleMesh, mailbox: int, cache: LayoutCache
) -> TracePlan:
    """Return the plan of ``grid.dda`` and ``grid.skip`` on an irregular grid."""
    return TracePlan(trace_kernel, irregular_layout(grid, mesh, cache, mailbox))
