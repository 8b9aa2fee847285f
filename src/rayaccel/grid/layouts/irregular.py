"""The irregular grid (Pérard-Gayot, Kalojanov, Slusallek 2017) and its traversal layout.

Canonical layout (:class:`IrregularGrid`)
    A *virtual* fine grid of ``fine_res = top_res << shift`` voxels over the box
    ``[lo, hi]``; no array is that large. Its cells are boxes of whole voxels,
    ``cell_box[c] = (x0, y0, z0, x1, y1, z1)`` (``[x0, x1)`` on each axis), that tile
    the fine grid, and each lists ``prim_index[cell_start[c]:cell_start[c + 1]]`` in
    increasing id order: every triangle that overlaps it (the union of the lists of the
    two-level leaves merged into it).

    The *voxel map* finds the cell of a voxel in two steps: the top cell ``t`` holding
    it (``voxel >> shift``), whose sub-grid has ``2^log_dim[t]`` leaves per axis starting
    at ``leaf_first[t]``, then ``cell_of_leaf`` of the leaf holding it.

    ``cell_exit[c]`` is the cell's box with each face pushed out over neighbours whose
    triangles it also lists (the expansion; ``cell_exit ⊇ cell_box``). A ray inside
    the cell may run to the exit of that larger box testing only the cell's list: every
    triangle the box overlaps is listed. Cells are entered by the voxel map alone.

Traversal layout (:class:`IrregularTrace`, :func:`trace_layout`)
    The box interleaved as the root box of :mod:`rayaccel.trace.ray_setup`, the voxel
    size and its inverse, the fine and top resolutions, the voxel map, the expanded
    boxes with inclusive upper bounds, the cell ranges and the triangle rows copied in
    cell order. Bytes: 4 per leaf and per top cell (voxel map), 24 per cell (expanded
    box), 4 per cell and per reference (canonical), 36 per reference copied.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import StructureInvariantError
from rayaccel.grid.layouts.uniform import (
    ListedRefs,
    interleaved_box,
    validate_box,
    validate_lists,
)
from rayaccel.kernels.triangle_rows import gather_rows

#: Largest virtual fine grid resolution along one axis (voxel coordinates stay exact
#: in float32 arithmetic well below 2**24).
MAX_FINE_RES = 2**20


def voxel_cell_py(x, y, z, top_res, shift, log_dim, leaf_first, cell_of_leaf):
    """Return the cell holding voxel ``(x, y, z)`` by the voxel map (two lookups).

    The tables are read at unsigned indices, so numba adds no wraparound of negative
    ones to the chain of dependent loads.
    """
    t = np.uint64((x >> shift) + top_res[0] * ((y >> shift) + top_res[1] * (z >> shift)))
    d = log_dim[t]
    s = shift - d
    mask = (1 << shift) - 1
    side = 1 << d
    leaf = ((x & mask) >> s) + side * (((y & mask) >> s) + side * ((z & mask) >> s))
    return cell_of_leaf[np.uint64(leaf_first[t] + leaf)]


voxel_cell = cpu_inline(voxel_cell_py)


@cpu_kernel(parallel=True)
def leaf_boxes(top_res, shift, log_dim, leaf_first):
    """Return the ``(n_leaves, 6)`` int32 voxel bounds of the leaves of every top cell."""
    out = np.empty((leaf_first[-1], 6), dtype=np.int32)
    rx = top_res[0]
    ry = top_res[1]
    for t in prange(log_dim.shape[0]):
        d = log_dim[t]
        side = 1 << d
        width = 1 << (shift - d)
        tx = (t % rx) << shift
        ty = ((t // rx) % ry) << shift
        tz = (t // (rx * ry)) << shift
        for k in range(leaf_first[t + 1] - leaf_first[t]):
            leaf = leaf_first[t] + k
            out[leaf, 0] = tx + (k % side) * width
            out[leaf, 1] = ty + ((k // side) % side) * width
            out[leaf, 2] = tz + (k // (side * side)) * width
            out[leaf, 3] = out[leaf, 0] + width
            out[leaf, 4] = out[leaf, 1] + width
            out[leaf, 5] = out[leaf, 2] + width
    return out


class IrregularTrace(NamedTuple):
    """What the irregular grid traversal reads, as one kernel argument."""

    box: FloatArray
    lo: FloatArray
    voxel: FloatArray
    inv_voxel: FloatArray
    fine_res: IntArray
    top_res: IntArray
    shift: IntArray
    log_dim: IntArray
    leaf_first: IntArray
    cell_of_leaf: IntArray
    exit_lo: IntArray
    exit_hi: IntArray
    cell_start: IntArray
    tri: FloatArray
    tri_prim: IntArray
    mailbox: IntArray


@dataclass(frozen=True, slots=True, eq=False)
class IrregularGrid(ListedRefs):
    """Irregular grid (see the module docstring).

    Attributes
    ----------
    lo, hi : (3,) float32
        The grid box.
    top_res : (3,) int32
        Top cells per axis.
    shift : int
        ``log2`` of the voxels per top cell along each axis.
    log_dim : (n_top,) int32
        ``log2`` of the leaves per axis of each top cell's sub-grid (``<= shift``).
    leaf_first : (n_top + 1,) int32
        First leaf of each top cell.
    cell_of_leaf : (n_leaves,) int32
        The cell each leaf belongs to after merging.
    cell_box : (n_cells, 6) int32
        Voxel bounds ``(x0, y0, z0, x1, y1, z1)``, upper bounds exclusive.
    cell_exit : (n_cells, 6) int32
        The expanded bounds, same convention.
    cell_start : (n_cells + 1,) int32
    prim_index : (n_refs,) int32
    n_prims : int
    phase_ms : dict
        Build milliseconds by phase.
    stats : dict
        Build counts: leaves, cells after each merge round, faces expanded.
    """

    lo: FloatArray
    hi: FloatArray
    top_res: IntArray
    shift: int
    log_dim: IntArray
    leaf_first: IntArray
    cell_of_leaf: IntArray
    cell_box: IntArray
    cell_exit: IntArray
    cell_start: IntArray
    prim_index: IntArray
    n_prims: int
    phase_ms: dict[str, float] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def fine_res(self) -> IntArray:
        """Voxels per axis of the virtual fine grid."""
        return (self.top_res.astype(np.int64) << self.shift).astype(INDEX)

    @property
    def voxel_size(self) -> np.ndarray:
        """The ``(3,)`` float64 size of a voxel of the fine grid."""
        size: np.ndarray = (self.hi.astype(np.float64) - self.lo) / self.fine_res
        return size

    @property
    def n_cells(self) -> int:
        """Number of cells (after merging)."""
        return int(self.cell_start.shape[0] - 1)

    def nbytes(self) -> int:
        """Return the canonical size in bytes (voxel map, boxes, ranges, references)."""
        arrays = (self.log_dim, self.leaf_first, self.cell_of_leaf, self.cell_box,
                  self.cell_exit, self.cell_start, self.prim_index)  # fmt: skip
        return int(sum(a.nbytes for a in arrays))

    def info(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> dict[str, Any]:
        """Return resolutions, cells, leaves, references per primitive, bytes, phases."""
        _ = (inner_cost, prim_cost)
        counts = np.diff(self.cell_start)
        return {
            "resolution": tuple(int(r) for r in self.top_res),
            "fine_resolution": tuple(int(r) for r in self.fine_res),
            "n_cells": self.n_cells,
            "n_leaves": int(self.cell_of_leaf.shape[0]),
            "n_refs": self.n_refs,
            "empty_fraction": float(np.count_nonzero(counts == 0) / max(self.n_cells, 1)),
            "refs_per_prim": self.n_refs / max(self.n_prims, 1),
            "max_cell_refs": int(counts.max()) if counts.size else 0,
            "grid_bytes": self.nbytes(),
            "build_stats": dict(self.stats),
            "build_phase_ms": {k: round(v, 3) for k, v in self.phase_ms.items()},
        }

    def leaf_boxes(self) -> np.ndarray:
        """Return the ``(n_leaves, 6)`` int32 voxel bounds of every leaf."""
        boxes: np.ndarray = leaf_boxes(self.top_res, self.shift, self.log_dim, self.leaf_first)
        return boxes

    def validate(self, triangles: FloatArray | None = None) -> None:
        """Check every invariant; raise :class:`StructureInvariantError` naming the first broken.

        Checks: dtypes and shapes; the voxel map (each top cell's leaves, each leaf in
        the box of its cell, the cells tiling the fine grid); cell ranges, ids in range
        and increasing, every primitive listed; expanded boxes inside the grid and
        holding their cell; and, given ``triangles (F, 3, 3)``, every triangle inside the
        grid box, every listed triangle's box overlapping its cell's (widened) box, and
        every triangle overlapping an expanded box's voxels listed by its cell (checked
        on grids of at most 4096 cells).
        """
        validate_box(self.lo, self.hi)
        n_top = int(np.prod(self.top_res.astype(np.int64)))
        if self.log_dim.shape != (n_top,) or self.leaf_first.shape != (n_top + 1,):
            raise StructureInvariantError("grid: log_dim and leaf_first must cover the top cells")
        if (self.log_dim < 0).any() or (self.log_dim > self.shift).any():
            raise StructureInvariantError("grid: a top cell's log_dim is outside 0..shift")
        if (self.fine_res > MAX_FINE_RES).any():
            raise StructureInvariantError(f"grid: fine resolution above {MAX_FINE_RES}")
        expect = np.concatenate([[0], np.cumsum(8 ** self.log_dim.astype(np.int64))])
        if not np.array_equal(self.leaf_first, expect):
            raise StructureInvariantError("grid: leaf_first is not the prefix sum of 8^log_dim")
        n = self.n_cells
        for name in ("cell_box", "cell_exit"):
            a = getattr(self, name)
            if a.dtype != INDEX or a.shape != (n, 6):
                raise StructureInvariantError(f"grid: {name} must be int32 (n_cells, 6)")
        ids = self.cell_of_leaf
        if ids.shape != (int(expect[-1]),) or (ids < 0).any() or (ids >= n).any():
            raise StructureInvariantError("grid: cell_of_leaf entry out of range")
        box = self.cell_box.astype(np.int64)
        leaf = self.leaf_boxes().astype(np.int64)
        mine = box[ids]
        if ((leaf[:, :3] < mine[:, :3]) | (leaf[:, 3:] > mine[:, 3:])).any():
            raise StructureInvariantError("grid: a leaf lies outside its cell's box")
        fine = self.fine_res.astype(np.int64)
        if (box[:, :3] < 0).any() or (box[:, 3:] > fine).any() or (box[:, 3:] <= box[:, :3]).any():
            raise StructureInvariantError("grid: a cell box is empty or outside the grid")
        volume = np.prod(box[:, 3:] - box[:, :3], axis=1)
        leaf_volume = np.bincount(ids, weights=np.prod(leaf[:, 3:] - leaf[:, :3], axis=1),
                                  minlength=n)  # fmt: skip
        if not np.array_equal(volume, leaf_volume.astype(np.int64)):
            raise StructureInvariantError("grid: a cell's leaves do not fill its box")
        ext = self.cell_exit.astype(np.int64)
        if (
            (ext[:, :3] > box[:, :3]).any()
            or (ext[:, 3:] < box[:, 3:]).any()
            or (ext[:, :3] < 0).any()
            or (ext[:, 3:] > fine).any()
        ):
            raise StructureInvariantError("grid: an expanded box does not hold its cell")
        _, cell_of_ref = validate_lists(self.cell_start, self.prim_index, n, self.n_prims)
        if triangles is not None:
            self._validate_geometry(triangles, leaf, cell_of_ref)

    def _validate_geometry(
        self, triangles: FloatArray, leaf: np.ndarray, cell_of_ref: np.ndarray
    ) -> None:
        t_lo = triangles.min(axis=1).astype(np.float64)
        t_hi = triangles.max(axis=1).astype(np.float64)
        if (t_lo < self.lo).any() or (t_hi > self.hi).any():
            raise StructureInvariantError("grid: a triangle lies outside the grid box")
        voxel = self.voxel_size
        box = self.cell_box[cell_of_ref].astype(np.float64)
        # The leaves' overlap margin is a fraction 2^-10 of their size plus ulps.
        slack = (box[:, 3:] - box[:, :3]) * voxel * 2.0**-9 + (
            np.abs(self.lo) + np.abs(self.hi)
        ) * 2.0**-20
        c_lo = self.lo + box[:, :3] * voxel - slack
        c_hi = self.lo + box[:, 3:] * voxel + slack
        p = self.prim_index
        bad = ((t_lo[p] > c_hi) | (t_hi[p] < c_lo)).any(axis=1)
        if bad.any():
            ref = int(np.argmax(bad))
            raise StructureInvariantError(
                f"grid: triangle {int(p[ref])} listed in cell {int(cell_of_ref[ref])} "
                "it does not overlap"
            )
        if self.n_cells > 4096:
            return
        # Expansion: every triangle listed by a leaf inside an expanded box is listed
        # by the box's cell (leaves list what overlaps them, so this covers the box).
        lists = [set(p[self.cell_start[c]:self.cell_start[c + 1]].tolist())
                 for c in range(self.n_cells)]  # fmt: skip
        ext = self.cell_exit.astype(np.int64)
        for c in range(self.n_cells):
            inside = ((leaf[:, :3] < ext[c, 3:]) & (leaf[:, 3:] > ext[c, :3])).all(axis=1)
            for other in np.unique(self.cell_of_leaf[inside]):
                if not lists[int(other)] <= lists[c]:
                    raise StructureInvariantError(
                        f"grid: cell {c}'s expanded box covers cell {int(other)}, "
                        "whose triangles it does not list"
                    )


def trace_layout(grid: IrregularGrid, hit_rows: FloatArray, mailbox: int) -> IrregularTrace:
    """Return the arrays the irregular grid traversal reads (see the module docstring)."""
    voxel = grid.voxel_size
    return IrregularTrace(
        box=interleaved_box(grid.lo, grid.hi),
        lo=grid.lo.copy(),
        voxel=voxel.astype(REAL),
        inv_voxel=(grid.fine_res / (grid.hi.astype(np.float64) - grid.lo)).astype(REAL),
        fine_res=grid.fine_res,
        top_res=grid.top_res.copy(),
        shift=np.array([grid.shift], INDEX),
        log_dim=grid.log_dim,
        leaf_first=grid.leaf_first,
        cell_of_leaf=grid.cell_of_leaf,
        exit_lo=np.ascontiguousarray(grid.cell_exit[:, :3]),
        exit_hi=np.ascontiguousarray(grid.cell_exit[:, 3:] - 1),
        cell_start=grid.cell_start,
        tri=gather_rows(hit_rows, grid.prim_index),
        tri_prim=grid.prim_index,
        mailbox=np.array([mailbox], INDEX),
    )
