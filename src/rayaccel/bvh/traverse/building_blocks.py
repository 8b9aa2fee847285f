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

from rayaccel._jit import cpu_inline, keep_branch
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, STACK_SIZE
from rayaccel.errors import TraversalOverflowError
from rayaccel.kernels.aabb import ray_box_entry, ray_box_exit

INF32 = np.float32(np.inf)


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
