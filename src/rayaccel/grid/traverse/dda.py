"""3D-DDA through a uniform grid (Amanatides & Woo 1987), plain or skipping empty space.

The ray is clipped to the grid box over ``[tmin - pad, t_hit + pad]`` (the culling pad
of :mod:`rayaccel.kernels.aabb`) and starts in the cell of its entry point, clamped to
the grid; each axis's start cell is biased by a small fraction of a cell *against* the
ray direction, so rounding can only start the walk one cell early (the next step fixes
that), never one cell late. Per axis the walk keeps the distance ``t_next[a]`` to the
cell's exit plane, recomputed from the plane each step as ``(lo + k·size - o) / d``
(``inf`` on an axis with a zero direction component, of either sign), and steps on the
axis with the smallest one; ties go to x, then y, then z.

Each cell's triangles are tested in id order with the watertight test (Woop et al.
2013), skipping ids found in a small per-ray ring *mailbox* of recently tested ones (a
triangle spans several cells; re-testing it could not change the hit, since the hit
interval only shrinks). The walk ends when the closest hit lies in front of the
current cell's exit, with the culling pad: it stops only when ``t_hit + pad <=
t_exit``, so a hit that rounding places on the wrong side of a cell boundary is never
taken before the cell in which a nearer triangle may lie (cells overlap their
neighbours by a margin, :func:`~rayaccel.grid.layouts.uniform.cell_margin`, which
covers the rounding of points and planes). Any-hit queries stop at the first hit.

``grid.skip`` additionally reads the grid's skip data: in an empty cell it jumps to the
exit of the empty box the grid stores for it (the cube of the distance field, the
macro region, or the coarsest empty block of the occupancy mip-map) and re-enters at
the cell beyond, computed exactly on the exit axis and clamped into the box on the
others (the irregular grid's rule, Pérard-Gayot et al. 2017), so it never lands past
a non-empty cell. On a grid without skip data it is the plain DDA.

A two-level grid (Kalojanov, Billeter, Slusallek 2011) is walked DDA in DDA by the same
body: the top-level walk is the one above, and in a non-empty top cell a second DDA walks
its sub-grid from the point where the ray entered the top cell (start leaf biased
against the direction and clamped to the sub-grid) until it leaves the sub-grid or the
closest hit lies before the leaf's exit (then the whole walk ends). The mailbox lives
across both levels. With ``skip`` (``grid.skip``), an empty top cell with skip data is
crossed in one jump as in the uniform grid (the thesis's proposal: empty-space skipping
on the two-level grid).

Counters (``with_stats``): ``steps`` cell steps and jumps (top and leaf), ``cells``
cells entered (leaf cells and empty top cells of a two-level grid), ``empty_cells``
empty ones, ``prim_tests`` triangle tests, ``mailbox_hits`` tests saved by the
mailbox, ``vertical_steps`` mip-map levels climbed (descents into a sub-grid on a
two-level grid), ``bytes`` 8 per cell range and 40 per triangle and id read.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, TypeAlias

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.errors import InvalidInputError
from rayaccel.grid.layouts.irregular import IrregularGrid
from rayaccel.grid.layouts.two_level import TwoLevelGrid, TwoLevelTrace, two_level_trace_layout
from rayaccel.grid.layouts.uniform import (
    SKIP_DISTANCE,
    SKIP_MACRO,
    SKIP_NONE,
    GridTrace,
    UniformGrid,
    trace_layout,
    with_mailbox,
)
from rayaccel.grid.traverse.walk import (
    HIT_BEFORE_EXIT,
    MOVED,
    distance_box,
    enter_lattice,
    exit_plane,
    intersect_cell,
    leave_box,
    make_mailbox,
    next_cell,
    store_walk_counters,
    walk_start,
)
from rayaccel.queries import QUERY_ANY
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.ray_setup import ray_start
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal
from rayaccel.trace.run import body_kernels, memoised_layout
from rayaccel.trace.skeleton import store_hit

INF32 = np.float32(np.inf)
MAX_MAILBOX = 64
_CELL_BYTES = 8
_PRIM_BYTES = 40

#: The grids ``grid.dda`` and ``grid.skip`` walk.
Grid: TypeAlias = "UniformGrid | TwoLevelGrid | IrregularGrid"


@dataclass(frozen=True, slots=True)
class DdaOptions:
    """Options of the grid traversals.

    Attributes
    ----------
    mailbox : int
        Recently tested primitive ids remembered per ray (0..64; 0 disables the mailbox).
    """

    mailbox: int = 8

    def __post_init__(self) -> None:
        if not 0 <= self.mailbox <= MAX_MAILBOX:
            raise InvalidInputError(f"mailbox: expected 0..{MAX_MAILBOX}, got {self.mailbox}")


@functools.cache
def trace_body(two_level: bool) -> Any:
    """Return the per-ray body (``cpu_inline``) of the DDA, jumping over the layout's empty boxes.

    The kind of skip data is read from the layout at run time, so one compiled body
    serves ``grid.dda`` (a layout whose ``skip_kind`` is ``SKIP_NONE``: a cell-by-cell
    walk) and ``grid.skip`` on the distance field, the macro regions and the mip-map.
    With ``two_level`` the body walks a :class:`TwoLevelTrace`: DDA in DDA, a non-empty
    top cell walked through its sub-grid (see the module docstring).
    """

    def trace_rays_py(
        grid, scratch, origin, direction, tmin, tmax, begin, end,
        hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
    ):  # fmt: skip
        """Trace rays ``begin:end`` through ``grid`` (GridTrace or TwoLevelTrace); return 0."""
        mailbox = scratch
        skip_kind = grid.skip_kind[0]
        n_mail = grid.mailbox[0]
        cell_start = grid.cell_start
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
        vx = grid.inv_size[0]
        vy = grid.inv_size[1]
        vz = grid.inv_size[2]
        for r in range(begin, end):
            n_steps = n_cells = n_empty = n_prim = n_mailbox = n_vertical = n_bytes = 0
            (
                _valid, ox, oy, oz, ix, iy, iz, _nx, _ny, _nz, _fx, _fy, _fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
                _box_lo, _box_hi, t_start, best_prim, best_u, best_v,
            ) = ray_start(origin, direction, tmin, tmax, r, grid.box)  # fmt: skip
            if t_start != INF32:
                dx, dy, dz, step_x, step_y, step_z, slot = walk_start(direction, r, mailbox, n_mail)
                cx, cy, cz, tnx, tny, tnz = enter_lattice(
                    t_start, ox, oy, oz, dx, dy, dz, ix, iy, iz, step_x, step_y, step_z,
                    lox, loy, loz, sx, sy, sz, vx, vy, vz, rx, ry, rz,
                )  # fmt: skip
                # Where the ray entered the current (top) cell.
                t_enter = t_start
                while True:
                    cell = cx + rx * (cy + ry * cz)
                    first = cell_start[cell]
                    last = cell_start[cell + 1]
                    if with_stats:
                        n_steps += 1
                        n_bytes += _CELL_BYTES
                        if first == last:
                            n_cells += 1
                            n_empty += 1
                        elif two_level:
                            n_vertical += 1
                        else:
                            n_cells += 1
                    if first == last and skip_kind != SKIP_NONE:
                        # Empty cell: leave the empty box around it in one jump.
                        if skip_kind == SKIP_DISTANCE:
                            k = np.int32(grid.skip[cell, 0]) - 1
                            bx0, by0, bz0, bx1, by1, bz1 = distance_box(cx, cy, cz, k, rx, ry, rz)
                        elif skip_kind == SKIP_MACRO:
                            bx0 = np.int32(grid.skip[cell, 0])
                            by0 = np.int32(grid.skip[cell, 1])
                            bz0 = np.int32(grid.skip[cell, 2])
                            bx1 = np.int32(grid.skip[cell, 3])
                            by1 = np.int32(grid.skip[cell, 4])
                            bz1 = np.int32(grid.skip[cell, 5])
                        else:
                            # Mip-map: climb while the block one level up is empty.
                            bits = np.int32(grid.skip[cell, 0]) & 0xFFFF
                            m = 0
                            while m < 15 and not (bits >> (m + 1)) & 1:
                                m += 1
                            if with_stats:
                                n_vertical += m
                            bx0 = (cx >> m) << m
                            by0 = (cy >> m) << m
                            bz0 = (cz >> m) << m
                            bx1 = min(bx0 + (1 << m) - 1, rx - 1)
                            by1 = min(by0 + (1 << m) - 1, ry - 1)
                            bz1 = min(bz0 + (1 << m) - 1, rz - 1)
                        moved, t_enter, cx, cy, cz = leave_box(
                            bx0, by0, bz0, bx1, by1, bz1, cx, cy, cz, step_x, step_y,
                            step_z, grid.lo, grid.size, grid.inv_size, grid.res,
                            ox, oy, oz, ix, iy, iz, dx, dy, dz, t_hit + pad,
                        )  # fmt: skip
                        if not moved:
                            break
                        tnx = exit_plane(lox, sx, ox, ix, cx, step_x)
                        tny = exit_plane(loy, sy, oy, iy, cy, step_y)
                        tnz = exit_plane(loz, sz, oz, iz, cz, step_z)
                        continue
                    if two_level and first != last:
                        # Descend: a DDA over this top cell's sub-grid from t_enter.
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
                        jx, jy, jz, lnx, lny, lnz = enter_lattice(
                            t_enter, ox, oy, oz, dx, dy, dz, ix, iy, iz, step_x, step_y,
                            step_z, tlx, tly, tlz, lsx, lsy, lsz, grid.leaf_inv[cell, 0],
                            grid.leaf_inv[cell, 1], grid.leaf_inv[cell, 2], lrx, lry, lrz,
                        )  # fmt: skip
                        state = MOVED
                        while state == MOVED:
                            leaf = base + jx + lrx * (jy + lry * jz)
                            leaf_first = grid.leaf_start[leaf]
                            leaf_last = grid.leaf_start[leaf + 1]
                            if with_stats:
                                n_steps += 1
                                n_cells += 1
                                n_bytes += _CELL_BYTES
                                if leaf_first == leaf_last:
                                    n_empty += 1
                            t_hit, best_prim, best_u, best_v, slot, n_prim, n_mailbox = (
                                intersect_cell(
                                    tri, tri_prim, leaf_first, leaf_last, mailbox, n_mail,
                                    slot, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo,
                                    t_hit, best_prim, best_u, best_v, n_prim, n_mailbox,
                                    query == QUERY_ANY,
                                )
                            )  # fmt: skip
                            if query == QUERY_ANY and best_prim >= 0:
                                state = HIT_BEFORE_EXIT
                                break
                            state, _t, jx, jy, jz, lnx, lny, lnz = next_cell(
                                jx, jy, jz, lnx, lny, lnz, step_x, step_y, step_z,
                                lrx, lry, lrz, tlx, tly, tlz, lsx, lsy, lsz,
                                ox, oy, oz, ix, iy, iz, t_hit + pad,
                            )  # fmt: skip
                        if state == HIT_BEFORE_EXIT:
                            # The closest hit lies before this leaf's exit: done.
                            break
                    elif not two_level:
                        t_hit, best_prim, best_u, best_v, slot, n_prim, n_mailbox = (
                            intersect_cell(
                                tri, tri_prim, first, last, mailbox, n_mail, slot,
                                okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit,
                                best_prim, best_u, best_v, n_prim, n_mailbox,
                                query == QUERY_ANY,
                            )
                        )  # fmt: skip
                        if query == QUERY_ANY and best_prim >= 0:
                            break
                    # Step to the next cell unless every hit so far lies before it.
                    state, t_enter, cx, cy, cz, tnx, tny, tnz = next_cell(
                        cx, cy, cz, tnx, tny, tnz, step_x, step_y, step_z, rx, ry, rz,
                        lox, loy, loz, sx, sy, sz, ox, oy, oz, ix, iy, iz, t_hit + pad,
                    )  # fmt: skip
                    if state != MOVED:
                        break
            if with_stats:
                store_walk_counters(
                    counters, r, n_steps, n_cells, n_empty, n_prim, n_mailbox, n_vertical,
                    n_bytes + _PRIM_BYTES * n_prim,
                )  # fmt: skip
            store_hit(hit_t, hit_prim, hit_u, hit_v, r, t_hit, best_prim, best_u, best_v)
        return 0

    return cpu_inline(trace_rays_py)


@functools.cache
def kernels_for(two_level: bool) -> Any:
    """``kernel_for(query, with_stats, parallel)`` of the DDA (see :func:`trace_body`)."""
    return body_kernels(make_mailbox, trace_body(two_level))


def walk_layout(layout: GridTrace | TwoLevelTrace, mailbox: int, skip: bool) -> Any:
    """Return ``layout`` with its mailbox size set, its skip kind ``SKIP_NONE`` unless ``skip``.

    The layouts themselves are memoised per ``Accel``; this copy only replaces the two
    ``(1,)`` entries, so ``grid.dda`` and ``grid.skip`` share one compiled body.
    """
    walked = with_mailbox(layout, mailbox)
    if not skip:
        walked = walked._replace(skip_kind=np.array([SKIP_NONE], dtype=walked.skip_kind.dtype))
    return walked


def _plan(
    grid: Grid, mesh: TriangleMesh, options: DdaOptions, cache: LayoutCache, skip: bool
) -> TracePlan:
    if isinstance(grid, IrregularGrid):
        from rayaccel.grid.traverse.irregular import irregular_plan

        return irregular_plan(grid, mesh, options.mailbox, cache)
    if isinstance(grid, TwoLevelGrid):
        layout: GridTrace | TwoLevelTrace = memoised_layout(
            cache, "grid.two_level_trace", lambda: two_level_trace_layout(grid, mesh.hit_rows())
        )
    else:
        layout = memoised_layout(
            cache, "grid.trace", lambda: trace_layout(grid, mesh.hit_rows(), 0)
        )
    walked = walk_layout(layout, options.mailbox, skip)
    return TracePlan(kernels_for(isinstance(grid, TwoLevelGrid)), walked)


@register_traversal("grid.dda", default=True)
def trace_grid_dda(
    grid: UniformGrid | TwoLevelGrid | IrregularGrid,
    mesh: TriangleMesh,
    options: DdaOptions,
    cache: LayoutCache,
) -> TracePlan:
    """3D-DDA cell walk with a per-ray mailbox (closest and any hit).

    Trace rays through a uniform grid cell by cell, a two-level one DDA in DDA.

    Skip data is ignored. An irregular grid is walked cell by cell through its
    expanded boxes (:mod:`rayaccel.grid.traverse.irregular`).

    References
    ----------
    Amanatides & Woo 1987, A Fast Voxel Traversal Algorithm for Ray Tracing.
    """
    return _plan(grid, mesh, options, cache, False)


@register_traversal("grid.skip")
def trace_grid_skip(
    grid: UniformGrid | TwoLevelGrid | IrregularGrid,
    mesh: TriangleMesh,
    options: DdaOptions,
    cache: LayoutCache,
) -> TracePlan:
    """3D-DDA jumping over the grid's empty boxes (distance field, macro regions, mip-map).

    Trace rays through a uniform grid, jumping over empty space with its skip data.

    A grid without skip data (``grid.uniform``) is walked cell by cell, and an
    irregular grid as by :func:`trace_grid_dda`.

    References
    ----------
    Devillers 1989, The Macro-Regions, an Efficient Space Subdivision Structure.
    """
    return _plan(grid, mesh, options, cache, True)
