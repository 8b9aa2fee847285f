"""The wide layout of a binary BVH: each row holds up to 4 (or 8) child boxes side by side.

Wald, Benthin, Boulos 2008, "Getting Rid of Packets — Efficient SIMD Single-Ray
Traversal using Multi-branching BVHs" (IEEE RT 2008) and Dammertz, Hanika, Keller
2008, "Shallow Bounding Volume Hierarchies for Fast SIMD Ray Tracing of Incoherent
Rays" (EGSR 2008): a 4-ary BVH lets one node visit test four boxes with one SIMD
instruction per slab and halves the number of traversal steps, at the price of
testing some boxes a binary traversal would have skipped; an 8-ary one (the width of
an AVX register, Embree's BVH8) halves them again.

Derivation from the canonical binary tree (Wald et al. 2008 §3.1): a wide node starts
from a binary inner node's two children and repeatedly replaces the inner child with
the largest surface area by its two children until it has ``width`` children or only
leaves remain. Leaves are the binary tree's leaves, unchanged and addressed by their
canonical node (whose ``node_first``/``node_count`` give their triangle rows), so the
triangle rows of :class:`~rayaccel.bvh.layouts.bvh2.PackedBvh2` are shared and no other
table is needed. Rows are numbered breadth-first with the children of a row adjacent.

Row layout for width ``W`` (``8·W`` float32: 128 bytes for W = 4, 256 for W = 8): columns
``0:W`` are the children's ``lo.x``, ``W:2W`` ``hi.x``, then ``lo.y``, ``hi.y``, ``lo.z``,
``hi.z`` (structure of arrays, so a ray reads the near planes of one axis as W adjacent
floats), ``6W:7W`` the child references as int32 (``>= 0`` a wide row, ``< 0``
``~node``, a leaf of the canonical tree), ``7W`` the number of children, then padding. An
unused lane holds the empty box ``lo = +inf, hi = -inf``, which every ray misses, so the
box test needs no lane mask.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from rayaccel._jit import cpu_kernel
from rayaccel.bvh.layouts.bvh2 import CACHE_LINE, PackedBvh2, aligned_zeros, row_arrays
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import InvalidInputError

#: Children per wide node that the layout and the traversal support.
WIDTHS = (4, 8)
MAX_WIDTH = 8


def row_floats(width: int) -> int:
    """float32 columns per wide row."""
    return 8 * width


def ref_column(width: int) -> int:
    """Column of the first child reference."""
    return 6 * width


def count_column(width: int) -> int:
    """Column of the child count."""
    return 7 * width


class WideArrays(NamedTuple):
    """The wide layout as one kernel argument (triangles: the packed layout's)."""

    box: FloatArray  # (n_rows, 8 * width) float32
    ref: IntArray  # int32 view of ``box``
    leaf_first: IntArray  # the canonical node_first: leaf ``~ref``'s first triangle row
    leaf_count: IntArray  # the canonical node_count
    tri: FloatArray
    tri_prim: IntArray
    root_box: FloatArray
    root_ref: IntArray


@dataclass(frozen=True, slots=True, eq=False)
class WideBvh:
    """Wide rows derived from a :class:`PackedBvh2` (see the module docstring)."""

    rows: np.ndarray  # (n_rows, 8 * width) float32 buffer
    packed: PackedBvh2
    root_ref: IntArray
    width: int

    @property
    def n_rows(self) -> int:
        """Number of wide inner rows."""
        return int(self.rows.shape[0]) if self.root_ref[0] >= 0 else 0

    def arrays(self) -> WideArrays:
        """Return the arrays kernels take as one argument."""
        tree = self.packed.source
        return WideArrays(
            *row_arrays(self.rows, self.packed, tree.node_first, tree.node_count), self.root_ref
        )

    def nbytes(self) -> int:
        """Bytes of the wide rows (the shared packed arrays count with the packed layout)."""
        return int(self.rows.nbytes)


@cpu_kernel()
def _collapse_kernel(bvh, rows, width):
    """Fill ``rows`` with the wide nodes over the canonical binary tree; return how many.

    The tree's root must be an inner node. A leaf child's reference is ``~node``, its
    canonical node (whose ``node_first`` is its first triangle row).
    """
    ints = rows.view(np.int32)
    n_rows = 1
    queue = np.empty(rows.shape[0], dtype=np.int32)
    queue[0] = 0
    cand = np.empty(MAX_WIDTH, dtype=np.int32)
    for w in range(rows.shape[0]):
        if w >= n_rows:
            break
        # Start from the binary node's two children.
        first = bvh.node_first[queue[w]]
        cand[0] = first
        cand[1] = first + 1
        count = 2
        # Open the inner child with the largest surface area until ``width`` children.
        while count < width:
            best = -1
            best_area = np.float32(-1.0)
            for c in range(count):
                if bvh.node_count[cand[c]] == 0:
                    ex = bvh.node_hi[cand[c], 0] - bvh.node_lo[cand[c], 0]
                    ey = bvh.node_hi[cand[c], 1] - bvh.node_lo[cand[c], 1]
                    ez = bvh.node_hi[cand[c], 2] - bvh.node_lo[cand[c], 2]
                    area = ex * ey + ey * ez + ez * ex
                    if area > best_area:
                        best_area = area
                        best = c
            if best < 0:
                break
            opened = bvh.node_first[cand[best]]
            cand[best] = opened
            cand[count] = opened + 1
            count += 1
        # Write the row (structure of arrays; empty lanes get the box every ray misses).
        for c in range(width):
            for a in range(3):
                if c < count:
                    rows[w, 2 * a * width + c] = bvh.node_lo[cand[c], a]
                    rows[w, (2 * a + 1) * width + c] = bvh.node_hi[cand[c], a]
                else:
                    rows[w, 2 * a * width + c] = np.inf
                    rows[w, (2 * a + 1) * width + c] = -np.inf
            if c < count:
                ref = ~cand[c]
                if bvh.node_count[cand[c]] == 0:
                    queue[n_rows] = cand[c]
                    ref = n_rows
                    n_rows += 1
                ints[w, 6 * width + c] = ref
            else:
                ints[w, 6 * width + c] = -2147483648
        ints[w, 7 * width] = count
        for k in range(7 * width + 1, 8 * width):
            ints[w, k] = 0
    return n_rows


def wide_layout(packed: PackedBvh2, width: int = 8) -> WideBvh:
    """Derive the ``width``-wide rows (4 or 8) of ``packed`` from its canonical tree.

    The packed layout's own rows are not needed (nor made).
    """
    if width not in WIDTHS:
        raise InvalidInputError(f"width: expected one of {WIDTHS}, got {width}")
    root = int(packed.root_ref[0])
    tree = packed.source
    n_inner = tree.n_nodes - tree.n_leaves
    floats = row_floats(width)
    if root < 0:
        # A single leaf: no inner rows; the traversal starts at the leaf.
        rows = aligned_zeros((1, floats), REAL, CACHE_LINE)
        return WideBvh(rows, packed, np.array([root], dtype=INDEX), width)
    # At most one wide row per binary inner node. The zeroed buffer's pages past the rows
    # written are never touched, so the view of the rows costs no memory beyond them.
    rows = aligned_zeros((n_inner, floats), REAL, CACHE_LINE)
    n_rows = _collapse_kernel(tree.arrays(), rows, width)
    return WideBvh(rows[:n_rows], packed, np.array([0], dtype=INDEX), width)
