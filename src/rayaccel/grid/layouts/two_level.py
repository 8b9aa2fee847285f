"""The two-level grid (Kalojanov, Billeter, Slusallek 2011) and its traversal layout.

Canonical layout (:class:`TwoLevelGrid`)
    A top-level :class:`~rayaccel.grid.layouts.uniform.UniformGrid` (its cell ranges
    list the primitives of each top cell; its skip data, if any, covers empty top
    cells) and, per top cell ``c``, a sub-grid of ``sub_res[c]`` leaf cells over the top
    cell's box, whose leaf cells are ``leaf_first[c] .. leaf_first[c + 1]`` (same
    ``x + rx·(y + ry·z)`` order inside). Leaf cell ``l`` lists
    ``prim_index[leaf_start[l]:leaf_start[l + 1]]``. Leaf cell ``j`` of top cell ``c``
    on axis ``a`` spans ``top_lo_a + j·leaf_size[c, a]`` onwards, with ``top_lo_a =
    lo_a + c_a·size_a`` computed in float32 exactly as the traversal does. Leaf cells
    overlap their neighbours by :func:`~rayaccel.grid.layouts.uniform.cell_margin` of
    the leaf size (less than the top cell's margin, so a top cell lists every triangle
    its leaves do). Empty top cells get one empty leaf.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import StructureInvariantError
from rayaccel.grid.layouts.uniform import (
    ListedRefs,
    UniformGrid,
    interleaved_box,
    validate_lists,
)
from rayaccel.kernels.triangle_rows import gather_rows


class TwoLevelTrace(NamedTuple):
    """What the two-level DDA reads, as one kernel argument."""

    box: FloatArray
    lo: FloatArray
    size: FloatArray
    inv_size: FloatArray
    res: IntArray
    cell_start: IntArray
    skip: np.ndarray
    skip_kind: IntArray
    sub_res: IntArray
    leaf_first: IntArray
    leaf_size: FloatArray
    leaf_inv: FloatArray
    leaf_start: IntArray
    tri: FloatArray
    tri_prim: IntArray
    mailbox: IntArray


@dataclass(frozen=True, slots=True, eq=False)
class TwoLevelGrid(ListedRefs):
    """Two-level grid (see the module docstring).

    Attributes
    ----------
    top : UniformGrid
        The top level (density λ1), possibly with skip data over its empty cells.
    sub_res : (n_top, 3) int32
        Leaf cells per axis of each top cell.
    leaf_first : (n_top + 1,) int32
        First leaf cell of each top cell.
    leaf_size : (n_top, 3) float32
        Leaf cell size of each top cell.
    leaf_start : (n_leaves + 1,) int32
        Leaf cell ranges into ``prim_index``.
    prim_index : (n_leaf_refs,) int32
        Primitive ids in leaf order, increasing within a leaf.
    n_prims : int
    leaf_density : float
        λ2.
    phase_ms : dict
        Build milliseconds by phase.
    """

    top: UniformGrid
    sub_res: IntArray
    leaf_first: IntArray
    leaf_size: FloatArray
    leaf_start: IntArray
    prim_index: IntArray
    n_prims: int
    leaf_density: float = 1.2
    phase_ms: dict[str, float] = field(default_factory=dict)

    @property
    def skip_kind(self) -> int:
        """Skip data kind of the top level."""
        return self.top.skip_kind

    @property
    def n_leaves(self) -> int:
        """Number of leaf cells."""
        return int(self.leaf_start.shape[0] - 1)

    def nbytes(self) -> int:
        """Return the canonical size in bytes (both levels)."""
        return int(
            self.top.nbytes() + self.sub_res.nbytes + self.leaf_first.nbytes
            + self.leaf_size.nbytes + self.leaf_start.nbytes + self.prim_index.nbytes
        )  # fmt: skip

    def info(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> dict[str, Any]:
        """Return both levels' resolution and cells, empty fraction, references, phases."""
        top = self.top.info(inner_cost, prim_cost)
        counts = np.diff(self.leaf_start)
        return {
            "resolution": top["resolution"],
            "n_cells": top["n_cells"],
            "n_leaf_cells": self.n_leaves,
            "n_refs": self.n_refs,
            "density": top["density"],
            "leaf_density": self.leaf_density,
            "empty_fraction": float(np.count_nonzero(counts == 0) / max(self.n_leaves, 1)),
            "top_empty_fraction": top["empty_fraction"],
            "refs_per_prim": self.n_refs / max(self.n_prims, 1),
            "max_cell_refs": int(counts.max()) if counts.size else 0,
            "skip": top["skip"],
            "grid_bytes": self.nbytes(),
            "build_phase_ms": {k: round(v, 3) for k, v in self.phase_ms.items()},
        }

    def validate(self, triangles: FloatArray | None = None) -> None:
        """Check both levels; raise :class:`StructureInvariantError` naming the first broken.

        The top level as a uniform grid; sub-resolutions positive; ``leaf_first`` the
        prefix sum of the sub-grid sizes; leaf ranges rising from 0 to ``n_refs``; ids
        in range, increasing within a leaf, each leaf's ids listed by its top cell; every
        primitive in some leaf.
        """
        self.top.validate(triangles)
        n_top = self.top.n_cells
        if self.sub_res.dtype != INDEX or self.sub_res.shape != (n_top, 3):
            raise StructureInvariantError("grid: sub_res must be int32 (n_top, 3)")
        if (self.sub_res < 1).any():
            raise StructureInvariantError("grid: a sub-grid has no cells")
        if self.leaf_size.dtype != REAL or self.leaf_size.shape != (n_top, 3):
            raise StructureInvariantError("grid: leaf_size must be float32 (n_top, 3)")
        sizes = np.prod(self.sub_res.astype(np.int64), axis=1)
        expect = np.concatenate([[0], np.cumsum(sizes)])
        if self.leaf_first.dtype != INDEX or not np.array_equal(self.leaf_first, expect):
            raise StructureInvariantError("grid: leaf_first is not the prefix sum of sub-grids")
        _, leaf_of_ref = validate_lists(
            self.leaf_start, self.prim_index, int(expect[-1]), self.n_prims, "leaf", "leaf_start"
        )
        # Each leaf's ids are listed by its top cell.
        top_of_leaf = np.repeat(np.arange(n_top, dtype=np.int64), sizes)
        top_counts = np.diff(self.top.cell_start)
        top_of_ref = np.repeat(np.arange(n_top, dtype=np.int64), top_counts)
        top_pairs = top_of_ref * self.n_prims + self.top.prim_index
        leaf_pairs = top_of_leaf[leaf_of_ref] * self.n_prims + self.prim_index
        if not np.isin(leaf_pairs, top_pairs).all():
            raise StructureInvariantError("grid: a leaf lists a primitive its top cell does not")


def two_level_trace_layout(grid: TwoLevelGrid, hit_rows: FloatArray) -> TwoLevelTrace:
    """Return the arrays the two-level DDA reads (triangle rows copied in leaf order)."""
    top = grid.top
    return TwoLevelTrace(
        box=interleaved_box(top.lo, top.hi),
        lo=top.lo.copy(),
        size=((top.hi - top.lo) / top.res).astype(REAL),
        inv_size=(top.res / (top.hi - top.lo)).astype(REAL),
        res=top.res.copy(),
        cell_start=top.cell_start,
        skip=top.skip,
        skip_kind=np.array([top.skip_kind], dtype=INDEX),
        sub_res=grid.sub_res,
        leaf_first=grid.leaf_first,
        leaf_size=grid.leaf_size,
        leaf_inv=(1.0 / grid.leaf_size).astype(REAL),
        leaf_start=grid.leaf_start,
        tri=gather_rows(hit_rows, grid.prim_index),
        tri_prim=grid.prim_index,
        mailbox=np.zeros(1, dtype=INDEX),
    )
