"""Two-level grid construction (Kalojanov, Billeter, Slusallek 2011).

"Two-Level Grids for Ray Tracing on GPUs" (CGF 30(2), Eurographics 2011):

1. The top level is a uniform grid of density λ1 (default 1/16, the value in the
   authors' released code) built as ``grid.uniform`` does (count, prefix sum, fill
   with the exact overlap test, sort, cell ranges).
2. Each top cell gets its own resolution from its reference count ``n_c`` and its box
   with the leaf density λ2 (default 1.2): Slusallek's formula over the top cell
   (:func:`~rayaccel.grid.builders.uniform.grid_resolution`); an empty top cell gets
   one empty leaf. A prefix sum of the sub-grid sizes gives each top cell its first
   leaf cell.
3. *One sort for the whole leaf level*: every (top cell, primitive) pair of the top
   level emits a pair (global leaf cell, primitive) for each leaf cell of that top
   cell it overlaps (counted, prefix-summed, filled, exact test), and a single radix
   sort over all of them yields every leaf's range.

``skip="distance"`` adds a chessboard distance field over the *top* cells, the thesis's
own proposal (empty-space skipping on the two-level grid), read by ``grid.skip``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel._variant import register
from rayaccel.dtypes import INDEX, REAL
from rayaccel.errors import InvalidInputError
from rayaccel.grid.builders.skip import add_skip
from rayaccel.grid.builders.uniform import (
    MASK_BITS,
    PRIM_CHUNK,
    UniformGridOptions,
    build_uniform,
    sort_pairs,
)
from rayaccel.grid.layouts.two_level import TwoLevelGrid
from rayaccel.grid.layouts.uniform import MAX_RES_AXIS, SKIP_DISTANCE, cell_margin
from rayaccel.kernels.overlap import triangle_box_overlap
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class TwoLevelOptions:
    """Options of :func:`build_two_level_grid`.

    Attributes
    ----------
    top_density : float
        λ1, top cells per primitive (0 < λ1 <= 1024); 1/16 in Kalojanov's code.
    leaf_density : float
        λ2, leaf cells per reference of a top cell (0 < λ2 <= 1024); 1.2 in his code.
    skip : {"none", "distance"}
        Skip data over empty top cells (``grid.skip`` reads it).
    max_cells : int
        Largest number of top cells, and of leaf cells (as ``grid.uniform``).
    max_refs, max_refs_per_prim
        The reference budget of the top level (as ``grid.uniform``) and of the leaf
        level, whose sub-grids are coarsened to fit it (:func:`_cells_to_coarsen`).
    """

    top_density: float = 1.0 / 16.0
    leaf_density: float = 1.2
    skip: str = "none"
    max_cells: int = 2**26
    max_refs: int = 2**26
    max_refs_per_prim: float = 16.0

    def __post_init__(self) -> None:
        for name in ("top_density", "leaf_density"):
            value = getattr(self, name)
            if not (0.0 < value <= 1024.0):
                raise InvalidInputError(f"{name}: expected 0 < λ <= 1024, got {value}")
        if self.skip not in ("none", "distance"):
            raise InvalidInputError(f"skip: expected 'none' or 'distance', got {self.skip!r}")
        UniformGridOptions(1.0, self.max_cells, self.max_refs, self.max_refs_per_prim)


def sub_resolutions(size: np.ndarray, counts: np.ndarray, density: float) -> np.ndarray:
    """Return ``(n_top, 3)`` int32 leaf resolutions: Slusallek's formula per top cell."""
    e = np.asarray(size, dtype=np.float64)
    wanted = np.maximum(density * counts.astype(np.float64), 1.0)
    free = np.ones((counts.shape[0], 3), dtype=bool)
    res = np.ones((counts.shape[0], 3), dtype=np.float64)
    for _ in range(3):
        k = free.sum(axis=1)
        volume = np.prod(np.where(free, e, 1.0), axis=1)
        scale = (wanted / volume) ** (1.0 / np.maximum(k, 1))
        res = np.where(free, e * scale[:, None], 1.0)
        small = free & (res < 1.0)
        if not small.any():
            break
        free &= ~small
    out = np.clip(np.floor(res + 0.5), 1, MAX_RES_AXIS)
    out[counts == 0] = 1
    return out.astype(INDEX)


#: ``_leaf_pairs`` modes: count overlapped leaves, write the pairs, or bound the count.
COUNT = 0
FILL = 1
BOUND = 2
#: Rounds of halving sub-grid resolutions before the leaf level fits its reference budget.
MAX_SHRINK_ROUNDS = 64


@cpu_kernel(parallel=True)
def _leaf_pairs(
    tri, top_of_ref, top_prim, lo, size, res, sub_res, leaf_first, leaf_size, margin,
    counts, masks, offsets, keys, values, mode,
):  # fmt: skip
    """Count, write or bound the leaf cells each top reference overlaps.

    ``mode`` COUNT: exact counts into ``counts`` and, for a reference with at most
    ``MASK_BITS`` candidate leaves, which of them it overlaps into ``masks`` (as the
    uniform grid's pair pass does); FILL: pairs written from ``offsets``, from the
    mask, or with no test when the count says every candidate leaf overlaps, else
    tested again; BOUND: the number of candidate leaves (the triangle's box in leaf
    cells) into ``counts``, no test.
    """
    fill = mode == FILL
    n = top_prim.shape[0]
    n_chunks = (n + PRIM_CHUNK - 1) // PRIM_CHUNK
    rx = res[0]
    ry = res[1]
    for ch in prange(n_chunks):
        b_lo = np.empty(3, dtype=np.float32)
        b_hi = np.empty(3, dtype=np.float32)
        first = np.empty(3, dtype=np.int64)
        last = np.empty(3, dtype=np.int64)
        top_lo = np.empty(3, dtype=np.float32)
        for i in range(ch * PRIM_CHUNK, min(n, (ch + 1) * PRIM_CHUNK)):
            c = top_of_ref[i]
            p = top_prim[i]
            cx = c % rx
            cy = (c // rx) % ry
            cz = c // (rx * ry)
            top_lo[0] = lo[0] + np.float32(cx) * size[0]
            top_lo[1] = lo[1] + np.float32(cy) * size[1]
            top_lo[2] = lo[2] + np.float32(cz) * size[2]
            single = True
            for a in range(3):
                t_lo = min(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
                t_hi = max(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
                inv = 1.0 / np.float64(leaf_size[c, a])
                m2 = 2.0 * np.float64(margin[c, a])
                j0 = np.int64(np.floor((np.float64(t_lo) - m2 - top_lo[a]) * inv))
                j1 = np.int64(np.floor((np.float64(t_hi) + m2 - top_lo[a]) * inv))
                r = np.int64(sub_res[c, a])
                first[a] = min(max(j0, 0), r - 1)
                last[a] = min(max(j1, 0), r - 1)
                if first[a] != last[a] or j0 < 0 or j1 >= r:
                    single = False
            lrx = np.int64(sub_res[c, 0])
            lry = np.int64(sub_res[c, 1])
            slot = offsets[i] if fill else 0
            if single:
                if fill:
                    keys[slot] = leaf_first[c] + first[0] + lrx * (first[1] + lry * first[2])
                    values[slot] = p
                else:
                    counts[i] = 1
                continue
            n_cand = (last[0] - first[0] + 1) * (last[1] - first[1] + 1) * (last[2] - first[2] + 1)
            if mode == BOUND:
                counts[i] = n_cand
                continue
            masked = n_cand <= MASK_BITS
            every = fill and counts[i] == n_cand
            bits = masks[i] if fill and masked else np.int64(0)
            k = 0
            for z in range(first[2], last[2] + 1):
                b_lo[2] = top_lo[2] + np.float32(z) * leaf_size[c, 2] - margin[c, 2]
                b_hi[2] = top_lo[2] + np.float32(z + 1) * leaf_size[c, 2] + margin[c, 2]
                for y in range(first[1], last[1] + 1):
                    b_lo[1] = top_lo[1] + np.float32(y) * leaf_size[c, 1] - margin[c, 1]
                    b_hi[1] = top_lo[1] + np.float32(y + 1) * leaf_size[c, 1] + margin[c, 1]
                    for x in range(first[0], last[0] + 1):
                        if fill and masked:
                            hit = (bits >> k) & 1 == 1
                        elif every:
                            hit = True
                        else:
                            b_lo[0] = top_lo[0] + np.float32(x) * leaf_size[c, 0]
                            b_lo[0] -= margin[c, 0]
                            b_hi[0] = top_lo[0] + np.float32(x + 1) * leaf_size[c, 0]
                            b_hi[0] += margin[c, 0]
                            hit = triangle_box_overlap(tri, p, b_lo, b_hi)
                            if masked and hit:
                                bits |= np.int64(1) << k
                        if hit:
                            if fill:
                                keys[slot] = leaf_first[c] + x + lrx * (y + lry * z)
                                values[slot] = p
                            slot += 1
                        k += 1
            if not fill:
                counts[i] = slot
                if masked:
                    masks[i] = bits


def _leaf_geometry(top: Any, size: np.ndarray, sub_res: np.ndarray) -> tuple[Any, Any]:
    """Return the leaf cell sizes and overlap margins of every top cell's sub-grid."""
    leaf_size = (size[None, :] / sub_res).astype(REAL)
    coords = (np.abs(top.lo.astype(np.float64)) + np.abs(top.hi)) * 2.0**-21
    margin = np.minimum(
        (leaf_size * (2.0**-10) + coords).astype(REAL), cell_margin(top.lo, top.hi, top.res)
    )
    return leaf_size, margin


def _cells_to_coarsen(
    top_of_ref: np.ndarray,
    bound: np.ndarray,
    counts: np.ndarray,
    sub_res: np.ndarray,
    budget: int,
    opts: TwoLevelOptions,
) -> np.ndarray | None:
    """Return the top cells whose sub-grids to halve, or None when the leaf level fits.

    λ2 sizes a sub-grid by its reference count alone, so a top cell holding many large
    or identical overlapping triangles (100k copies of one triangle) would list each
    in most of its leaves: billions of pairs. While the upper bound on the pairs
    (each reference's box in leaf cells) exceeds the budget (``max_refs``, and
    ``max_refs_per_prim`` per primitive), the cells whose references average more than
    ``max_refs_per_prim`` leaves are halved, or failing those every cell whose
    references span several leaves; at resolution 1 a cell lists each reference
    once, within the top level's own budget.
    """
    if int(bound.sum()) <= budget:
        return None
    per_cell = np.bincount(top_of_ref, weights=bound, minlength=counts.shape[0])
    spread = per_cell / np.maximum(counts, 1)
    can = (sub_res > 1).any(axis=1)
    shrink = can & (spread > opts.max_refs_per_prim)
    if not shrink.any():
        shrink = can & (spread > 1.0)
    return shrink if shrink.any() else None


def top_level(
    mesh: TriangleMesh, opts: Any, key: str
) -> tuple[Any, np.ndarray, dict[str, float], np.ndarray]:
    """Build the top grid of density ``opts.top_density`` (two-level and irregular grids).

    Returns the grid, the triangles ``(F, 3, 3)``, the phases (``top_*``) and each top
    cell's leaf resolution by ``opts.leaf_density`` (:func:`sub_resolutions`).
    """
    top_opts = UniformGridOptions(
        opts.top_density, opts.max_cells, opts.max_refs, opts.max_refs_per_prim
    )
    top, tri = build_uniform(mesh, top_opts, key)
    phases = {f"top_{k}": v for k, v in top.phase_ms.items()}
    size = ((top.hi - top.lo) / top.res).astype(REAL)
    sub_res = sub_resolutions(size, np.diff(top.cell_start), opts.leaf_density)
    return top, tri, phases, sub_res


class LeafLevel(NamedTuple):
    """The leaf level of a two-level grid: sub-grids, their cell ranges and references."""

    sub_res: np.ndarray
    leaf_first: np.ndarray
    leaf_size: np.ndarray
    leaf_start: np.ndarray
    prim_index: np.ndarray


def leaf_level(
    top: Any,
    tri: np.ndarray,
    sub_res: np.ndarray,
    opts: Any,
    asked: str,
    phases: dict[str, float],
) -> LeafLevel:
    """Bin every top cell's references into its sub-grid of ``sub_res`` cells, one sort.

    Sub-grids are first halved where the references would exceed the budget
    (:func:`_cells_to_coarsen`); ``opts`` gives ``max_cells``, ``max_refs`` and
    ``max_refs_per_prim``; ``asked`` names what asked for the cells in the error;
    ``phases`` receives build milliseconds. Used by ``grid.two_level`` and
    ``grid.irregular``.
    """
    t0 = time.perf_counter()
    sub_res = sub_res.copy()
    n_top = top.n_cells
    counts = np.diff(top.cell_start)
    size = ((top.hi - top.lo) / top.res).astype(REAL)
    top_of_ref = np.repeat(np.arange(n_top, dtype=np.int64), counts)
    n_ref = top.n_refs
    offsets = np.empty(n_ref, dtype=np.int64)
    no_masks = np.empty(0, dtype=np.int64)
    budget = min(opts.max_refs, max(n_ref, int(opts.max_refs_per_prim * top.n_prims)))
    for _ in range(MAX_SHRINK_ROUNDS):
        leaf_size, margin = _leaf_geometry(top, size, sub_res)
        args = (tri, top_of_ref, top.prim_index, top.lo, size, top.res, sub_res,
                np.zeros(n_top + 1, INDEX), leaf_size, margin, offsets)  # fmt: skip
        _leaf_pairs(*args, no_masks, offsets, np.empty(0, np.int64), np.empty(0, np.int32), BOUND)
        shrink = _cells_to_coarsen(top_of_ref, offsets, counts, sub_res, budget, opts)
        if shrink is None:
            break
        sub_res[shrink] = np.maximum(sub_res[shrink] // 2, 1)
    n_sub = np.prod(sub_res.astype(np.int64), axis=1)
    leaf_first64 = np.concatenate([[0], np.cumsum(n_sub)])
    n_leaves = int(leaf_first64[-1])
    if n_leaves > opts.max_cells:
        raise InvalidInputError(
            f"{asked} asks for {n_leaves} leaf cells, more than "
            f"max_cells={opts.max_cells}; lower it or raise max_cells"
        )
    leaf_first = leaf_first64.astype(INDEX)
    leaf_size, margin = _leaf_geometry(top, size, sub_res)
    phases["sub_res"] = (time.perf_counter() - t0) * 1e3
    t1 = time.perf_counter()
    args = (tri, top_of_ref, top.prim_index, top.lo, size, top.res, sub_res, leaf_first,
            leaf_size, margin, offsets)  # fmt: skip
    masks = np.empty(n_ref, dtype=np.int64)
    _leaf_pairs(*args, masks, offsets, np.empty(0, np.int64), np.empty(0, np.int32), COUNT)
    total = np.cumsum(offsets)
    n_pairs = int(total[-1]) if n_ref else 0
    if n_pairs > 2**31 - 1:
        raise InvalidInputError(f"{asked}: {n_pairs} leaf references exceed int32")
    starts = np.empty(n_ref, dtype=np.int64)
    if n_ref:
        starts[0] = 0
        starts[1:] = total[:-1]
    keys = np.empty(n_pairs, dtype=np.int64)
    values = np.empty(n_pairs, dtype=np.int32)
    _leaf_pairs(*args, masks, starts, keys, values, FILL)
    phases["leaf_pairs"] = (time.perf_counter() - t1) * 1e3
    leaf_start, values = sort_pairs(keys, values, n_leaves, phases, "leaf_")
    return LeafLevel(
        sub_res, leaf_first, leaf_size, leaf_start, np.ascontiguousarray(values, dtype=INDEX)
    )


@register(
    "builder",
    "grid.two_level",
    options=TwoLevelOptions,
    summary="two-level grid: λ1 top grid, per-cell λ2 sub-grids, one sort for all leaves",
    reference="Kalojanov, Billeter, Slusallek 2011, Two-Level Grids for Ray Tracing on GPUs",
)
def build_two_level_grid(
    mesh: TriangleMesh, options: TwoLevelOptions | None = None
) -> TwoLevelGrid:
    """Build a two-level grid over ``mesh``'s triangles (see the module docstring).

    Raises
    ------
    InvalidInputError
        A density asks for more cells than ``max_cells`` or memory allows.
    """
    opts = options or TwoLevelOptions()
    top, tri, phases, sub_res = top_level(mesh, opts, "grid.two_level")
    asked = f"grid.two_level: leaf density λ2={opts.leaf_density}"
    leaves = leaf_level(top, tri, sub_res, opts, asked, phases)
    if opts.skip == "distance":
        top = add_skip(top, SKIP_DISTANCE, phases)
    return TwoLevelGrid(
        top=top, **leaves._asdict(), n_prims=top.n_prims,
        leaf_density=float(opts.leaf_density), phase_ms=phases,
    )  # fmt: skip
