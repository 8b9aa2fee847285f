"""The canonical uniform grid (``grid``) and the traversal layout derived from it.

Canonical layout (:class:`UniformGrid`, what every grid builder emits)
    A box ``[lo, hi]`` cut into ``res = (rx, ry, rz)`` equal cells of size
    ``(hi - lo) / res``; cell ``(x, y, z)`` has the linear index ``x + rx·(y + ry·z)``
    and lists the primitives ``prim_index[cell_start[c] : cell_start[c + 1]]``, in
    increasing id order, each once. A primitive is listed in every cell whose box,
    widened by :func:`cell_margin` on every side, it overlaps (exact triangle/box test),
    so a ray point that rounding places a hair into the neighbouring cell still finds
    the triangles of the cell it is really in. The box is the scene box widened by
    :data:`BOX_MARGIN` of its largest extent, so a scene flat along an axis still has
    cells of non-zero size.

Skip data (``skip_kind``, ``skip``)
    ``SKIP_NONE``: none (``skip`` is ``(n_cells, 0)``). ``SKIP_DISTANCE``: ``skip[c, 0]``
    is the chessboard distance from cell ``c`` to the nearest non-empty cell (0 for a
    non-empty cell), so the cube of cells within ``skip[c, 0] - 1`` of ``c`` is empty.
    ``SKIP_MACRO``: ``skip[c] = (x0, y0, z0, x1, y1, z1)`` is an empty box of cells
    containing ``c`` (inclusive bounds; the cell itself when it is not empty).
    ``SKIP_MIPMAP``: the cell's column of the occupancy mip-map, as bits: bit ``m`` of
    ``skip[c, 0]`` (read as uint16) is set when the level-``m`` block holding ``c``,
    the aligned ``2^m`` cells per axis (:func:`mip_block`, cut at the grid's end),
    holds a non-empty cell; levels ``0..``:func:`mip_levels_needed`, the last one
    covering the grid.

Traversal layout (:class:`GridTrace`, :func:`trace_layout`)
    The box interleaved as ``(lo_x, hi_x, lo_y, hi_y, lo_z, hi_z)`` (the root box of
    :mod:`rayaccel.trace.ray_setup`), the cell size and resolution, the cell ranges, the
    triangle rows copied in cell order (``tri (n_refs, 9)``) with their ids
    (``tri_prim``), the skip data and its kind (``(1,)`` int32), and the mailbox size.
    Bytes: 4 per cell, 4 per reference (canonical), 36 more per reference for the
    copied rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple, TypeVar

import numpy as np

from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import StructureInvariantError
from rayaccel.kernels.triangle_rows import gather_rows

SKIP_NONE = 0
SKIP_DISTANCE = 1
SKIP_MACRO = 2
SKIP_MIPMAP = 3
SKIP_NAMES = {
    SKIP_NONE: "none", SKIP_DISTANCE: "distance", SKIP_MACRO: "macro_regions",
    SKIP_MIPMAP: "mipmap",
}  # fmt: skip
#: Columns of ``skip`` per kind.
SKIP_COLUMNS = {SKIP_NONE: 0, SKIP_DISTANCE: 1, SKIP_MACRO: 6, SKIP_MIPMAP: 1}

#: The grid box is the scene box widened by this fraction of its largest extent.
BOX_MARGIN = 2.0**-16
#: Cells overlap their neighbours by this fraction of their size (plus coordinate ulps).
CELL_MARGIN = 2.0**-10
#: Largest resolution along one axis (macro regions store int16 cell coordinates).
MAX_RES_AXIS = 32767

CELL_BYTES = 4
REF_BYTES = 4
TRIANGLE_BYTES = 36


def mip_levels_needed(res: IntArray) -> int:
    """Return the mip-map's coarsest level: the first whose one block covers the grid (≤ 15)."""
    return int(np.ceil(np.log2(max(int(res.max()), 1))))


def mip_block(
    cell: np.ndarray, level: np.ndarray, res: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Return the inclusive bounds ``(lo, hi)`` of the aligned ``2^level`` block holding ``cell``.

    Works elementwise on integer arrays: ``lo = (cell >> level) << level`` and ``hi =
    lo + 2^level - 1`` cut at ``res - 1``.
    """
    lo = (cell >> level) << level
    return lo, np.minimum(lo + (1 << level) - 1, res - 1)


def cell_margin(lo: FloatArray, hi: FloatArray, res: IntArray) -> FloatArray:
    """Return the ``(3,)`` float32 widening of every cell box on each side.

    A fraction :data:`CELL_MARGIN` of the cell size plus a few float32 ulps of the
    coordinates, so rounding of ray points and cell planes (a few ulps) never puts a
    point outside the widened box of the cell the DDA is in.
    """
    lo64 = lo.astype(np.float64)
    hi64 = hi.astype(np.float64)
    size = (hi64 - lo64) / res
    return (size * CELL_MARGIN + (np.abs(lo64) + np.abs(hi64)) * 2.0**-21).astype(REAL)


class GridTrace(NamedTuple):
    """What the grid traversals read, as one kernel argument."""

    box: FloatArray
    lo: FloatArray
    size: FloatArray
    inv_size: FloatArray
    res: IntArray
    cell_start: IntArray
    tri: FloatArray
    tri_prim: IntArray
    skip: np.ndarray
    skip_kind: IntArray
    mailbox: IntArray


#: A grid traversal layout: a NamedTuple with a ``mailbox`` field.
Layout = TypeVar("Layout", bound=Any)


class UniformGridArrays(NamedTuple):
    """The canonical arrays as one kernel argument."""

    lo: FloatArray
    hi: FloatArray
    res: IntArray
    cell_start: IntArray
    prim_index: IntArray
    skip: np.ndarray


class ListedRefs:
    """``n_refs`` of a grid whose cells (or leaf cells) list ``prim_index`` (every grid layout)."""

    __slots__ = ()
    prim_index: IntArray

    @property
    def n_refs(self) -> int:
        """Number of cell/primitive references."""
        return int(self.prim_index.shape[0])


@dataclass(frozen=True, slots=True, eq=False)
class UniformGrid(ListedRefs):
    """Uniform grid; cell ``(x, y, z)`` is ``x + rx·(y + ry·z)`` (see the module docstring).

    Attributes
    ----------
    lo, hi : (3,) float32
        The grid box (the scene box widened by :data:`BOX_MARGIN`).
    res : (3,) int32
        Cells per axis, each in ``1..MAX_RES_AXIS``.
    cell_start : (n_cells + 1,) int32
        Cell ``c`` lists ``prim_index[cell_start[c]:cell_start[c + 1]]``.
    prim_index : (n_refs,) int32
        Primitive ids in cell order, increasing within a cell.
    skip_kind : int
        ``SKIP_NONE``, ``SKIP_DISTANCE``, ``SKIP_MACRO`` or ``SKIP_MIPMAP``.
    skip : (n_cells, SKIP_COLUMNS[skip_kind]) int16
        The skip data of ``skip_kind``.
    n_prims : int
        Number of primitives of the mesh.
    density : float
        The density λ (cells per primitive) the resolution was derived from.
    phase_ms : dict
        Build milliseconds by phase.
    """

    lo: FloatArray
    hi: FloatArray
    res: IntArray
    cell_start: IntArray
    prim_index: IntArray
    skip_kind: int
    skip: np.ndarray
    n_prims: int
    density: float = 5.0
    phase_ms: dict[str, float] = field(default_factory=dict)

    def arrays(self) -> UniformGridArrays:
        """Return the arrays as a NamedTuple kernels take as one argument."""
        return UniformGridArrays(
            self.lo, self.hi, self.res, self.cell_start, self.prim_index, self.skip
        )

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return int(self.cell_start.shape[0] - 1)

    def nbytes(self) -> int:
        """Return the canonical size in bytes (cell ranges, references, skip data)."""
        return int(self.cell_start.nbytes + self.prim_index.nbytes + self.skip.nbytes)

    def info(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> dict[str, Any]:
        """Return resolution, cells, empty fraction, references per primitive, bytes, phases.

        (``inner_cost`` and ``prim_cost`` are unused: a grid has no SAH cost.)
        """
        _ = (inner_cost, prim_cost)
        counts = np.diff(self.cell_start)
        return {
            "resolution": tuple(int(r) for r in self.res),
            "n_cells": self.n_cells,
            "n_refs": self.n_refs,
            "density": self.density,
            "empty_fraction": float(np.count_nonzero(counts == 0) / max(self.n_cells, 1)),
            "refs_per_prim": self.n_refs / max(self.n_prims, 1),
            "max_cell_refs": int(counts.max()) if counts.size else 0,
            "skip": SKIP_NAMES[self.skip_kind],
            "grid_bytes": self.nbytes(),
            "build_phase_ms": {k: round(v, 3) for k, v in self.phase_ms.items()},
        }

    def validate(self, triangles: FloatArray | None = None) -> None:
        """Check every invariant; raise :class:`StructureInvariantError` naming the first broken.

        Checks: dtypes and shapes; resolution in range; ``cell_start`` starts at 0, ends
        at ``n_refs`` and never decreases; ids in range, increasing within each cell, and
        every primitive listed; the skip data of its kind (distances and macro boxes
        empty and containing their cell, mip-map bits those of the occupancy); and, given
        ``triangles (F, 3, 3)``, every triangle inside the grid box and every listed
        triangle's box overlapping its widened cell.
        """
        validate_box(self.lo, self.hi)
        if self.res.dtype != INDEX or self.res.shape != (3,):
            raise StructureInvariantError("grid: res must be int32 (3,)")
        if (self.res < 1).any() or (self.res > MAX_RES_AXIS).any():
            raise StructureInvariantError(f"grid: resolution {self.res} outside 1..{MAX_RES_AXIS}")
        n_cells = int(np.prod(self.res.astype(np.int64)))
        counts, cell_of_ref = validate_lists(
            self.cell_start, self.prim_index, n_cells, self.n_prims
        )
        self._validate_skip(counts)
        if triangles is not None:
            self._validate_geometry(triangles, cell_of_ref)

    def _validate_skip(self, counts: IntArray) -> None:
        columns = SKIP_COLUMNS.get(self.skip_kind)
        if columns is None:
            raise StructureInvariantError(f"grid: unknown skip kind {self.skip_kind}")
        if self.skip.dtype != np.int16 or self.skip.shape != (self.n_cells, columns):
            raise StructureInvariantError("grid: skip must be int16 (n_cells, columns of kind)")
        occupied = (counts > 0).reshape(tuple(self.res[::-1]))  # [z, y, x]
        if self.skip_kind == SKIP_DISTANCE:
            dist = self.skip[:, 0].reshape(occupied.shape)
            if (dist[occupied] != 0).any() or (dist[~occupied] < 1).any():
                raise StructureInvariantError("grid: distance 0 iff the cell is non-empty")
            if occupied.size <= 4096:
                _check_distance_brute(occupied, dist)
        elif self.skip_kind in (SKIP_MACRO, SKIP_MIPMAP):
            cells = np.arange(self.n_cells, dtype=np.int64)
            rx, ry = int(self.res[0]), int(self.res[1])
            xyz = np.stack([cells % rx, (cells // rx) % ry, cells // (rx * ry)], axis=1)
            table = _summed_volume(occupied)
            empty = counts == 0
            if self.skip_kind == SKIP_MACRO:
                box = self.skip.astype(np.int64)
                if ((box[:, :3] > xyz) | (box[:, 3:] < xyz) | (box[:, :3] < 0)).any() or (
                    box[:, 3:] >= self.res
                ).any():
                    raise StructureInvariantError("grid: a macro region does not contain its cell")
                name = "macro region"
            else:
                box = self._validate_mip_levels(xyz, empty, table)
                name = "mip-map block"
            if (_box_sum(table, box)[empty] != 0).any():
                raise StructureInvariantError(f"grid: a {name} holds a non-empty cell")
            if (box[~empty, :3] != xyz[~empty]).any() or (box[~empty, 3:] != xyz[~empty]).any():
                raise StructureInvariantError(f"grid: a non-empty cell's {name} is not itself")

    def _validate_mip_levels(
        self, xyz: np.ndarray, empty: np.ndarray, table: np.ndarray
    ) -> np.ndarray:
        """Check every cell's pyramid bits; return the coarsest empty block of each cell."""
        bits = self.skip[:, 0].astype(np.int64) & 0xFFFF
        top = mip_levels_needed(self.res)
        res = self.res.astype(np.int64)
        expect = np.zeros_like(bits)
        for m in range(top + 1):
            lo, hi = mip_block(xyz, np.full((1, 1), m), res)
            full = _box_sum(table, np.concatenate([lo, hi], axis=1)) > 0
            expect |= full.astype(np.int64) << m
        if not np.array_equal(bits, expect):
            raise StructureInvariantError("grid: mip-map bits differ from the occupancy")
        # The climb's level: the last of the clear bits from bit 0 (0 for a non-empty cell).
        climb = np.zeros_like(bits)
        for m in range(1, top + 1):
            climb = np.where((climb == m - 1) & empty & ((bits >> m) & 1 == 0), m, climb)
        lo, hi = mip_block(xyz, climb[:, None], res)
        return np.concatenate([lo, hi], axis=1)

    def _validate_geometry(self, triangles: FloatArray, cell_of_ref: np.ndarray) -> None:
        t_lo = triangles.min(axis=1)
        t_hi = triangles.max(axis=1)
        if (t_lo < self.lo).any() or (t_hi > self.hi).any():
            raise StructureInvariantError("grid: a triangle lies outside the grid box")
        if self.n_refs == 0:
            return
        size = (self.hi.astype(np.float64) - self.lo) / self.res
        margin = cell_margin(self.lo, self.hi, self.res).astype(np.float64) * 2
        rx, ry = int(self.res[0]), int(self.res[1])
        xyz = np.stack(
            [cell_of_ref % rx, (cell_of_ref // rx) % ry, cell_of_ref // (rx * ry)], axis=1
        )
        c_lo = self.lo + xyz * size - margin
        c_hi = self.lo + (xyz + 1) * size + margin
        p_lo = t_lo[self.prim_index]
        p_hi = t_hi[self.prim_index]
        bad = ((p_lo > c_hi) | (p_hi < c_lo)).any(axis=1)
        if bad.any():
            ref = int(np.argmax(bad))
            raise StructureInvariantError(
                f"grid: triangle {int(self.prim_index[ref])} listed in cell "
                f"{int(cell_of_ref[ref])} it does not overlap"
            )


def validate_lists(
    starts: IntArray,
    prim_index: IntArray,
    n_units: int,
    n_prims: int,
    unit: str = "cell",
    starts_name: str = "cell_start",
) -> tuple[IntArray, np.ndarray]:
    """Check ``n_units`` ranges ``starts`` into ``prim_index``; return counts and owners.

    Checks: both C-contiguous int32 ``(n,)``, ``n_units + 1`` starts rising from 0 to
    the number of references, ids in ``[0, n_prims)``, increasing within each range,
    and every primitive listed. Returns each range's length and, per reference, the
    index of its range (int64). Shared by the uniform, two-level and irregular grids.
    """
    for name, a in ((starts_name, starts), ("prim_index", prim_index)):
        if a.dtype != INDEX or a.ndim != 1 or not a.flags.c_contiguous:
            raise StructureInvariantError(f"grid: {name} must be C-contiguous int32 (n,)")
    if starts.shape[0] != n_units + 1:
        raise StructureInvariantError(f"grid: {starts_name} must have n_{unit}s + 1 entries")
    n_refs = prim_index.shape[0]
    counts = np.diff(starts)
    if starts[0] != 0 or starts[-1] != n_refs or (counts < 0).any():
        raise StructureInvariantError(f"grid: {starts_name} must rise from 0 to n_refs")
    if n_refs and (prim_index.min() < 0 or prim_index.max() >= n_prims):
        raise StructureInvariantError("grid: prim_index entry out of range [0, n_prims)")
    owner = np.repeat(np.arange(n_units, dtype=np.int64), counts)
    if n_refs > 1 and ((owner[1:] == owner[:-1]) & (prim_index[1:] <= prim_index[:-1])).any():
        raise StructureInvariantError(f"grid: ids not increasing within a {unit}")
    listed = np.zeros(n_prims, dtype=bool)
    listed[prim_index] = True
    if not listed.all():
        raise StructureInvariantError(f"grid: primitive {int(np.argmin(listed))} in no {unit}")
    return counts, owner


def interleaved_box(lo: FloatArray, hi: FloatArray) -> FloatArray:
    """Return the box as ``(lo_x, hi_x, lo_y, hi_y, lo_z, hi_z)`` float32 (the root box)."""
    return np.array([lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]], REAL)


def validate_box(lo: FloatArray, hi: FloatArray) -> None:
    """Check a grid box: finite float32 ``(3,)`` corners with ``lo < hi`` on every axis."""
    for name, a in (("lo", lo), ("hi", hi)):
        if a.dtype != REAL or a.shape != (3,) or not np.isfinite(a).all():
            raise StructureInvariantError(f"grid: {name} must be finite float32 (3,)")
    if not (lo < hi).all():
        raise StructureInvariantError("grid: box has lo >= hi on some axis")


def _summed_volume(occupied: np.ndarray) -> np.ndarray:
    """Return the ``(z+1, y+1, x+1)`` int64 summed-volume table of an occupancy grid."""
    table = np.zeros(tuple(s + 1 for s in occupied.shape), dtype=np.int64)
    table[1:, 1:, 1:] = occupied.astype(np.int64).cumsum(0).cumsum(1).cumsum(2)
    return table


def _box_sum(table: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Return the occupied cells in each inclusive box ``(x0, y0, z0, x1, y1, z1)``."""
    x0, y0, z0 = box[:, 0], box[:, 1], box[:, 2]
    x1, y1, z1 = box[:, 3] + 1, box[:, 4] + 1, box[:, 5] + 1
    sums: np.ndarray = (
        table[z1, y1, x1] - table[z0, y1, x1] - table[z1, y0, x1] - table[z1, y1, x0]
        + table[z0, y0, x1] + table[z0, y1, x0] + table[z1, y0, x0] - table[z0, y0, x0]
    )  # fmt: skip
    return sums


def _check_distance_brute(occupied: np.ndarray, dist: np.ndarray) -> None:
    """Check a small distance field against its definition (brute force)."""
    full = np.argwhere(occupied)
    cells = np.argwhere(np.ones_like(occupied))
    if full.size == 0:
        return
    cheb = np.abs(cells[:, None, :] - full[None, :, :]).max(axis=2).min(axis=1)
    expect = np.minimum(cheb, np.iinfo(np.int16).max).reshape(occupied.shape)
    if not np.array_equal(expect, dist):
        raise StructureInvariantError("grid: distance field differs from its definition")


def trace_layout(grid: UniformGrid, hit_rows: FloatArray, mailbox: int) -> GridTrace:
    """Return the arrays the grid traversals read (see the module docstring).

    ``hit_rows`` are the mesh's ``(F, 9)`` rows (:meth:`TriangleMesh.hit_rows`);
    ``mailbox`` the per-ray mailbox size (0 disables it).
    """
    rows = gather_rows(hit_rows, grid.prim_index)
    # The cell planes in the rows' precision: float64 rays compute lo + k·size in float64
    # from the same float32 values (see the module docstring).
    real = hit_rows.dtype
    return with_mailbox(
        GridTrace(
            box=interleaved_box(grid.lo, grid.hi),
            lo=grid.lo.astype(real),
            size=((grid.hi - grid.lo) / grid.res).astype(REAL).astype(real),
            inv_size=(grid.res / (grid.hi - grid.lo)).astype(REAL).astype(real),
            res=grid.res.copy(),
            cell_start=grid.cell_start,
            tri=rows,
            tri_prim=grid.prim_index,
            skip=grid.skip,
            skip_kind=np.array([grid.skip_kind], dtype=INDEX),
            mailbox=np.zeros(1, dtype=INDEX),
        ),
        mailbox,
    )


def with_mailbox(layout: Layout, mailbox: int) -> Layout:
    """Return a grid traversal layout with its mailbox size set (a ``(1,)`` int32 array)."""
    updated: Layout = layout._replace(mailbox=np.array([mailbox], dtype=INDEX))
    return updated
