"""Float64 meshes in a float32 kd-tree: every float64 triangle listed in each leaf it touches.

A mesh with ``precision="float64"`` (huge coordinates: geospatial, CAD) is intersected
in float64, but its kd-tree is the one every builder makes, over the float32 rounding of
the vertices, with float32 split planes. At ``1e7`` a float32 ulp is 1, so a float64
triangle may stick out of its rounded twin by half a unit, across a split plane into a
leaf that does not list it, or out of the scene box. :func:`conservative_kdtree` keeps
the tree's planes and adds references (the same structure, a few more entries):

1. The scene box moves one float32 step outward on every side (``np.nextafter``); by the
   argument of :mod:`rayaccel.bvh.precision` (rounding to nearest is monotone) every
   float64 corner, hence every float64 triangle, lies inside it.
2. Every triangle is added to each leaf whose closed cell, grown by ``g = 2^-30`` of the
   scene's magnitude on every side, its float64 triangle touches
   (:func:`rayaccel.kernels.overlap.touches`, float64 arithmetic), unless the leaf lists
   it already. The builder's lists are kept as they are, in their order, the additions
   after them.

Why this suffices. Every kd traversal keeps a hit found beyond the current leaf and
skips a later leaf only when it begins (within the culling pad) beyond the closest hit
(:mod:`rayaccel.kdtree.traverse`); it never rejects a hit for lying outside a cell. So
a float64 hit point ``P`` at ``t*`` on triangle ``T`` is found if ``T`` is tested in a
leaf the ray passes through at ``t*``: the ray then reaches that leaf before ``t*``
with no nearer hit known (or a nearer one is kept). ``P`` lies in the scene box (1.),
the closed leaf cells tile it, so some leaf cell ``C`` holds ``P``, the ray passes
through ``C`` at ``t*`` (the traversals' split distances are computed in the rays'
float64 from the float32 planes, exact to float64 rounding, far inside the culling
pad), and ``T`` touches ``C``, so (2.) lists it there. The growth ``g`` covers the
float64 rounding of the touch test: its projections err by a few float64 ulps of the
coordinates (``2^-50`` of the magnitude), ``g`` is ``2^20`` times that, so a triangle
touching ``C`` is never found apart from it; a triangle within ``g`` of ``C`` is listed
too, which costs a test, never a hit. :func:`~rayaccel.kernels.overlap.touches` omits
the separating-axis test's plane axis, whose float64 rounding is not bounded by ``g``
for slivers (its normal is a rounded cross product); fewer axes only list more.

The traversal stacks keep segment ends in float32 (:mod:`rayaccel.kdtree.traverse.stack`):
rounding one moves it by at most ``2^-24`` of its distance, while the culling pad is
``2^-20`` of the distance to the far side of the scene box, so every comparison with a
stored end still has the pad's slack.

Cost: one descent per triangle through the tree by its box (parallel), and the
references of triangles lying within half a float32 ulp of a split plane on the side
that did not list them.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.dtypes import INDEX, REAL
from rayaccel.errors import StructureInvariantError
from rayaccel.kdtree.layouts.kdtree import (
    LEAF_AXIS,
    MAX_DEPTH,
    KdTree,
    new_descent,
    push_reached_children,
    start_descent,
)
from rayaccel.kernels.overlap import touches
from rayaccel.scene.mesh import TriangleMesh

#: Cells grow by this fraction of the scene's magnitude when listing float64 triangles.
GROW = 2.0**-30


@cpu_kernel(parallel=True)
def _leaf_pairs(tri, node_split, node_bits, lo, hi, grow, counts, offsets, out_leaf, fill):
    """Count (``fill`` False) or write the leaves each float64 triangle touches.

    Each triangle descends by its box grown by ``grow``; at a leaf it is listed when
    :func:`touches` its cell grown by ``grow``.
    """
    for p in prange(tri.shape[0]):
        stack, s_lo, s_hi = new_descent(MAX_DEPTH, lo)
        c_lo = np.empty(3, dtype=np.float64)
        c_hi = np.empty(3, dtype=np.float64)
        t_lo = np.empty(3, dtype=np.float64)
        t_hi = np.empty(3, dtype=np.float64)
        for a in range(3):
            t_lo[a] = min(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a]) - grow
            t_hi[a] = max(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a]) + grow
        sp = start_descent(stack, s_lo, s_hi, lo, hi)
        n = 0
        while sp > 0:
            sp -= 1
            node = stack[sp]
            bits = node_bits[node]
            axis = bits & 3
            if axis == LEAF_AXIS:
                for a in range(3):
                    c_lo[a] = s_lo[sp, a] - grow
                    c_hi[a] = s_hi[sp, a] + grow
                if touches(tri, p, c_lo, c_hi):
                    if fill:
                        out_leaf[offsets[p] + n] = bits >> 2
                    n += 1
                continue
            split = np.float64(node_split[node])
            sp = push_reached_children(
                stack, s_lo, s_hi, sp, bits >> 2, axis, split, t_lo[axis] <= split,
                t_hi[axis] >= split,
            )  # fmt: skip
        if not fill:
            counts[p] = n


def _touched_pairs(kd: KdTree, tri: np.ndarray, grow: float) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(leaf, prim)`` int64 arrays: every leaf each triangle touches (cells grown)."""
    n = tri.shape[0]
    split = np.ascontiguousarray(kd.node_split)
    bits = np.ascontiguousarray(kd.node_bits)
    lo = kd.lo.astype(np.float64)
    hi = kd.hi.astype(np.float64)
    counts = np.zeros(n, dtype=np.int64)
    dummy = np.zeros(1, dtype=np.int64)
    _leaf_pairs(tri, split, bits, lo, hi, grow, counts, counts, dummy, False)
    offsets = np.zeros(n, dtype=np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    leaf = np.empty(int(counts.sum()), dtype=np.int64)
    _leaf_pairs(tri, split, bits, lo, hi, grow, counts, offsets, leaf, True)
    return leaf, np.repeat(np.arange(n, dtype=np.int64), counts)


def _listed_pairs(kd: KdTree) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(leaf, prim)`` int64 arrays of the tree's references, leaf by leaf."""
    counts = kd.leaf_count.astype(np.int64)
    owner = np.repeat(np.arange(kd.n_leaves, dtype=np.int64), counts)
    before = np.zeros(kd.n_leaves, dtype=np.int64)
    np.cumsum(counts[:-1], out=before[1:])
    at = np.repeat(kd.leaf_first.astype(np.int64) - before, counts) + np.arange(owner.size)
    return owner, kd.prim_index[at].astype(np.int64)


def _grow(kd: KdTree) -> float:
    """Return the cell growth ``GROW`` times the scene's magnitude (coordinates or size)."""
    lo = kd.lo.astype(np.float64)
    hi = kd.hi.astype(np.float64)
    magnitude = max(float(np.abs(lo).max()), float(np.abs(hi).max()), float((hi - lo).max()))
    return GROW * max(magnitude, 1e-30)


def conservative_kdtree(kd: KdTree, mesh: TriangleMesh) -> KdTree:
    """Return ``kd`` with its box and leaf lists holding ``mesh``'s float64 triangles.

    Parameters
    ----------
    kd : KdTree
        A valid tree built over ``mesh`` (over its float32 :attr:`vertices`); unchanged.
    mesh : TriangleMesh
        The mesh; for a float32 mesh ``kd`` is returned as it is.

    Returns
    -------
    KdTree
        The same nodes; the scene box one float32 step larger per side, and every
        triangle added to each leaf whose cell its float64 version touches (see the
        module docstring for why this suffices).
    """
    if mesh.precision != "float64":
        return kd
    lo = np.nextafter(kd.lo, np.float32(-np.inf)).astype(REAL)
    hi = np.nextafter(kd.hi, np.float32(np.inf)).astype(REAL)
    wide = KdTree(kd.nodes, kd.leaf_first, kd.leaf_count, kd.prim_index, lo, hi, kd.n_prims,
                  kd.perfect_splits)  # fmt: skip
    tri = mesh.triangles64()
    old_leaf, old_prim = _listed_pairs(wide)
    new_leaf, new_prim = _touched_pairs(wide, tri, _grow(wide))
    n_prims = max(kd.n_prims, 1)
    fresh = ~np.isin(new_leaf * n_prims + new_prim, old_leaf * n_prims + old_prim)
    leaf = np.concatenate([old_leaf, new_leaf[fresh]])
    prim = np.concatenate([old_prim, new_prim[fresh]])
    order = np.argsort(leaf, kind="stable")
    counts = np.bincount(leaf, minlength=kd.n_leaves)
    first = np.zeros(kd.n_leaves, dtype=np.int64)
    np.cumsum(counts[:-1], out=first[1:])
    return KdTree(
        nodes=kd.nodes,
        leaf_first=first.astype(INDEX),
        leaf_count=counts.astype(INDEX),
        prim_index=np.ascontiguousarray(prim[order], dtype=INDEX),
        lo=lo,
        hi=hi,
        n_prims=kd.n_prims,
        perfect_splits=kd.perfect_splits,
    )


def check_conservative(kd: KdTree, mesh: TriangleMesh) -> None:
    """Raise :class:`StructureInvariantError` unless ``kd`` holds ``mesh``'s float64 triangles.

    Checks that every float64 corner lies in the scene box and that every triangle is
    listed in each leaf whose closed cell (not grown) its float64 version touches.
    """
    tri = mesh.triangles64()
    corners = tri.reshape(-1, 3)
    if (corners < kd.lo).any() or (corners > kd.hi).any():
        raise StructureInvariantError("kdtree: a float64 triangle sticks out of the scene box")
    need_leaf, need_prim = _touched_pairs(kd, tri, 0.0)
    old_leaf, old_prim = _listed_pairs(kd)
    n_prims = max(kd.n_prims, 1)
    missing = ~np.isin(need_leaf * n_prims + need_prim, old_leaf * n_prims + old_prim)
    if missing.any():
        at = int(np.argmax(missing))
        raise StructureInvariantError(
            f"kdtree: float64 triangle {int(need_prim[at])} touches the cell of leaf "
            f"{int(need_leaf[at])} but is not listed there"
        )
