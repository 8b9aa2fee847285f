"""Build references: the boxes a BVH builder builds over, each naming its mesh triangle.

A builder normally builds over one box per triangle. Pre-splitting (Dammertz & Keller
2008, "The Edge Volume Heuristic"; Karras & Aila 2013, "Fast Parallel Construction of
High-Quality Bounding Volume Hierarchies", §5.9) instead hands it several smaller
boxes per large or badly shaped triangle: each covers a part of the triangle and
names the whole triangle, so the tree's leaves are tighter while traversal still
intersects the original triangle (results stay exact). :class:`BuildRefs` is that
hand-over: flat arrays, one row per reference, made by a ``"before"`` build step
(``bvh2+presplit``) and taken by builders as ``refs=``. :func:`triangle_refs` gives
the one-reference-per-triangle list (what builders build over when no step ran, and a
starting point for references made by hand).

Pieces of one triangle may end up in the same leaf. Karras & Aila remove such
duplicates after building; :func:`remove_leaf_duplicates` does it, and the canonical
conversions (:mod:`rayaccel.bvh.layouts.linked_tree`, :mod:`rayaccel.bvh.builders.common`) apply it
whenever a tree has more references than primitives, so no leaf of a canonical
:class:`~rayaccel.bvh.layouts.bvh2.Bvh2` names a triangle twice. Leaf boxes keep the union
of all their references (the kept reference's triangle part may extend into the
removed one's box). Cost O(n_refs · leaf size), parallel over leaves.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh


class BuildRefs(NamedTuple):
    """References a builder builds over (see the module docstring).

    Attributes
    ----------
    lo, hi : (m, 3) float32
        Box of each reference: the whole triangle's box or a part of it (24 bytes).
    prim : (m,) int32
        The mesh triangle each reference names (4 bytes).
    """

    lo: FloatArray
    hi: FloatArray
    prim: IntArray

    @property
    def n_refs(self) -> int:
        """Number of references ``m``."""
        return int(self.prim.shape[0])


def triangle_refs(mesh: TriangleMesh) -> BuildRefs:
    """Return one reference per triangle of ``mesh``: its box, naming itself."""
    tri = mesh.triangles()
    lo = np.ascontiguousarray(tri.min(axis=1), dtype=REAL)
    hi = np.ascontiguousarray(tri.max(axis=1), dtype=REAL)
    return BuildRefs(lo, hi, np.arange(mesh.n_triangles, dtype=INDEX))


def check_refs(refs: BuildRefs, mesh: TriangleMesh, builder: str) -> BuildRefs:
    """Return ``refs`` with C-contiguous arrays of the canonical dtypes; raise if malformed.

    Raises
    ------
    InvalidInputError
        Wrong shapes, non-finite or inverted boxes, no references, a reference naming
        no triangle of ``mesh``, or a triangle named by no reference; the message
        names ``builder``.
    """
    if not isinstance(refs, BuildRefs):
        raise InvalidInputError(f"{builder}: refs must be a BuildRefs, got {type(refs).__name__}")
    lo = np.ascontiguousarray(refs.lo, dtype=REAL)
    hi = np.ascontiguousarray(refs.hi, dtype=REAL)
    prim = np.ascontiguousarray(refs.prim, dtype=INDEX)
    m = prim.shape[0]
    if prim.ndim != 1 or lo.shape != (m, 3) or hi.shape != (m, 3):
        raise InvalidInputError(f"{builder}: refs need lo, hi (m, 3) and prim (m,)")
    if m < mesh.n_triangles:
        raise InvalidInputError(
            f"{builder}: {m} refs for {mesh.n_triangles} triangles (every triangle needs one)"
        )
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (lo > hi).any():
        raise InvalidInputError(f"{builder}: refs have non-finite or inverted boxes")
    if prim.min() < 0 or prim.max() >= mesh.n_triangles:
        raise InvalidInputError(f"{builder}: a ref names no triangle of the mesh")
    if np.bincount(prim, minlength=mesh.n_triangles).min() == 0:
        raise InvalidInputError(f"{builder}: a triangle is named by no ref")
    return BuildRefs(lo, hi, prim)


@cpu_kernel(parallel=True)
def _mark_first_copies(node_first, node_count, prim_index, keep):
    """Set ``keep[r] = 1`` for the first reference of each primitive within its leaf."""
    for node in prange(node_count.shape[0]):
        count = node_count[node]
        begin = node_first[node]
        # Leaves hold at most 64 references (max_leaf_size <= 64): a quadratic scan is cheap.
        for i in range(begin, begin + count):
            keep[i] = 1
            for j in range(begin, i):
                if prim_index[j] == prim_index[i]:
                    keep[i] = 0
                    break


def remove_leaf_duplicates(bvh: Bvh2) -> Bvh2:
    """Return ``bvh`` with every leaf naming each primitive once (``bvh`` if none repeats).

    Node boxes and topology are unchanged; leaf ranges shrink and ``prim_index`` is
    compacted in leaf order. Only trees with ``n_refs > n_prims`` can hold repeats.
    """
    if bvh.n_refs <= bvh.n_prims:
        return bvh
    keep = np.zeros(bvh.n_refs, dtype=np.uint8)
    _mark_first_copies(bvh.node_first, bvh.node_count, bvh.prim_index, keep)
    if keep.all():
        return bvh
    # New slot of every old slot: an exclusive prefix sum of the kept flags.
    slot = np.zeros(bvh.n_refs + 1, dtype=np.int64)
    np.cumsum(keep, out=slot[1:])
    leaf = np.flatnonzero(bvh.node_count > 0)
    first = bvh.node_first[leaf].astype(np.int64)
    new_first = bvh.node_first.copy()
    new_count = bvh.node_count.copy()
    new_first[leaf] = slot[first]
    new_count[leaf] = slot[first + bvh.node_count[leaf]] - slot[first]
    return Bvh2(
        node_lo=bvh.node_lo,
        node_hi=bvh.node_hi,
        node_first=np.ascontiguousarray(new_first, dtype=INDEX),
        node_count=np.ascontiguousarray(new_count, dtype=INDEX),
        prim_index=np.ascontiguousarray(bvh.prim_index[keep.view(bool)], dtype=INDEX),
        n_prims=bvh.n_prims,
    )
