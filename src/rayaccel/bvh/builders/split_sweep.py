"""Full-sweep SAH object splits (Wald, Boulos, Shirley 2007, §4).

Wald, Boulos, Shirley 2007, "Ray Tracing Deformable Scenes using Dynamic Bounding
Volume Hierarchies" (ACM TOG 26(1)), §4. The split function of ``bvh2.sweep_sah``,
called by the top-down scheduler (:mod:`rayaccel.bvh.builders.topdown`).

At every node all ``N-1`` "first i | rest" splits of the primitives sorted by
centroid are evaluated on all three axes: a suffix pass records the area of the
right part, a prefix pass adds the left part and keeps the cheapest SAH cost
(:func:`~rayaccel.kernels.sah.sah_split_cost_scaled`, ``C_prim/A`` folded per
node). The three orders (``order (3, n)``, the scheduler's references) are sorted
once by the builder; a split marks the primitives that go left and stably
partitions each order within the node's range, so every node costs O(N) (no
per-node sorting). A node whose best split is no cheaper than a leaf, but which
holds too many primitives for one, or whose depth must stay bounded, is cut at the
median of its longest axis's order.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from rayaccel._jit import cpu_inline
from rayaccel.kernels.box_grow import EMPTY_BOUNDS, union_bounds
from rayaccel.kernels.sah import bounds_half_area, box_half_area, sah_split_cost_scaled


class SweepParams(NamedTuple):
    """Constants of a full-sweep SAH build, as the kernels take them.

    Attributes
    ----------
    max_leaf_size : int
        Nodes with more primitives are always split.
    traversal_cost, intersection_cost : float
        SAH ``C_trav`` and ``C_prim``.
    """

    max_leaf_size: int
    traversal_cost: float
    intersection_cost: float


class SweepWorkspace(NamedTuple):
    """Scratch arrays of a sweep build (:func:`sweep_workspace`).

    Attributes
    ----------
    right_area : (n + 1,) float64
        Half area of the suffix ``i..end-1`` of the current axis's order.
    goes_left : (n_prims,) uint8
        Side of each primitive in the split being applied.
    scratch : (n,) int32
        Right part of an order during its stable partition.
    """

    right_area: np.ndarray
    goes_left: np.ndarray
    scratch: np.ndarray


@cpu_inline
def sweep_workspace(order, aux):
    """Return a :class:`SweepWorkspace` for ``order (3, n)`` over the boxes in ``aux``."""
    n = order.shape[1]
    return SweepWorkspace(
        np.empty(n + 1, dtype=np.float64),
        np.zeros(aux[0].shape[0], dtype=np.uint8),
        np.empty(n, dtype=np.int32),
    )


@cpu_inline
def sweep_try_split(
    order, aux, params, ws, node, begin, end, cap, depth, forced, box, t_lo, t_hi
):
    """Find the best "first i | rest" split of a node: ``(cost, axis, i)``.

    The scheduler's ``try_split`` for :data:`~rayaccel.bvh.builders.topdown.SWEEP`.
    ``order[a, begin:end]`` are the node's primitives sorted by centroid on axis
    ``a``; ``aux = (prim_lo, prim_hi)`` their boxes, ``t_lo``/``t_hi`` the node's box.
    ``axis`` is -1 (cost ``inf``) when ``forced``. ``cap``, ``depth`` and ``box`` are
    unused.
    """
    prim_lo, prim_hi = aux
    right_area = ws.right_area
    node_area = box_half_area(
        t_lo[node, 0], t_lo[node, 1], t_lo[node, 2], t_hi[node, 0], t_hi[node, 1], t_hi[node, 2]
    )
    inv_area = 1.0 / node_area if node_area > 0 else 0.0
    cost_scale = params.intersection_cost * inv_area
    best_cost = np.inf
    best_axis = -1
    best_i = -1
    if forced:
        return best_cost, best_axis, best_i
    for a in range(3):
        # Suffix pass: area of primitives i..end-1 in this axis's order.
        right = EMPTY_BOUNDS
        for i in range(end - 1, begin, -1):
            right = union_bounds(right, prim_lo, prim_hi, order[a, i], 0)
            right_area[i - begin] = bounds_half_area(right)
        # Prefix pass: evaluate "begin..i-1 | i..end-1".
        left = EMPTY_BOUNDS
        for i in range(begin + 1, end):
            left = union_bounds(left, prim_lo, prim_hi, order[a, i - 1], 0)
            cost = sah_split_cost_scaled(
                params.traversal_cost, cost_scale, bounds_half_area(left), i - begin,
                right_area[i - begin], end - i,
            )  # fmt: skip
            if cost < best_cost:
                best_cost = cost
                best_axis = a
                best_i = i
    return best_cost, best_axis, best_i


@cpu_inline
def sweep_apply_split(
    order, aux, params, ws, node, left, begin, end, cap, cost, axis, pos, box, child_item, t_lo,
    t_hi,
):  # fmt: skip
    """Apply :func:`sweep_try_split`'s split (or a median cut); return the children's ranges.

    The scheduler's split step for :data:`~rayaccel.bvh.builders.topdown.SWEEP`. When
    the split is no cheaper than a leaf (the node is split only because it is too
    large) or there is none, the node is cut at the median of its longest axis's
    order. Every axis's order is then stably partitioned, the children's boxes go to
    pool slots ``left``/``left + 1``, and ``(i, i, end, i)`` is returned as
    ``(left_end, right_begin, right_end, left_cap)``. ``child_item`` is unused.
    """
    prim_lo, prim_hi = aux
    goes_left = ws.goes_left
    scratch = ws.scratch
    count = end - begin
    best_axis = axis
    best_i = pos
    if best_axis < 0 or cost >= params.intersection_cost * count:
        # Degenerate or depth-bounded node: median of the longest axis's order.
        ex = np.float64(t_hi[node, 0]) - t_lo[node, 0]
        ey = np.float64(t_hi[node, 1]) - t_lo[node, 1]
        ez = np.float64(t_hi[node, 2]) - t_lo[node, 2]
        best_axis = 0
        if ey > ex and ey >= ez:
            best_axis = 1
        elif ez > ex and ez > ey:
            best_axis = 2
        best_i = begin + count // 2
    # Mark the left side, then stably partition every axis's order.
    for i in range(begin, end):
        goes_left[order[best_axis, i]] = 1 if i < best_i else 0
    for a in range(3):
        if a == best_axis:
            continue
        n_l = 0
        n_r = 0
        for i in range(begin, end):
            p = order[a, i]
            if goes_left[p]:
                order[a, begin + n_l] = p
                n_l += 1
            else:
                scratch[n_r] = p
                n_r += 1
        for j in range(n_r):
            order[a, begin + n_l + j] = scratch[j]
    # Child boxes from the split axis's order.
    for c in range(2):
        c_begin = begin if c == 0 else best_i
        c_end = best_i if c == 0 else end
        for k in range(3):
            t_lo[left + c, k] = np.inf
            t_hi[left + c, k] = -np.inf
        for i in range(c_begin, c_end):
            p = order[best_axis, i]
            for k in range(3):
                t_lo[left + c, k] = min(t_lo[left + c, k], prim_lo[p, k])
                t_hi[left + c, k] = max(t_hi[left + c, k], prim_hi[p, k])
    return best_i, best_i, end, best_i
