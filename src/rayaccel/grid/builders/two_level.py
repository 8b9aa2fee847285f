"""Two-level grid construction (Kalojanov, Billeter, Slusallek 2011).

"Two-Level Grids for Ray Tracing on GPUs" (CGF 30(2), Eurographics 2011):

1. The top level is a uniform grid of density λ1 (default 1/16, the value in the
   authors' released code) built as ``grid.uniform`` does (count, prefix sum, fill
   with the exact overlap test, sort, cell ranges).
2. Each top cell gets its own resolution from its reference count ``n_c`` and its box
   with the leaf density λ2 (default 1.2): Slusallek's formula over the top cell
   (:func:`~rayaccel.grid.builders.uniform.resolutions`); an empty top cell gets
   one empty leaf. A prefix sum of the sub-grid sizes gives each top cell its first
   leaf cell.
3. *The whole leaf level at once*: every (top cell, primitive) pair of the top level
   adds the primitive to each leaf cell of that top cell it overlaps (exact test). The
   paper emits (global leaf cell, primitive) pairs and sorts them all; since a leaf
   belongs to one top cell, a count per leaf, one prefix sum over all leaves and a
   fill, each top cell's references walked by one thread, give the same ranges
   without the sort (primitives stay in increasing order within a leaf, as a stable
   sort leaves them).

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
    candidate_hit,
    cell_interval,
    cell_span,
    check_density,
    resolutions,
)
from rayaccel.grid.layouts.two_level import TwoLevelGrid
from rayaccel.grid.layouts.uniform import MAX_RES_AXIS, SKIP_DISTANCE, cell_margin
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
        check_density("top_density", self.top_density)
        check_density("leaf_density", self.leaf_density)
        if self.skip not in ("none", "distance"):
            raise InvalidInputError(f"skip: expected 'none' or 'distance', got {self.skip!r}")
        UniformGridOptions(1.0, self.max_cells, self.max_refs, self.max_refs_per_prim)


def sub_resolutions(size: np.ndarray, counts: np.ndarray, density: float) -> np.ndarray:
    """Return ``(n_top, 3)`` int32 leaf resolutions: Slusallek's formula per top cell."""
    return resolutions(size, counts, density)


#: ``_leaf_refs`` modes (see there).
BOUND = 0
COUNT = 1
COUNT_REST = 2
FILL = 3
#: ``counts`` of a reference whose exact count waits for the ``COUNT_REST`` pass.
DEFERRED = -1
#: Rounds of halving sub-grid resolutions before the leaf level fits its reference budget.
MAX_SHRINK_ROUNDS = 64


@cpu_kernel(parallel=True)
def _leaf_refs(
    tri, cell_start, top_prim, chunk_cells, lo, size, res, sub_res, leaf_first, leaf_size,
    margin, span, counts, masks, cursor, values, mode,
):  # fmt: skip
    """Bound, count or write the leaf cells each top reference overlaps; return the bound.

    Work goes by top cell, chunk ``k`` taking the cells ``chunk_cells[k]`` to
    ``chunk_cells[k + 1]``; a leaf belongs to one top cell, so no two chunks touch the
    same leaf counter. ``mode``:

    - BOUND: each reference's candidate leaves (its triangle's box in leaf cells,
      widened by twice the margin) into ``span`` (first and last per axis).
    - COUNT: the same, and a reference with at most ``MASK_BITS`` candidates is
      tested at once (a triangle strictly inside one leaf needs no test): its exact
      count into ``counts``, which candidates it overlaps into ``masks`` (as the
      uniform grid's pair pass does), and each overlapped leaf's counter
      ``cursor[leaf + 1]`` up by one. A reference with more candidates is marked
      ``DEFERRED``, so the work before the budget check stays bounded.
    - COUNT_REST: the deferred references counted likewise, from ``span``.
    - FILL: ``cursor[leaf]`` is the leaf's next free slot in ``values``; the overlaps
      come from the mask, or need no test when the count says every candidate leaf
      overlaps, else are tested again.

    Returns the number of candidate leaves of all references (BOUND and COUNT).
    """
    fill = mode == FILL
    rx = res[0]
    ry = res[1]
    total = 0
    for ch in prange(chunk_cells.shape[0] - 1):
        for c in range(chunk_cells[ch], chunk_cells[ch + 1]):
            # This top cell's corner, leaf sizes and margins as scalars: the candidate
            # boxes stay in registers (no small array that other arrays may alias).
            lo_x = lo[0] + np.float32(c % rx) * size[0]
            lo_y = lo[1] + np.float32((c // rx) % ry) * size[1]
            lo_z = lo[2] + np.float32(c // (rx * ry)) * size[2]
            s_x = leaf_size[c, 0]
            s_y = leaf_size[c, 1]
            s_z = leaf_size[c, 2]
            m_x = margin[c, 0]
            m_y = margin[c, 1]
            m_z = margin[c, 2]
            inv_x = 1.0 / np.float64(s_x)
            inv_y = 1.0 / np.float64(s_y)
            inv_z = 1.0 / np.float64(s_z)
            m2_x = 2.0 * np.float64(m_x)
            m2_y = 2.0 * np.float64(m_y)
            m2_z = 2.0 * np.float64(m_z)
            r_x = np.int64(sub_res[c, 0])
            r_y = np.int64(sub_res[c, 1])
            r_z = np.int64(sub_res[c, 2])
            base = np.int64(leaf_first[c])
            for i in range(cell_start[c], cell_start[c + 1]):
                p = top_prim[i]
                if mode == COUNT_REST and counts[i] != DEFERRED:
                    continue
                if mode in (BOUND, COUNT):
                    x0, x1, x_one = cell_span(tri, p, 0, lo_x, inv_x, m2_x, r_x)
                    y0, y1, y_one = cell_span(tri, p, 1, lo_y, inv_y, m2_y, r_y)
                    z0, z1, z_one = cell_span(tri, p, 2, lo_z, inv_z, m2_z, r_z)
                    span[i, 0] = x0
                    span[i, 1] = y0
                    span[i, 2] = z0
                    span[i, 3] = x1
                    span[i, 4] = y1
                    span[i, 5] = z1
                    n_cand = (x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1)
                    single = x_one and y_one and z_one
                    total += n_cand
                    if mode == BOUND:
                        continue
                    if single:
                        cursor[base + x0 + r_x * (y0 + r_y * z0) + 1] += 1
                        counts[i] = 1
                        masks[i] = 1
                        continue
                    if n_cand > MASK_BITS:
                        counts[i] = DEFERRED
                        continue
                x0 = np.int64(span[i, 0])
                y0 = np.int64(span[i, 1])
                z0 = np.int64(span[i, 2])
                x1 = np.int64(span[i, 3])
                y1 = np.int64(span[i, 4])
                z1 = np.int64(span[i, 5])
                n_cand = (x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1)
                masked = n_cand <= MASK_BITS
                every = fill and counts[i] == n_cand
                from_bits = fill and masked
                bits = masks[i] if from_bits else np.int64(0)
                k = 0
                n_hit = 0
                for z in range(z0, z1 + 1):
                    bz_lo, bz_hi = cell_interval(lo_z, s_z, m_z, z)
                    for y in range(y0, y1 + 1):
                        by_lo, by_hi = cell_interval(lo_y, s_y, m_y, y)
                        for x in range(x0, x1 + 1):
                            hit, bits = candidate_hit(
                                tri, p, x, by_lo, bz_lo, by_hi, bz_hi, lo_x, s_x, m_x, k, bits,
                                from_bits, every, masked,
                            )  # fmt: skip
                            if hit:
                                leaf = base + x + r_x * (y + r_y * z)
                                if fill:
                                    values[cursor[leaf]] = p
                                    cursor[leaf] += 1
                                else:
                                    cursor[leaf + 1] += 1
                                n_hit += 1
                            k += 1
                if not fill:
                    counts[i] = n_hit
                    if masked:
                        masks[i] = bits
    return total


def _chunk_cells(cell_start: np.ndarray) -> np.ndarray:
    """Return the first top cell of each work chunk, about ``PRIM_CHUNK`` references each."""
    n_top = cell_start.shape[0] - 1
    cuts = np.searchsorted(cell_start, np.arange(0, int(cell_start[-1]), PRIM_CHUNK), "right")
    return np.unique(np.concatenate([[0], np.minimum(cuts - 1, n_top), [n_top]])).astype(np.int64)


def _leaf_geometry(top: Any, size: np.ndarray, sub_res: np.ndarray) -> tuple[Any, Any]:
    """Return the leaf cell sizes and overlap margins of every top cell's sub-grid."""
    leaf_size = (size[None, :] / sub_res).astype(REAL)
    coords = (np.abs(top.lo.astype(np.float64)) + np.abs(top.hi)) * 2.0**-21
    margin = np.minimum(
        (leaf_size * (2.0**-10) + coords).astype(REAL), cell_margin(top.lo, top.hi, top.res)
    )
    return leaf_size, margin


def _cells_to_coarsen(
    cell_start: np.ndarray,
    span: np.ndarray,
    total: int,
    sub_res: np.ndarray,
    budget: int,
    opts: TwoLevelOptions,
) -> np.ndarray | None:
    """Return the top cells whose sub-grids to halve, or None when the leaf level fits.

    λ2 sizes a sub-grid by its reference count alone, so a top cell holding many large
    or identical overlapping triangles (100k copies of one triangle) would list each
    in most of its leaves: billions of pairs. While the upper bound on the pairs
    (``total``, each reference's box in leaf cells, ``span``) exceeds the budget
    (``max_refs``, and ``max_refs_per_prim`` per primitive), the cells whose
    references average more than ``max_refs_per_prim`` leaves are halved, or failing
    those every cell whose references span several leaves; at resolution 1 a cell
    lists each reference once, within the top level's own budget.
    """
    if total <= budget:
        return None
    bound = np.prod(span[:, 3:].astype(np.int64) - span[:, :3] + 1, axis=1)
    counts = np.diff(cell_start)
    top_of_ref = np.repeat(np.arange(counts.shape[0], dtype=np.int64), counts)
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
    """Bin every top cell's references into its sub-grid of ``sub_res`` cells.

    Sub-grids are first halved where the references would exceed the budget
    (:func:`_cells_to_coarsen`); ``opts`` gives ``max_cells``, ``max_refs`` and
    ``max_refs_per_prim``; ``asked`` names what asked for the cells in the error;
    ``phases`` receives build milliseconds. Used by ``grid.two_level`` and
    ``grid.irregular``.
    """
    t0 = time.perf_counter()
    sub_res = sub_res.copy()
    if int(sub_res.max(initial=1)) > MAX_RES_AXIS:
        raise InvalidInputError(f"{asked}: a sub-grid above {MAX_RES_AXIS} cells per axis")
    n_top = top.n_cells
    size = ((top.hi - top.lo) / top.res).astype(REAL)
    chunks = _chunk_cells(top.cell_start)
    n_ref = top.n_refs
    counts = np.empty(n_ref, dtype=np.int32)
    masks = np.empty(n_ref, dtype=np.int64)
    span = np.empty((n_ref, 6), dtype=np.int16)
    budget = min(opts.max_refs, max(n_ref, int(opts.max_refs_per_prim * top.n_prims)))
    for round_index in range(MAX_SHRINK_ROUNDS):
        leaf_size, margin = _leaf_geometry(top, size, sub_res)
        n_sub = np.prod(sub_res.astype(np.int64), axis=1)
        leaf_first64 = np.concatenate([[0], np.cumsum(n_sub)])
        n_leaves = int(leaf_first64[-1])
        # Counted in the same pass unless the leaves are too many to count.
        fits = n_leaves <= opts.max_cells
        cursor = np.zeros(n_leaves + 1 if fits else 0, dtype=INDEX)
        args = (tri, top.cell_start, top.prim_index, chunks, top.lo, size, top.res, sub_res,
                leaf_first64 if fits else np.zeros(n_top + 1, np.int64), leaf_size, margin,
                span, counts, masks, cursor)  # fmt: skip
        total = _leaf_refs(*args, np.empty(0, np.int32), COUNT if fits else BOUND)
        if round_index == MAX_SHRINK_ROUNDS - 1:
            break  # the counts of the last round stand
        shrink = _cells_to_coarsen(top.cell_start, span, int(total), sub_res, budget, opts)
        if shrink is None:
            break
        sub_res[shrink] = np.maximum(sub_res[shrink] // 2, 1)
    if not fits:
        raise InvalidInputError(
            f"{asked} asks for {n_leaves} leaf cells, more than "
            f"max_cells={opts.max_cells}; lower it or raise max_cells"
        )
    if (counts == DEFERRED).any():
        _leaf_refs(*args, np.empty(0, np.int32), COUNT_REST)
    phases["leaf_count"] = (time.perf_counter() - t0) * 1e3
    t1 = time.perf_counter()
    n_pairs = int(counts.sum(dtype=np.int64))
    if n_pairs > 2**31 - 1:
        raise InvalidInputError(f"{asked}: {n_pairs} leaf references exceed int32")
    np.cumsum(cursor, out=cursor)  # int32: the pairs fit, checked above
    leaf_start = cursor.copy()
    values = np.empty(n_pairs, dtype=np.int32)
    _leaf_refs(*args, values, FILL)
    phases["leaf_fill"] = (time.perf_counter() - t1) * 1e3
    return LeafLevel(sub_res, leaf_first64.astype(INDEX), leaf_size, leaf_start, values)


@register("builder", "grid.two_level")
def build_two_level_grid(
    mesh: TriangleMesh, options: TwoLevelOptions | None = None
) -> TwoLevelGrid:
    """Two-level grid: λ1 top grid, per-cell λ2 sub-grids, all leaves binned at once.

    Build a two-level grid over ``mesh``'s triangles (see the module docstring).

    Raises
    ------
    InvalidInputError
        A density asks for more cells than ``max_cells`` or memory allows.

    References
    ----------
    Kalojanov, Billeter, Slusallek 2011, Two-Level Grids for Ray Tracing on GPUs.
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
