"""Layouts derived from the packed BVH2 for the stackless traversals: links and skips.

Parent links (:class:`LinkedBvh2`, Hapala et al. 2011; Áfra & Szirmay-Kalos 2014)
    The packed layout (:mod:`rayaccel.bvh.layouts.bvh2`) stores each inner node as a
    64-byte row holding its children's boxes and references. A node's box therefore
    lives in its *parent's* row, in slot 0 or 1. The up-link of a node is
    ``parent_row * 2 + slot`` (``-1`` for the root): one int32 per inner row
    (``row_up``) and per leaf (``leaf_up``), 4 bytes per node. The sibling is the
    other slot of the same row, so no sibling link is stored. The packed rows, leaf
    tables and triangles are shared with ``bvh2.stack`` and not counted again.

Skip pointers (:class:`SkipBvh2`, Smits 1998, "Efficiency Issues for Ray Tracing")
    Nodes in depth-first pre-order, one 32-byte row each: the interleaved box
    (``[lo.x, hi.x, lo.y, hi.y, lo.z, hi.z]``), the *skip* index (the next node in
    pre-order after this node's subtree; ``n_nodes`` ends the walk) and the leaf
    index (``-1`` for inner nodes) as int32 in columns 6 and 7. A hit box continues
    with the next row, a missed one jumps to its skip index: a stackless walk with a
    fixed child order (child 0 first).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from rayaccel._jit import cpu_kernel
from rayaccel.bvh.layouts.bvh2 import CACHE_LINE, Bvh2, PackedBvh2, aligned_zeros, row_arrays
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.trace.run import memoised_layout

#: Bytes per up-link and per skip row.
LINK_BYTES = 4
SKIP_ROW_BYTES = 32


class LinkedArrays(NamedTuple):
    """Packed layout plus up-links, as one kernel argument."""

    inner_box: FloatArray
    inner_ref: IntArray
    leaf_first: IntArray
    leaf_count: IntArray
    tri: FloatArray
    tri_prim: IntArray
    root_box: FloatArray
    root_ref: IntArray
    row_up: IntArray  # (n_inner,) parent_row * 2 + slot, -1 at the root
    leaf_up: IntArray  # (n_leaves,) parent_row * 2 + slot, -1 for a root leaf


@dataclass(frozen=True, slots=True, eq=False)
class LinkedBvh2:
    """Up-links over a :class:`~rayaccel.bvh.layouts.bvh2.PackedBvh2` (see the module docstring)."""

    packed: PackedBvh2
    row_up: IntArray
    leaf_up: IntArray

    def arrays(self) -> LinkedArrays:
        """Return the arrays as a NamedTuple kernels take as one argument."""
        p = self.packed.arrays()
        return LinkedArrays(*p, self.row_up, self.leaf_up)

    def nbytes(self) -> int:
        """Bytes of the links alone (the packed layout is cached and counted separately)."""
        return int(self.row_up.nbytes + self.leaf_up.nbytes)


@cpu_kernel()
def _up_links_kernel(refs, n_inner, row_up, leaf_up):
    """Fill the up-links from the child references of every packed row."""
    for row in range(n_inner):
        for slot in range(2):
            child = refs[row, 12 + slot]
            if child >= 0:
                row_up[child] = 2 * row + slot
            else:
                leaf_up[~child] = 2 * row + slot


def link_packed(packed: PackedBvh2) -> LinkedBvh2:
    """Derive the up-links of a packed BVH2."""
    n_leaves = packed.leaf_first.shape[0]
    n_inner = n_leaves - 1 if packed.root_ref[0] >= 0 else 0
    row_up = np.full(max(n_inner, 1), -1, dtype=INDEX)
    leaf_up = np.full(n_leaves, -1, dtype=INDEX)
    _up_links_kernel(packed.rows.view(np.int32), n_inner, row_up, leaf_up)
    return LinkedBvh2(packed, row_up, leaf_up)


def linked_layout(packed: PackedBvh2, cache: dict[str, Any] | None) -> LinkedBvh2:
    """Return the up-links of ``packed``, memoised in ``cache`` under ``"bvh2.links"``."""
    return memoised_layout(cache, "bvh2.links", lambda: link_packed(packed))


class SkipArrays(NamedTuple):
    """The skip-pointer layout as one kernel argument."""

    node_row: FloatArray  # (n_nodes, 8) float32: box, then skip and leaf as int32
    node_int: IntArray  # int32 view of the same rows
    leaf_first: IntArray
    leaf_count: IntArray
    tri: FloatArray
    tri_prim: IntArray
    root_box: FloatArray


@dataclass(frozen=True, slots=True, eq=False)
class SkipBvh2:
    """Pre-order rows with skip pointers (see the module docstring)."""

    rows: FloatArray
    packed: PackedBvh2

    def arrays(self) -> SkipArrays:
        """Return the arrays as a NamedTuple kernels take as one argument."""
        packed = self.packed
        return SkipArrays(*row_arrays(self.rows, packed, packed.leaf_first, packed.leaf_count))

    def nbytes(self) -> int:
        """Bytes of the skip rows (leaf tables and triangles are shared with the packed layout)."""
        return int(self.rows.nbytes)


@cpu_kernel()
def _skip_kernel(bvh, rows, max_depth):
    """Write the pre-order rows: box, skip index and leaf index (packed leaf numbering)."""
    ints = rows.view(np.int32)
    n = bvh.node_count.shape[0]
    # Packed leaves are numbered in canonical node order.
    leaf_of = np.full(n, -1, dtype=np.int32)
    n_leaf = 0
    for i in range(n):
        if bvh.node_count[i] > 0:
            leaf_of[i] = n_leaf
            n_leaf += 1
    # Depth-first pre-order with an explicit stack; a node's skip is filled when its
    # subtree is complete, i.e. when the next node is emitted outside it.
    stack = np.empty(max_depth + 2, dtype=np.int32)
    open_rows = np.empty(max_depth + 2, dtype=np.int32)
    open_depth = np.empty(max_depth + 2, dtype=np.int32)
    depth_of = np.empty(max_depth + 2, dtype=np.int32)
    n_open = 0
    stack[0] = 0
    depth_of[0] = 0
    sp = 1
    out = 0
    while sp > 0:
        sp -= 1
        node = stack[sp]
        depth = depth_of[sp]
        # Close every open subtree that does not contain this node.
        while n_open > 0 and open_depth[n_open - 1] >= depth:
            n_open -= 1
            ints[open_rows[n_open], 6] = out
        for a in range(3):
            rows[out, 2 * a] = bvh.node_lo[node, a]
            rows[out, 2 * a + 1] = bvh.node_hi[node, a]
        ints[out, 7] = leaf_of[node]
        if bvh.node_count[node] > 0:
            ints[out, 6] = out + 1
        else:
            open_rows[n_open] = out
            open_depth[n_open] = depth
            n_open += 1
            first = bvh.node_first[node]
            stack[sp] = first + 1
            depth_of[sp] = depth + 1
            stack[sp + 1] = first
            depth_of[sp + 1] = depth + 1
            sp += 2
        out += 1
    while n_open > 0:
        n_open -= 1
        ints[open_rows[n_open], 6] = out


def skip_layout(bvh: Bvh2, packed: PackedBvh2, cache: dict[str, Any] | None) -> SkipBvh2:
    """Return the skip-pointer layout of ``bvh``, memoised in ``cache`` under ``"bvh2.skip"``."""

    def make() -> SkipBvh2:
        rows = aligned_zeros((bvh.n_nodes, 8), REAL, CACHE_LINE)
        _skip_kernel(bvh.arrays(), rows, bvh.depth())
        return SkipBvh2(rows, packed)

    return memoised_layout(cache, "bvh2.skip", make)
