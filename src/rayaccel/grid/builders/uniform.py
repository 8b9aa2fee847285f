"""Uniform grid construction by sorting cell/primitive pairs (Kalojanov & Slusallek 2009).

Resolution (Slusallek's lecture; ALGORITHMS §7.1): ``R_a = e_a · cbrt(λ·n / V)`` for
the box extents ``e``, its volume ``V``, ``n`` primitives and the density λ (cells per
primitive, default 5 as in Kalojanov's code). An axis whose ``R_a`` falls below one
gets one cell and the formula is re-solved over the other axes (a flat scene gets the
2D formula ``e_a · sqrt(λ·n / A)``), so the cell count stays ``λ·n``.

Build, data-parallel like the GPU original ("A Parallel Algorithm for Construction of
Uniform Grids", HPG 2009):

1. *count*: each primitive counts the cells of its bounding box that it really overlaps
   (exact triangle/box test, Akenine-Möller 2001, :mod:`rayaccel.kernels.overlap`,
   against the cell widened by :func:`~rayaccel.grid.layouts.uniform.cell_margin`);
   a triangle inside one cell skips the test;
2. *prefix sum* of the counts gives each primitive its output slots;
3. *fill*: the same loop writes ``(cell, primitive)`` pairs;
4. *sort* the pairs by cell (parallel LSD radix sort, :mod:`rayaccel.kernels.radix_sort`;
   stable, so ids stay increasing within a cell);
5. *cell ranges*: where each cell's run starts.

Memory never grows without bound: a density asking for more than ``max_cells`` cells
raises :class:`~rayaccel.errors.InvalidInputError`, and when the primitives' bounding
boxes would make more than ``min(max_refs, max_refs_per_prim · n)`` pairs (e.g. 100k
copies of one triangle, each in every cell) the resolution is lowered until they fit.
Cost O(n + pairs + cells).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.dtypes import INDEX, REAL
from rayaccel.errors import InvalidInputError
from rayaccel.grid.layouts.uniform import (
    BOX_MARGIN,
    MAX_RES_AXIS,
    SKIP_COLUMNS,
    SKIP_NONE,
    UniformGrid,
    cell_margin,
)
from rayaccel.kernels.overlap import separating_axes_of_box
from rayaccel.kernels.radix_sort import radix_sort
from rayaccel.scene.mesh import TriangleMesh

#: Primitives per work chunk of the count and fill kernels.
PRIM_CHUNK = 4096


def check_density(name: str, value: float) -> None:
    """Raise ``InvalidInputError`` unless the density option ``name`` lies in ``(0, 1024]``."""
    if not (0.0 < value <= 1024.0):
        raise InvalidInputError(f"{name}: expected 0 < λ <= 1024, got {value}")


@dataclass(frozen=True, slots=True)
class UniformGridOptions:
    """Options of :func:`build_uniform_grid` (and the skipping builders on it).

    Attributes
    ----------
    density : float
        λ, cells per primitive (0 < λ <= 1024); 5 is Kalojanov's default.
    max_cells : int
        Largest number of cells (1..2**31 - 2); a density asking for more raises
        ``InvalidInputError``. Also capped by a quarter of the physical memory at 16
        bytes per cell.
    max_refs : int
        Largest number of cell/primitive pairs the bounding boxes may make
        (1..2**31 - 1); above it the resolution is lowered (each pair costs about 24
        bytes while sorting and 40 in the traversal layout).
    max_refs_per_prim : float
        The same budget per primitive (>= 1): ``min(max_refs, max_refs_per_prim · n)``.
        Primitives whose boxes span many cells (huge triangles, many copies of one)
        thus lower the resolution instead of multiplying the references.
    """

    density: float = 5.0
    max_cells: int = 2**26
    max_refs: int = 2**26
    max_refs_per_prim: float = 16.0

    def __post_init__(self) -> None:
        check_density("density", self.density)
        if not 1 <= self.max_cells <= 2**31 - 2:
            raise InvalidInputError(f"max_cells: expected 1..2**31-2, got {self.max_cells}")
        if not 1 <= self.max_refs <= 2**31 - 1:
            raise InvalidInputError(f"max_refs: expected 1..2**31-1, got {self.max_refs}")
        if not self.max_refs_per_prim >= 1.0:
            raise InvalidInputError(
                f"max_refs_per_prim: expected >= 1, got {self.max_refs_per_prim}"
            )


def grid_box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the float32 grid box, widened so every axis has extent.

    The scene box grows by ``BOX_MARGIN`` of its largest extent (or coordinate) and by at
    least one float32 ulp.
    """
    lo64 = lo.astype(np.float64)
    hi64 = hi.astype(np.float64)
    coords = float(np.abs(np.concatenate([lo64, hi64])).max())
    scale = max(float((hi64 - lo64).max()), coords, 1e-30)
    pad = scale * BOX_MARGIN
    g_lo = (lo64 - pad).astype(REAL)
    g_hi = (hi64 + pad).astype(REAL)
    g_lo = np.minimum(g_lo, np.nextafter(lo, np.float32(-np.inf)))
    g_hi = np.maximum(g_hi, np.nextafter(hi, np.float32(np.inf)))
    return g_lo.astype(REAL), g_hi.astype(REAL)


@cpu_kernel()
def _resolutions(size, counts, density, max_axis, out):
    """Fill ``out[c]`` with the resolution of a ``size`` box for ``density·counts[c]`` cells.

    Slusallek's formula (see the module docstring): ``wanted = max(density·count, 1)``
    cells shared by the free axes as ``size · (wanted / volume)^(1/k)``; an axis that
    would get fewer than one cell gets one and leaves the others (at most three
    rounds); then rounded and clamped to ``[1, max_axis]``, and one cell for a count
    of 0. One loop serves the uniform grid (one box) and the two-level grid's
    sub-grids (one box per top cell, ``two_level.sub_resolutions``).
    """
    res = np.empty(3, dtype=np.float64)
    for c in range(counts.shape[0]):
        wanted = max(density * np.float64(counts[c]), 1.0)
        free = 7
        for _ in range(3):
            k = 0
            volume = 1.0
            for a in range(3):
                if (free >> a) & 1:
                    k += 1
                    volume *= size[a]
            scale = (wanted / volume) ** (1.0 / max(k, 1))
            small = 0
            for a in range(3):
                res[a] = size[a] * scale if (free >> a) & 1 else 1.0
                if (free >> a) & 1 and res[a] < 1.0:
                    small |= 1 << a
            if small == 0:
                break
            free &= ~small
        for a in range(3):
            r = np.floor(res[a] + 0.5)
            out[c, a] = 1 if counts[c] == 0 else np.int32(min(max(r, 1.0), max_axis))


def resolutions(size: np.ndarray, counts: np.ndarray, density: float) -> np.ndarray:
    """Return ``(len(counts), 3)`` int32 resolutions of a ``size`` box, one per count."""
    out = np.empty((counts.shape[0], 3), dtype=INDEX)
    _resolutions(
        np.asarray(size, dtype=np.float64), np.ascontiguousarray(counts, dtype=INDEX),
        float(density), float(MAX_RES_AXIS), out,
    )  # fmt: skip
    return out


def grid_resolution(extent: np.ndarray, n_cells_wanted: float) -> np.ndarray:
    """Return ``(3,)`` int32 cells per axis for about ``n_cells_wanted`` cubic-ish cells.

    Slusallek's ``R_a = e_a · cbrt(λn / V)``; axes that would get fewer than one cell get
    one and the scale is re-solved over the others (see the module docstring).
    """
    one: np.ndarray = resolutions(extent, np.ones(1, dtype=INDEX), n_cells_wanted)[0]
    return one


def _physical_memory() -> int:
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return 2**34


@cpu_kernel(parallel=True)
def _triangles_and_bounds(vertices, faces):
    """Return the ``(F, 3, 3)`` corners and the ``(2, 3)`` bounds of every triangle."""
    n = faces.shape[0]
    tri = np.empty((n, 3, 3), dtype=np.float32)
    n_chunks = (n + PRIM_CHUNK - 1) // PRIM_CHUNK
    part = np.empty((n_chunks, 2, 3), dtype=np.float32)
    for c in prange(n_chunks):
        x_lo = y_lo = z_lo = np.float32(np.inf)
        x_hi = y_hi = z_hi = np.float32(-np.inf)
        for p in range(c * PRIM_CHUNK, min(n, (c + 1) * PRIM_CHUNK)):
            for k in range(3):
                v = faces[p, k]
                x = vertices[v, 0]
                y = vertices[v, 1]
                z = vertices[v, 2]
                tri[p, k, 0] = x
                tri[p, k, 1] = y
                tri[p, k, 2] = z
                x_lo = min(x_lo, x)
                y_lo = min(y_lo, y)
                z_lo = min(z_lo, z)
                x_hi = max(x_hi, x)
                y_hi = max(y_hi, y)
                z_hi = max(z_hi, z)
        part[c, 0, 0] = x_lo
        part[c, 0, 1] = y_lo
        part[c, 0, 2] = z_lo
        part[c, 1, 0] = x_hi
        part[c, 1, 1] = y_hi
        part[c, 1, 2] = z_hi
    bounds = np.empty((2, 3), dtype=np.float32)
    for a in range(3):
        bounds[0, a] = np.inf
        bounds[1, a] = -np.inf
        for c in range(n_chunks):
            bounds[0, a] = min(bounds[0, a], part[c, 0, a])
            bounds[1, a] = max(bounds[1, a], part[c, 1, a])
    return tri, bounds


def cell_span_py(tri, p, a, lo, inv, m2, r):
    """Return the cells ``first, last`` along axis ``a`` that triangle ``p``'s box spans.

    The box is widened by ``m2`` (twice the cell margin); ``lo`` is the grid's (or top
    cell's) lower corner on that axis, ``inv`` one over the cell size, ``r`` the cells
    along it. The third value says whether the widened box lies within one cell,
    unclamped. Serves the uniform grid's cell ranges and the two-level grid's leaf spans.
    """
    t_lo = min(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
    t_hi = max(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
    j0 = np.int64(np.floor((np.float64(t_lo) - m2 - lo) * inv))
    j1 = np.int64(np.floor((np.float64(t_hi) + m2 - lo) * inv))
    first = min(max(j0, 0), r - 1)
    last = min(max(j1, 0), r - 1)
    return first, last, first == last and j0 >= 0 and j1 < r


cell_span = cpu_inline(cell_span_py)


@cpu_kernel(parallel=True)
def _prim_boxes(tri, lo, inv, margin, res, first, last):
    """Write each triangle's cell range into ``first``/``last``; return their total cells.

    Ranges cover the triangle's box widened by twice the cell margin (a superset of the
    cells it overlaps); the total is int64.
    """
    n = tri.shape[0]
    total = 0
    for p in prange(n):
        count = np.int64(1)
        for a in range(3):
            c0, c1, _ = cell_span(tri, p, a, lo[a], inv[a], 2.0 * margin[a], np.int64(res[a]))
            first[p, a] = c0
            last[p, a] = c1
            count *= c1 - c0 + 1
        total += count
    return total


#: Candidate cells up to which the count pass keeps its overlap results as bits, so the
#: fill pass writes the pairs without testing again.
MASK_BITS = 64


def cell_interval_py(lo, size, margin, i):
    """Return cell ``i``'s extent on one axis, widened by ``margin`` on both sides."""
    return lo + np.float32(i) * size - margin, lo + np.float32(i + 1) * size + margin


def candidate_hit_py(
    tri, p, x, by_lo, bz_lo, by_hi, bz_hi, lo_x, s_x, m_x, k, bits, from_bits, every, masked,
):  # fmt: skip
    """Return ``(hit, bits)``: whether triangle ``p`` overlaps candidate cell ``k``.

    The answer comes from bit ``k`` of ``bits`` (``from_bits``: the count pass kept it),
    is yes for every candidate (``every``: the count says all overlap), or comes from the
    exact test against the cell's box (x extent from column ``x``, y and z given), in
    which case, with ``masked``, a hit sets bit ``k``. The candidate loops of the uniform
    grid's pairs and the two-level grid's leaf level share it.
    """
    if from_bits:
        return (bits >> k) & 1 == 1, bits
    if every:
        return True, bits
    bx_lo, bx_hi = cell_interval(lo_x, s_x, m_x, x)
    hit = separating_axes_of_box(tri, p, bx_lo, by_lo, bz_lo, bx_hi, by_hi, bz_hi, True)
    if masked and hit:
        bits |= np.int64(1) << k
    return hit, bits


cell_interval = cpu_inline(cell_interval_py)
candidate_hit = cpu_inline(candidate_hit_py)


@cpu_kernel(parallel=True)
def _pairs(tri, lo, size, margin, res, first, last, counts, masks, offsets, keys, values, fill):
    """Count or write the cells each triangle overlaps.

    ``fill`` False: counts into ``counts[p]`` and, for a triangle with at most
    :data:`MASK_BITS` candidate cells, which of them it overlaps into ``masks[p]``
    (bit ``k`` for the ``k``-th candidate, x fastest); True: pairs written from
    ``offsets[p]``, from the mask, or with no test when the count says every candidate
    cell overlaps, else tested again.
    """
    n = tri.shape[0]
    n_chunks = (n + PRIM_CHUNK - 1) // PRIM_CHUNK
    rx = np.int64(res[0])
    ry = np.int64(res[1])
    lo_x, lo_y, lo_z = lo[0], lo[1], lo[2]
    s_x, s_y, s_z = size[0], size[1], size[2]
    m_x, m_y, m_z = margin[0], margin[1], margin[2]
    for c in prange(n_chunks):
        for p in range(c * PRIM_CHUNK, min(n, (c + 1) * PRIM_CHUNK)):
            x0 = np.int64(first[p, 0])
            y0 = np.int64(first[p, 1])
            z0 = np.int64(first[p, 2])
            x1 = np.int64(last[p, 0])
            y1 = np.int64(last[p, 1])
            z1 = np.int64(last[p, 2])
            slot = offsets[p] if fill else 0
            if x0 == x1 and y0 == y1 and z0 == z1:
                # Strictly inside one cell: it overlaps that cell.
                if fill:
                    keys[slot] = x0 + rx * (y0 + ry * np.int64(z0))
                    values[slot] = p
                else:
                    counts[p] = 1
                continue
            n_cand = (x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1)
            masked = n_cand <= MASK_BITS
            every = fill and counts[p] == n_cand
            from_bits = fill and masked
            bits = masks[p] if from_bits else np.int64(0)
            k = 0
            # The candidate boxes as scalars (see two_level._leaf_refs).
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
                            if fill:
                                keys[slot] = x + rx * (y + ry * np.int64(z))
                                values[slot] = p
                            slot += 1
                        k += 1
            if not fill:
                counts[p] = slot
                if masked:
                    masks[p] = bits


@cpu_kernel(parallel=True)
def cell_ranges(keys, n_cells):
    """Return ``cell_start (n_cells + 1,)`` int32 of keys sorted by cell."""
    n = keys.shape[0]
    start = np.empty(n_cells + 1, dtype=np.int32)
    for i in prange(n + 1):
        prev = keys[i - 1] if i > 0 else -1
        here = keys[i] if i < n else n_cells
        for c in range(prev + 1, here + 1):
            start[c] = i
    return start


def build_uniform(
    mesh: TriangleMesh, options: UniformGridOptions, key: str
) -> tuple[UniformGrid, np.ndarray]:
    """Build the uniform grid; return it (no skip data) and the triangles ``(F, 3, 3)``."""
    phases: dict[str, float] = {}
    t0 = time.perf_counter()
    n = mesh.n_triangles
    if n == 0:
        raise InvalidInputError(f"{key}: the mesh has no triangles")
    tri, bounds = _triangles_and_bounds(
        np.ascontiguousarray(mesh.vertices, dtype=REAL),
        np.ascontiguousarray(mesh.faces, dtype=INDEX),
    )
    lo, hi = grid_box(bounds[0], bounds[1])
    extent = hi.astype(np.float64) - lo
    wanted = options.density * n
    memory_cells = _physical_memory() // (4 * 16)
    cap = min(options.max_cells, memory_cells)
    if wanted > cap:
        raise InvalidInputError(
            f"{key}: density λ={options.density} asks for {wanted:.4g} cells for {n} "
            f"primitives, more than the cap of {cap} (max_cells={options.max_cells}, "
            f"memory allows {memory_cells}); lower the density or raise max_cells"
        )
    res = grid_resolution(extent, wanted)
    budget = min(options.max_refs, max(int(options.max_refs_per_prim * n), n))
    # Cell coordinates fit int16 (MAX_RES_AXIS); counts and offsets int32 (the pairs
    # are checked against int32 below): less fresh memory to fault in per build.
    first = np.empty((n, 3), dtype=np.int16)
    last = np.empty((n, 3), dtype=np.int16)
    while True:
        inv = (res / extent).astype(np.float64)
        margin = cell_margin(lo, hi, res)
        bbox_pairs = _prim_boxes(
            tri, lo.astype(np.float64), inv, margin.astype(np.float64), res, first, last
        )
        n_cells = int(np.prod(res.astype(np.int64)))
        if bbox_pairs <= budget or n_cells == 1:
            break
        # Too many pairs (primitives spanning many cells): fewer cells, same shape.
        shrink = max(budget / bbox_pairs, 1e-6) * 0.9
        res = grid_resolution(extent, n_cells * shrink)
        if int(np.prod(res.astype(np.int64))) >= n_cells:
            res = np.maximum(res // 2, 1).astype(INDEX)
    if bbox_pairs > 2**31 - 1:
        raise InvalidInputError(f"{key}: {bbox_pairs} cell/primitive pairs exceed int32")
    size = ((hi - lo) / res).astype(REAL)
    phases["bounds"] = (time.perf_counter() - t0) * 1e3
    t1 = time.perf_counter()
    counts = np.empty(n, dtype=np.int32)
    masks = np.empty(n, dtype=np.int64)
    # Cell ids as int32 where they fit (always below max_cells' default): less to move.
    key_type = np.int32 if n_cells <= 2**31 - 1 else np.int64
    dummy_k = np.empty(0, dtype=key_type)
    dummy_v = np.empty(0, dtype=np.int32)
    _pairs(tri, lo, size, margin, res, first, last, counts, masks, counts, dummy_k, dummy_v,
           False)  # fmt: skip
    phases["count"] = (time.perf_counter() - t1) * 1e3
    t1 = time.perf_counter()
    offsets = np.empty(n, dtype=np.int32)
    offsets[0] = 0
    np.cumsum(counts[:-1], out=offsets[1:])
    n_refs = int(offsets[-1]) + int(counts[-1])
    keys = np.empty(n_refs, dtype=key_type)
    values = np.empty(n_refs, dtype=np.int32)
    _pairs(tri, lo, size, margin, res, first, last, counts, masks, offsets, keys, values, True)
    phases["fill"] = (time.perf_counter() - t1) * 1e3
    t1 = time.perf_counter()
    keys, values = radix_sort(keys, values, max(1, (n_cells - 1).bit_length()))
    phases["sort"] = (time.perf_counter() - t1) * 1e3
    t1 = time.perf_counter()
    cell_start = cell_ranges(keys, n_cells)
    phases["ranges"] = (time.perf_counter() - t1) * 1e3
    grid = UniformGrid(
        lo=lo,
        hi=hi,
        res=res.astype(INDEX),
        cell_start=cell_start,
        prim_index=np.ascontiguousarray(values, dtype=INDEX),
        skip_kind=SKIP_NONE,
        skip=np.zeros((n_cells, SKIP_COLUMNS[SKIP_NONE]), dtype=np.int16),
        n_prims=n,
        density=float(options.density),
        phase_ms=phases,
    )
    return grid, tri


@register("builder", "grid.uniform", default=True)
def build_uniform_grid(
    mesh: TriangleMesh, options: UniformGridOptions | None = None
) -> UniformGrid:
    """Uniform grid, λ cells per primitive, sort-based parallel build with exact overlap.

    Build a uniform grid over ``mesh``'s triangles.

    The grid has no skip data (``grid.skip`` then walks it like ``grid.dda``).

    Raises
    ------
    InvalidInputError
        The density asks for more cells than ``max_cells`` or memory allows.

    References
    ----------
    Kalojanov & Slusallek 2009, A Parallel Algorithm for Construction of Uniform Grids.
    """
    grid, _ = build_uniform(mesh, options or UniformGridOptions(), "grid.uniform")
    return grid
