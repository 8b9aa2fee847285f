"""Inline building blocks shared by every ``bvh2`` traversal kernel.

Every stackless traversal of ``bvh2`` must return exactly the hits of the ordered
stack traversal (``bvh2.stack``, :mod:`rayaccel.bvh.traverse.stack`). They therefore
share with it the per-ray set-up and the leaf loop of :mod:`rayaccel.trace`, and,
through these helpers, the box tests on a packed 64-byte row; the child order (nearer
entry first, ties to child 0) is the same rule in each kernel. Keeping them here,
inlined into each kernel, guarantees the arithmetic is literally the same.

These helpers are CPU traversal glue (they call other inlined helpers), not leaf
numerics: the CUDA mirrors will have their own.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rayaccel._jit import cpu_inline, keep_branch, prefetch_row
from rayaccel.bvh.layouts.bvh2 import (
    LEAF_BYTES,
    MAX_DEPTH,
    PACKED_ROW_BYTES,
    REF_BYTES,
    STACK_SIZE,
    TRIANGLE_BYTES,
)
from rayaccel.errors import TraversalOverflowError
from rayaccel.kernels.aabb import ray_box_entry, ray_box_exit
from rayaccel.trace.leaf import intersect_leaf

INF32 = np.float32(np.inf)
_PRIM_BYTES = TRIANGLE_BYTES + REF_BYTES


def box_entry_py(box, row, col, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, lo, hi):
    """Entry distance of the interleaved box at ``box[row, col:col + 6]``, or inf."""
    return ray_box_entry(
        ox, oy, oz, ix, iy, iz,
        box[row, col + nx], box[row, col + ny], box[row, col + nz],
        box[row, col + fx], box[row, col + fy], box[row, col + fz],
        lo, hi,
    )  # fmt: skip


def box_exit_py(box, row, col, ox, oy, oz, ix, iy, iz, fx, fy, fz):
    """Exit distance (2-ulp enlarged, NaN ignored) of the box at ``box[row, col:col + 6]``."""
    return ray_box_exit(
        ox, oy, oz, ix, iy, iz, box[row, col + fx], box[row, col + fy], box[row, col + fz]
    )


def pick_py(first, a, b):
    """Return ``a if first else b``, kept a branch (:func:`rayaccel._jit.keep_branch`).

    For a traversal's next node: as a select it would wait for the box test that
    decides it; as a branch the CPU predicts it and fetches the node at once.
    """
    if first:
        keep_branch()
        return a
    keep_branch()
    return b


box_entry = cpu_inline(box_entry_py)
box_exit = cpu_inline(box_exit_py)
pick = cpu_inline(pick_py)


def lane_planes_py(lanes, nx, ny, nz, fx, fy, fz):
    """Return the near and far plane columns ``(near_x, far_x, near_y, far_y, near_z, far_z)``.

    For a row of ``lanes`` boxes stored structure-of-arrays (plane ``k`` of lane ``c``
    is column ``lanes * k + c``: the pairs layout of ``bvh2.stack``, 2 lanes, and the
    wide rows, 4 or 8), from the ray's interleaved near and far plane indices
    (:func:`rayaccel.trace.ray_setup.ray_prologue_py`). (Products of the indices, each
    a choice between two constants, so the columns stay constants the compiler hoists.)
    """
    return lanes * nx, lanes * fx, lanes * ny, lanes * fy, lanes * nz, lanes * fz


lane_planes = cpu_inline(lane_planes_py)


def child_entries_py(
    box, refs, node, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, lo, hi,
    n_box, n_bytes, with_stats,
):  # fmt: skip
    """Test both children of the packed inner row ``node`` (64 bytes).

    Starts fetching the inner children's rows first, so the fetch overlaps the box
    tests. Returns ``(c0, c1, t0, t1, n_box, n_bytes)``: the children's references,
    their entry distances within ``[lo, hi]`` (inf: missed) and, with ``with_stats``,
    the box test and byte counters advanced by the two tests and the row.
    """
    c0 = refs[node, 12]
    c1 = refs[node, 13]
    if c0 >= 0:
        prefetch_row(box, c0)
    if c1 >= 0:
        prefetch_row(box, c1)
    t0 = box_entry(box, node, 0, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, lo, hi)
    t1 = box_entry(box, node, 6, ox, oy, oz, ix, iy, iz, nx, ny, nz, fx, fy, fz, lo, hi)
    if with_stats:
        n_box += 2
        n_bytes += PACKED_ROW_BYTES
    return c0, c1, t0, t1, n_box, n_bytes


child_entries = cpu_inline(child_entries_py)


def leaf_hits_py(
    bvh, leaf, okx, oky, okz, kx, ky, kz, Sx, Sy, Sz, t_lo, t_hit, pad,
    best_prim, best_u, best_v, stop_at_first, n_prim, n_bytes, with_stats,
):  # fmt: skip
    """Test the triangles of leaf ``leaf`` (``leaf_first``/``leaf_count`` of ``bvh``).

    Returns ``(t_hit, best_prim, best_u, best_v, box_hi, n_prim, n_bytes)``: the hit
    as :func:`rayaccel.trace.leaf.intersect_leaf` leaves it, the culling interval's
    new end ``t_hit + pad``, and, with ``with_stats``, the triangle test and byte
    counters advanced by the triangles tested and the leaf record.
    """
    first = bvh.leaf_first[leaf]
    last = first + bvh.leaf_count[leaf]
    t_hit, best_prim, best_u, best_v, tested = intersect_leaf(
        bvh.tri, bvh.tri_prim, first, last, okx, oky, okz, kx, ky, kz,
        Sx, Sy, Sz, t_lo, t_hit, best_prim, best_u, best_v, stop_at_first,
    )  # fmt: skip
    if with_stats:
        n_prim += tested
        n_bytes += LEAF_BYTES + _PRIM_BYTES * tested
    return t_hit, best_prim, best_u, best_v, t_hit + pad, n_prim, n_bytes


leaf_hits = cpu_inline(leaf_hits_py)


def tally_backtrack_py(levels, targets):
    """Return the histogram ``targets`` with a backtrack ``levels`` levels up counted.

    ``targets`` counts backtracks to the sibling (0 levels up), the uncle (1), the
    grand-uncle (2) and further up; a ray starts with ``(0, 0, 0, 0)``
    (:func:`rayaccel.trace.skeleton.store_backtracks` stores it).
    """
    sibling, uncle, grand_uncle, further = targets
    if levels == 0:
        sibling += 1
    elif levels == 1:
        uncle += 1
    elif levels == 2:
        grand_uncle += 1
    else:
        further += 1
    return sibling, uncle, grand_uncle, further


tally_backtrack = cpu_inline(tally_backtrack_py)


def check_trail_depth(bvh: Any, cache: dict[str, Any] | None, key: str) -> None:
    """Raise ``TraversalOverflowError`` if ``bvh`` is deeper than a 64-bit trail can follow.

    Builders bound the depth by ``MAX_DEPTH`` (56), within every trail's bits; only a
    hand-made tree can be deeper. The depth is memoised in ``cache``.
    """
    depth = cache.get("bvh2.depth") if cache is not None else None
    if depth is None:
        depth = bvh.depth()
        if cache is not None:
            cache["bvh2.depth"] = depth
    if depth > MAX_DEPTH:
        raise TraversalOverflowError(
            f"{key}: the tree is {depth} levels deep, deeper than MAX_DEPTH = {MAX_DEPTH}; "
            f"its per-level trail holds at most {MAX_DEPTH} levels of a {STACK_SIZE}-bit word"
        )
