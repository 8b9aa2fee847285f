"""Irregular grid construction (Pérard-Gayot, Kalojanov, Slusallek 2017).

"GPU Ray Tracing using Irregular Grids" (CGF 36(2), Eurographics 2017), with the
parameters of the authors' released implementation (hagrid), ALGORITHMS §7.5:

1. A top grid of density λ1 (``top_density``, 0.12), built as ``grid.uniform`` does.
2. Each top cell gets ``2^d`` leaves per axis, ``d`` the base-2 logarithm of the
   sub-resolution λ2 (``leaf_density``, 2.4) asks for from its reference count,
   rounded up (at most ``max_depth``). The largest ``d`` is the ``shift`` of a virtual
   fine grid of ``top_res << shift`` voxels, in which every leaf is a box of whole
   voxels. The leaves are binned as the two-level grid's are
   (:func:`~rayaccel.grid.builders.two_level.leaf_level`); hagrid subdivides level by
   level like an octree, which ends in the same leaves.
3. Merge rounds (:func:`merge_candidates`, :func:`merge_pass` along x, then y,
   then z): a cell and its
   neighbour on the axis with the same extent on the other two merge when
   ``SA(A∪B)·(N(A∪B) + 1) <= SA(A)·(N_A + 1) + SA(B)·(N_B + 1)`` (unit traversal
   cost; ``N(A∪B)`` the size of the union of their lists, first bounded below by
   ``max(N_A, N_B)``). A cell merges at most once a pass (pairs, never chains, as
   in hagrid). Rounds repeat while a round leaves fewer than ``α`` (0.995) of the
   cells it started with.
4. Expansion (:func:`expand_cells`, ``expansion_passes``, 3): each face of a cell's
   *exit* box moves out over the layer of neighbouring cells beyond it when every
   one of them lists only triangles the cell lists, to the nearest far side among
   them; the traversal leaves a cell by that box.

Differences from hagrid: the top grid's resolution is not rounded up to even numbers
(hagrid's GPU subdivision wants it; this build bins each top cell's leaves directly),
and merging runs on one thread.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel._variant import register
from rayaccel.dtypes import INDEX, REAL
from rayaccel.errors import InvalidInputError
from rayaccel.grid.builders.two_level import leaf_level, top_level
from rayaccel.grid.builders.uniform import UniformGridOptions, check_density
from rayaccel.grid.layouts.irregular import MAX_FINE_RES, IrregularGrid, leaf_boxes, voxel_cell
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class IrregularOptions:
    """Options of :func:`build_irregular_grid`.

    Attributes
    ----------
    top_density : float
        λ1, top cells per primitive (0 < λ1 <= 1024); 0.12 in hagrid.
    leaf_density : float
        λ2, leaves per reference of a top cell (0 < λ2 <= 1024); 2.4 in hagrid.
    merge_threshold : float
        α: merge rounds go on while a round leaves fewer than ``α`` of its cells
        (0 < α <= 1; 0.995 in hagrid; 0 turns merging off).
    expansion_passes : int
        Passes of face expansion (0..16; 3 in hagrid; 0 turns it off).
    max_depth : int
        Largest ``log2`` of a top cell's leaves per axis (0..10).
    max_cells, max_refs, max_refs_per_prim
        As ``grid.two_level``: caps on the top and leaf cells and the reference budget.
    """

    top_density: float = 0.12
    leaf_density: float = 2.4
    merge_threshold: float = 0.995
    expansion_passes: int = 3
    max_depth: int = 8
    max_cells: int = 2**26
    max_refs: int = 2**26
    max_refs_per_prim: float = 16.0

    def __post_init__(self) -> None:
        check_density("top_density", self.top_density)
        check_density("leaf_density", self.leaf_density)
        if not 0.0 <= self.merge_threshold <= 1.0:
            raise InvalidInputError(
                f"merge_threshold: expected 0 <= α <= 1, got {self.merge_threshold}"
            )
        if not 0 <= self.expansion_passes <= 16:
            raise InvalidInputError(
                f"expansion_passes: expected 0..16, got {self.expansion_passes}"
            )
        if not 0 <= self.max_depth <= 10:
            raise InvalidInputError(f"max_depth: expected 0..10, got {self.max_depth}")
        UniformGridOptions(1.0, self.max_cells, self.max_refs, self.max_refs_per_prim)


@cpu_kernel()
def union_size(pool, a_first, a_count, b_first, b_count):
    """Return the size of the union of two increasing id lists of ``pool``."""
    i = a_first
    j = b_first
    a_end = a_first + a_count
    b_end = b_first + b_count
    n = 0
    while i < a_end and j < b_end:
        if pool[i] == pool[j]:
            i += 1
            j += 1
        elif pool[i] < pool[j]:
            i += 1
        else:
            j += 1
        n += 1
    return n + (a_end - i) + (b_end - j)


@cpu_kernel()
def is_subset(pool, a_first, a_count, b_first, b_count):
    """Return whether list ``a`` of ``pool`` is a subset of list ``b`` (both increasing)."""
    j = b_first
    b_end = b_first + b_count
    for i in range(a_first, a_first + a_count):
        while j < b_end and pool[j] < pool[i]:
            j += 1
        if j == b_end or pool[j] != pool[i]:
            return False
        j += 1
    return True


@cpu_kernel(parallel=True)
def merge_candidates(axis, box, first, count, pool, leaf_cell, top_res, shift, log_dim,
                     leaf_first, fine_res, voxel):  # fmt: skip
    """Return each cell's neighbour to merge with along ``axis`` (-1: none) and the union size.

    The neighbour is the cell beyond the upper face on ``axis``; it qualifies when it has
    the same extent on the other two axes and the surface-area cost does not rise (see
    the module docstring). Cells are independent here; :func:`merge_pass` pairs them.
    """
    n = box.shape[0]
    u = (axis + 1) % 3
    v = (axis + 2) % 3
    want = np.full(n, -1, dtype=np.int64)
    size = count.copy()
    vx = np.float64(voxel[0])
    vy = np.float64(voxel[1])
    vz = np.float64(voxel[2])
    for a in prange(n):
        if box[a, 3 + axis] >= fine_res[axis]:
            continue
        px = box[a, 3] if axis == 0 else box[a, 0]
        py = box[a, 4] if axis == 1 else box[a, 1]
        pz = box[a, 5] if axis == 2 else box[a, 2]
        b = voxel_cell(px, py, pz, top_res, shift, log_dim, leaf_first, leaf_cell)
        if (box[b, u] != box[a, u] or box[b, 3 + u] != box[a, 3 + u]
                or box[b, v] != box[a, v] or box[b, 3 + v] != box[a, 3 + v]):  # fmt: skip
            continue
        ea_x = (box[a, 3] - box[a, 0]) * vx
        ea_y = (box[a, 4] - box[a, 1]) * vy
        ea_z = (box[a, 5] - box[a, 2]) * vz
        eb_x = (box[b, 3] - box[b, 0]) * vx
        eb_y = (box[b, 4] - box[b, 1]) * vy
        eb_z = (box[b, 5] - box[b, 2]) * vz
        em_x = ea_x + eb_x if axis == 0 else ea_x
        em_y = ea_y + eb_y if axis == 1 else ea_y
        em_z = ea_z + eb_z if axis == 2 else ea_z
        sa_a = ea_x * ea_y + ea_y * ea_z + ea_z * ea_x
        sa_b = eb_x * eb_y + eb_y * eb_z + eb_z * eb_x
        sa_m = em_x * em_y + em_y * em_z + em_z * em_x
        separate = sa_a * (count[a] + 1) + sa_b * (count[b] + 1)
        if sa_m * (max(count[a], count[b]) + 1) > separate:
            continue
        n_union = union_size(pool, first[a], count[a], first[b], count[b])
        if sa_m * (n_union + 1) > separate:
            continue
        want[a] = b
        size[a] = n_union
    return want, size


@cpu_kernel(parallel=True)
def merge_pass(axis, want, size, box, first, count, pool, leaf_cell):
    """Merge the cells of :func:`merge_candidates` in pairs; return the new cells and lists.

    Returns ``(box, first, count, pool, leaf_cell)``. Pairs are taken in cell order, a
    cell taking part in at most one merge (pairs, never chains, as in hagrid).
    """
    n = box.shape[0]
    partner = np.full(n, -1, dtype=np.int64)
    absorbed = np.zeros(n, dtype=np.uint8)
    for a in range(n):
        b = want[a]
        if b >= 0 and partner[a] < 0 and not absorbed[a] and partner[b] < 0 and not absorbed[b]:
            partner[a] = b
            absorbed[b] = 1
    new_id = np.full(n, -1, dtype=np.int64)
    n_new = 0
    for a in range(n):
        if not absorbed[a]:
            new_id[a] = n_new
            n_new += 1
    new_first = np.empty(n_new, dtype=np.int64)
    new_count = np.empty(n_new, dtype=np.int64)
    total = 0
    for a in range(n):
        if absorbed[a]:
            continue
        c = new_id[a]
        new_first[c] = total
        new_count[c] = size[a] if partner[a] >= 0 else count[a]
        total += new_count[c]
    for a in range(n):
        if partner[a] >= 0:
            new_id[partner[a]] = new_id[a]
    new_box = np.empty((n_new, 6), dtype=np.int32)
    new_pool = np.empty(total, dtype=np.int32)
    for a in prange(n):
        if absorbed[a]:
            continue
        c = new_id[a]
        for k in range(6):
            new_box[c, k] = box[a, k]
        out = new_first[c]
        if partner[a] < 0:
            for k in range(count[a]):
                new_pool[out + k] = pool[first[a] + k]
            continue
        b = partner[a]
        new_box[c, 3 + axis] = box[b, 3 + axis]
        i = first[a]
        j = first[b]
        a_end = first[a] + count[a]
        b_end = first[b] + count[b]
        while i < a_end or j < b_end:
            if j == b_end or (i < a_end and pool[i] < pool[j]):
                new_pool[out] = pool[i]
                i += 1
            elif i == a_end or pool[j] < pool[i]:
                new_pool[out] = pool[j]
                j += 1
            else:
                new_pool[out] = pool[i]
                i += 1
                j += 1
            out += 1
    new_leaf_cell = np.empty_like(leaf_cell)
    for i in prange(leaf_cell.shape[0]):
        new_leaf_cell[i] = new_id[leaf_cell[i]]
    return new_box, new_first, new_count, new_pool, new_leaf_cell


@cpu_kernel(parallel=True)
def expand_cells(box, first, count, pool, leaf_cell, top_res, shift, log_dim, leaf_first,
                 fine_res, passes):  # fmt: skip
    """Return ``(n_cells, 6)`` int32 exit boxes and the number of faces moved.

    Each pass tries the six faces of every cell in turn: the layer of voxels just
    beyond the face, across the face's current extent, is walked cell by cell through
    the voxel map; when every cell met lists only triangles this cell lists, the face
    moves to the nearest far side among them.
    """
    n = box.shape[0]
    out = np.empty((n, 6), dtype=np.int32)
    moved = np.zeros(n, dtype=np.int64)
    for c in prange(n):
        e = np.empty(6, dtype=np.int64)
        for k in range(6):
            e[k] = box[c, k]
        p = np.empty(3, dtype=np.int64)
        for _pass in range(passes):
            for face in range(6):
                axis = face % 3
                upper = face >= 3
                u = (axis + 1) % 3
                v = (axis + 2) % 3
                if upper:
                    if e[3 + axis] >= fine_res[axis]:
                        continue
                    p[axis] = e[3 + axis]
                    limit = np.int64(fine_res[axis])
                else:
                    if e[axis] <= 0:
                        continue
                    p[axis] = e[axis] - 1
                    limit = np.int64(0)
                ok = True
                pv = e[v]
                while ok and pv < e[3 + v]:
                    row_end = np.int64(fine_res[v])
                    pu = e[u]
                    while pu < e[3 + u]:
                        p[u] = pu
                        p[v] = pv
                        nb = voxel_cell(p[0], p[1], p[2], top_res, shift, log_dim, leaf_first,
                                        leaf_cell)  # fmt: skip
                        if not is_subset(pool, first[nb], count[nb], first[c], count[c]):
                            ok = False
                            break
                        if upper:
                            limit = min(limit, np.int64(box[nb, 3 + axis]))
                        else:
                            limit = max(limit, np.int64(box[nb, axis]))
                        row_end = min(row_end, np.int64(box[nb, 3 + v]))
                        pu = box[nb, 3 + u]
                    pv = row_end
                if ok:
                    if upper:
                        e[3 + axis] = limit
                    else:
                        e[axis] = limit
                    moved[c] += 1
        for k in range(6):
            out[c, k] = e[k]
    return out, moved.sum()


@register("builder", "grid.irregular")
def build_irregular_grid(
    mesh: TriangleMesh, options: IrregularOptions | None = None
) -> IrregularGrid:
    """Irregular grid: λ1 top grid, power-of-two leaves, SAH merges, expanded exits.

    Build an irregular grid over ``mesh``'s triangles (see the module docstring).

    Raises
    ------
    InvalidInputError
        A density asks for more cells than ``max_cells`` or memory allows, or the
        virtual fine grid would exceed ``MAX_FINE_RES`` voxels per axis.

    References
    ----------
    Pérard-Gayot, Kalojanov, Slusallek 2017, GPU Ray Tracing using Irregular Grids.
    """
    opts = options or IrregularOptions()
    top, tri, phases, wanted_res = top_level(mesh, opts, "grid.irregular")
    wanted = wanted_res.max(axis=1)
    log_dim = np.minimum(np.ceil(np.log2(wanted)).astype(np.int64), opts.max_depth)
    sub_res = np.repeat((np.int64(1) << log_dim)[:, None], 3, axis=1).astype(INDEX)
    asked = f"grid.irregular: leaf density λ2={opts.leaf_density}"
    leaves = leaf_level(top, tri, sub_res, opts, asked, phases)
    log_dim = np.round(np.log2(leaves.sub_res[:, 0])).astype(INDEX)
    shift = int(log_dim.max())
    fine_res = (top.res.astype(np.int64) << shift).astype(INDEX)
    if (fine_res > MAX_FINE_RES).any():
        raise InvalidInputError(
            f"grid.irregular: {tuple(int(r) for r in fine_res)} voxels per axis exceed "
            f"{MAX_FINE_RES}; lower max_depth or the densities"
        )
    t0 = time.perf_counter()
    box = leaf_boxes(top.res, shift, log_dim, leaves.leaf_first)
    first = leaves.leaf_start[:-1].astype(np.int64)
    count = np.diff(leaves.leaf_start).astype(np.int64)
    pool = leaves.prim_index
    leaf_cell = np.arange(leaves.leaf_first[-1], dtype=INDEX)
    voxel = ((top.hi.astype(np.float64) - top.lo) / fine_res).astype(REAL)
    map_args = (top.res, shift, log_dim, leaves.leaf_first)
    rounds = [int(box.shape[0])]
    while opts.merge_threshold > 0.0 and box.shape[0] > 1:
        for axis in range(3):
            want, size = merge_candidates(
                axis, box, first, count, pool, leaf_cell, *map_args, fine_res, voxel
            )
            box, first, count, pool, leaf_cell = merge_pass(
                axis, want, size, box, first, count, pool, leaf_cell
            )
        rounds.append(int(box.shape[0]))
        if rounds[-1] >= opts.merge_threshold * rounds[-2]:
            break
    phases["merge"] = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    cell_exit, moved = expand_cells(
        box, first, count, pool, leaf_cell, *map_args, fine_res, opts.expansion_passes
    )
    phases["expand"] = (time.perf_counter() - t0) * 1e3
    cell_start = np.concatenate([[0], np.cumsum(count)]).astype(INDEX)
    return IrregularGrid(
        lo=top.lo,
        hi=top.hi,
        top_res=top.res,
        shift=shift,
        log_dim=log_dim,
        leaf_first=leaves.leaf_first,
        cell_of_leaf=np.ascontiguousarray(leaf_cell, dtype=INDEX),
        cell_box=box,
        cell_exit=cell_exit,
        cell_start=cell_start,
        prim_index=np.ascontiguousarray(pool, dtype=INDEX),
        n_prims=top.n_prims,
        phase_ms=phases,
        stats={
            "leaves": int(leaf_cell.shape[0]),
            "cells_per_round": rounds,
            "faces_moved": int(moved),
        },
    )
