"""The pairs layout of a binary BVH: one 64-byte row per inner node, its two children side by side.

The row format of Aila & Laine 2009 ("Understanding the Efficiency of Ray Traversal
on GPUs", §3: both children's boxes in the parent, so a step fetches one cache line)
with the planes stored structure-of-arrays, so that one ``<2 x float>`` load, subtract
and multiply compute a slab of both children (:data:`rayaccel.kernels.aabb_wide.slab_test2`),
and with the leaf ranges inlined, so that entering a leaf needs no leaf-table lookup:

======  =====================================================================
column  content (float32 row of 16; columns 12–15 are int32)
======  =====================================================================
0, 1    ``lo.x`` of child 0, child 1
2, 3    ``hi.x``
4–7     ``lo.y``, ``hi.y`` (two each)
8–11    ``lo.z``, ``hi.z``
12, 13  child references: ``>= 0`` an inner row, ``< 0`` ``~first`` triangle row
14, 15  the leaf children's triangle counts (0 for an inner child)
======  =====================================================================

Rows keep the packed layout's depth-first order and the triangle rows are the packed
layout's (:class:`~rayaccel.bvh.layouts.bvh2.PackedBvh2`); each row is written from the
canonical tree's two children and two leaf-table lookups.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from rayaccel.bvh.layouts.bvh2 import CACHE_LINE, PackedBvh2, aligned_zeros, child_rows
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray

#: Column of child ``c``'s reference and of its leaf count.
REF_COLUMN = 12
COUNT_COLUMN = 14


class PairsArrays(NamedTuple):
    """The pairs layout as one kernel argument."""

    box: FloatArray  # (n_inner, 16) float32 rows
    ref: IntArray  # int32 view of ``box``: references at 12, 13, leaf counts at 14, 15
    tri: FloatArray  # (n_refs, 9) triangle rows, leaf by leaf
    tri_prim: IntArray  # (n_refs,) mesh triangle of each row
    root_box: FloatArray  # (6,) interleaved lo/hi
    root_ref: IntArray  # (2,): the root's reference and, for a leaf root, its count


@dataclass(frozen=True, slots=True, eq=False)
class PairsBvh2:
    """Pairs rows derived from a :class:`PackedBvh2` (see the module docstring)."""

    rows: np.ndarray  # (n_inner, 16) float32 buffer
    packed: PackedBvh2
    root_ref: IntArray

    def arrays(self) -> PairsArrays:
        """Return the arrays kernels take as one argument."""
        p = self.packed
        return PairsArrays(
            self.rows, self.rows.view(np.int32), p.tri, p.tri_prim, p.root_box, self.root_ref
        )

    def nbytes(self) -> int:
        """Bytes of the pairs rows (the shared triangle rows count with the packed layout)."""
        return int(self.rows.nbytes)


def pairs_layout(packed: PackedBvh2) -> PairsBvh2:
    """Derive the pairs rows of ``packed`` (same row order) from its canonical tree.

    The packed layout's own rows are not needed (nor made).
    """
    tree = packed.source
    rows = aligned_zeros((max(tree.n_nodes - tree.n_leaves, 1), 16), REAL, CACHE_LINE)
    child_rows(tree.arrays(), packed.ref_of_node, packed.leaf_first, packed.leaf_count, rows, True)
    root = int(packed.root_ref[0])
    root_count = 0
    if root < 0:
        root_count = int(packed.leaf_count[~root])
        root = ~int(packed.leaf_first[~root])
    return PairsBvh2(rows, packed, np.array([root, root_count], dtype=INDEX))
