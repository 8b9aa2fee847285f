"""Float64 meshes in a float32 BVH: boxes widened to contain the float64 triangles.

A mesh with ``precision="float64"`` (huge coordinates: geospatial, CAD) is intersected
in float64, but its BVH is the structure every builder makes, over the float32 rounding
of the vertices (:attr:`rayaccel.scene.mesh.TriangleMesh.vertices`), with float32 boxes.
Those boxes bound the rounded triangles, not the float64 ones: at ``1e7`` a float32
ulp is 1, so a float64 triangle may stick out of its leaf by half a unit and a ray
hitting that part would never reach the leaf. :func:`conservative_bvh2` makes the tree
conservative, as a float64 intersector needs (the same structure, one float32 ulp
larger per box side):

1. Every box is recomputed as the exact min/max of the float32 corners of the
   triangles below it (:func:`rayaccel.bvh.builders.refit_vertices.refit_bvh2`). For
   most builders this reproduces the built boxes; leaves over split references (SBVH,
   pre-splitting) get their triangles' whole boxes, since the float64 part of a
   triangle inside a split cell is not the float32 part.
2. Every ``lo`` moves one float32 step down and every ``hi`` one step up
   (``np.nextafter``).

Why one step suffices. Let ``x`` be a float64 corner coordinate, ``f = fl32(x)`` its
rounding to nearest, and ``lo`` a box's lower bound, the minimum of such ``f`` over
the box's triangles, so ``f >= lo``. Rounding to nearest is monotone: ``x < y`` implies
``fl32(x) <= fl32(y)``. If ``x < nextdown(lo)`` then ``f = fl32(x) <= fl32(nextdown(lo))
= nextdown(lo) < lo``, a contradiction; hence ``x >= nextdown(lo)``, and symmetrically
``x <= nextup(hi)``. Every float64 corner, hence (by convexity) every point of every
float64 triangle below a node, lies in its widened box. Children stay inside their
parents, since widening is monotone too.

Cost: one refit pass (O(n), parallel) at build time; the boxes grow by one float32 ulp,
which changes the SAH cost negligibly. kd-trees and grids place split planes and cell
boundaries between float32 triangles and cannot be widened this way: a kd-tree lists each
float64 triangle in every leaf it touches instead (:mod:`rayaccel.kdtree.precision`), and
a grid's cell margins already cover the float64 triangles (:mod:`rayaccel.grid.precision`).
"""

from __future__ import annotations

import numpy as np

from rayaccel.bvh.builders.refit_vertices import RefitTopology, refit_bvh2
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.dtypes import REAL
from rayaccel.scene.mesh import TriangleMesh


def conservative_bvh2(
    bvh: Bvh2, mesh: TriangleMesh, topology: RefitTopology | None = None
) -> Bvh2:
    """Return ``bvh`` with every box containing ``mesh``'s float64 triangles.

    Parameters
    ----------
    bvh : Bvh2
        A valid tree built over ``mesh`` (over its float32 :attr:`vertices`); unchanged.
    mesh : TriangleMesh
        The mesh; for a float32 mesh ``bvh`` is returned as it is.
    topology : RefitTopology, optional
        ``bvh``'s refit topology when kept from an earlier refit (found here when None).

    Returns
    -------
    Bvh2
        The same topology; boxes are the float32 min/max of each subtree's corners,
        widened by one float32 step on each side (see the module docstring for why
        this contains every float64 triangle).
    """
    if mesh.precision != "float64":
        return bvh
    exact = refit_bvh2(bvh, mesh.vertices, mesh.faces, topology)
    lo = np.nextafter(exact.node_lo, np.float32(-np.inf)).astype(REAL)
    hi = np.nextafter(exact.node_hi, np.float32(np.inf)).astype(REAL)
    return Bvh2(
        node_lo=np.ascontiguousarray(lo),
        node_hi=np.ascontiguousarray(hi),
        node_first=exact.node_first,
        node_count=exact.node_count,
        prim_index=exact.prim_index,
        n_prims=exact.n_prims,
    )
