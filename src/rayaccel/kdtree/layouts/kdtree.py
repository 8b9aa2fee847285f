"""The canonical kd-tree (``kdtree``) and the trace layout every kd traversal reads.

Canonical layout (:class:`KdTree`, what every builder emits)
    Root at node 0; the two children of an inner node are adjacent, the lower one
    (``x[axis] <= split``) first. Each node is 8 bytes (Slusallek's lecture; Havran
    2000): ``nodes[i, 0]`` the split position (float32) and ``nodes[i, 1]``, read as
    int32 (:attr:`KdTree.node_bits`), ``(child << 2) | axis`` for an inner node
    (``axis`` in 0..2) or ``(leaf << 2) | 3`` for a leaf. Leaf ``l`` lists
    ``prim_index[leaf_first[l] : leaf_first[l] + leaf_count[l]]``; a primitive is
    listed in every leaf whose cell its (clipped) triangle overlaps, so
    ``n_refs >= n_prims``, and empty leaves are common (the SAH cuts empty space
    off). Cells are implicit: the root cell is the scene box ``lo``, ``hi`` kept
    with the tree, and each split halves its node's cell. A triangle lying in a split
    plane, or only touching it, is listed on one side (Wald & Havran 2006, §4.3), so
    the closed cells the traversals visit must include their boundary.

Trace layout (:class:`KdTraceLayout`, derived once per accel)
    A copy of the nodes in which each leaf carries its triangle range itself:
    ``(first, (count << 2) | 3)`` instead of ``(unused, (leaf << 2) | 3)``, so a walk
    reaching a leaf reads no leaf table (the words it needs share the node's cache
    line, and an empty leaf costs no further load); inner nodes as in the canonical
    layout. The buffer is kept as two views (split floats, packed ints). Then the
    triangles copied in reference order (``tri (n_refs, 9)``, the rows of
    :meth:`rayaccel.scene.mesh.TriangleMesh.hit_rows`) with ``tri_prim`` naming each
    one's mesh triangle, and the scene box interleaved ``(lo_x, hi_x, lo_y, ...)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import InvalidInputError, StructureInvariantError
from rayaccel.kdtree.layouts.node_order import line_aligned_copy
from rayaccel.kernels.box_grow import load_box, store_box
from rayaccel.kernels.overlap import triangle_box_overlap
from rayaccel.kernels.structure_checks import check_prims_listed
from rayaccel.kernels.triangle import triangle_edges64
from rayaccel.kernels.triangle_rows import gather_rows

#: Deepest tree any kd builder may emit; traversal stacks hold STACK_SIZE >= MAX_DEPTH entries.
MAX_DEPTH = 60
STACK_SIZE = 64
#: The axis field of a leaf node.
LEAF_AXIS = 3

#: Bytes per element, for ``info()["bytes"]`` and the ``bytes`` counter.
NODE_BYTES = 8
LEAF_BYTES = 8
REF_BYTES = 4
TRIANGLE_BYTES = 36
#: ``validate()`` checks a triangle by its box when the components of ``e1 × e2`` sum to
#: at most ``SLIVER·(|e1|² + |e2|²)``: thinner than float32 resolves, clipping may
#: round it away.
SLIVER = 2.0**-40


def max_depth_for(n_prims: int) -> int:
    """Return the depth cap ``8 + 1.3·log2 N`` (pbrt), at most :data:`MAX_DEPTH`."""
    return int(min(MAX_DEPTH, round(8 + 1.3 * np.log2(max(n_prims, 1)))))


def check_build_options(
    max_depth: int, max_leaf_size: int, parallel_threshold: int, max_duplication: float
) -> None:
    """Raise :class:`InvalidInputError` for an out-of-range option every kd builder has.

    Shared by ``kdtree.sah`` and ``kdtree.median`` (their costs are their own).
    """
    if not 1 <= max_depth <= MAX_DEPTH:
        raise InvalidInputError(f"max_depth must be in 1..{MAX_DEPTH}, got {max_depth}")
    if max_leaf_size < 1:
        raise InvalidInputError(f"max_leaf_size must be >= 1, got {max_leaf_size}")
    if parallel_threshold < 0:
        raise InvalidInputError(f"parallel_threshold must be >= 0, got {parallel_threshold}")
    if not max_duplication >= 1:
        raise InvalidInputError(f"max_duplication must be >= 1, got {max_duplication}")


class KdArrays(NamedTuple):
    """The canonical arrays as one kernel argument."""

    node_split: FloatArray  # (n,) float32 view of column 0
    node_bits: IntArray  # (n,) int32 view of column 1
    leaf_first: IntArray
    leaf_count: IntArray
    prim_index: IntArray
    lo: FloatArray
    hi: FloatArray


@dataclass(frozen=True, slots=True, eq=False)
class KdTree:
    """kd-tree; children adjacent (lower first); root at node 0 (see the module docstring).

    Attributes
    ----------
    nodes : (n_nodes, 2) float32
        Split position and, in the int32 view of column 1, ``(child or leaf) << 2 | axis``.
    leaf_first, leaf_count : (n_leaves,) int32
        Each leaf's range in ``prim_index``.
    prim_index : (n_refs,) int32
        Primitive ids in leaf order.
    lo, hi : (3,) float32
        The scene box (the root cell).
    n_prims : int
        Number of primitives of the mesh the tree was built over.
    perfect_splits : bool
        Whether straddling triangles were clipped to the cells (then each listed
        triangle overlaps its leaf's cell; otherwise only its bounding box does).
    """

    nodes: FloatArray
    leaf_first: IntArray
    leaf_count: IntArray
    prim_index: IntArray
    lo: FloatArray
    hi: FloatArray
    n_prims: int
    perfect_splits: bool = True

    @property
    def node_split(self) -> FloatArray:
        """``(n_nodes,)`` split positions (a view)."""
        return self.nodes[:, 0]

    @property
    def node_bits(self) -> IntArray:
        """``(n_nodes,)`` packed child/leaf index and axis (an int32 view)."""
        return self.nodes.view(np.int32)[:, 1]

    def arrays(self) -> KdArrays:
        """Return the arrays as a NamedTuple kernels take as one argument."""
        return KdArrays(
            np.ascontiguousarray(self.node_split),
            np.ascontiguousarray(self.node_bits),
            self.leaf_first,
            self.leaf_count,
            self.prim_index,
            self.lo,
            self.hi,
        )

    @property
    def n_nodes(self) -> int:
        """Number of nodes (inner and leaf)."""
        return int(self.nodes.shape[0])

    @property
    def n_leaves(self) -> int:
        """Number of leaves."""
        return int(self.leaf_first.shape[0])

    @property
    def n_refs(self) -> int:
        """Number of primitive references (a primitive is listed in every leaf it overlaps)."""
        return int(self.prim_index.shape[0])

    def cells(self) -> tuple[FloatArray, FloatArray, IntArray, IntArray]:
        """Return every node's cell ``lo, hi (n, 3)``, its parent (root: -1) and depth."""
        n = self.n_nodes
        lo = np.empty((n, 3), dtype=REAL)
        hi = np.empty((n, 3), dtype=REAL)
        parent = np.full(n, -1, dtype=INDEX)
        depth = np.zeros(n, dtype=INDEX)
        _cells(self.arrays(), lo, hi, parent, depth)
        return lo, hi, parent, depth

    def depth(self) -> int:
        """Return the depth of the deepest leaf (a single-leaf tree has depth 0)."""
        return int(self.cells()[3].max())

    def nbytes(self) -> int:
        """Return the canonical size in bytes (nodes, leaf table and references)."""
        return self.n_nodes * NODE_BYTES + self.n_leaves * LEAF_BYTES + self.n_refs * REF_BYTES

    def sah_cost(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> float:
        """Return the SAH cost ``(C_inner·Σ_inner SA + C_prim·Σ_leaf SA·N) / SA(root)``."""
        lo, hi, _, _ = self.cells()
        extent = (hi - lo).astype(np.float64)
        area = 2.0 * (
            extent[:, 0] * extent[:, 1] + extent[:, 1] * extent[:, 2] + extent[:, 2] * extent[:, 0]
        )
        bits = self.node_bits
        leaf = (bits & 3) == LEAF_AXIS
        count = np.zeros(self.n_nodes)
        count[leaf] = self.leaf_count[bits[leaf] >> 2]
        if area[0] <= 0.0:
            return float(prim_cost * self.n_refs)
        total = inner_cost * area[~leaf].sum() + prim_cost * (area[leaf] * count[leaf]).sum()
        return float(total / area[0])

    def info(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> dict[str, Any]:
        """Return node, leaf (and empty leaf) and reference counts, depth, SAH cost and bytes."""
        return {
            "n_nodes": self.n_nodes,
            "n_leaves": self.n_leaves,
            "n_empty_leaves": int(np.count_nonzero(self.leaf_count == 0)),
            "n_refs": self.n_refs,
            "depth": self.depth(),
            "sah": self.sah_cost(inner_cost, prim_cost),
            "mean_leaf_size": self.n_refs / max(self.n_leaves, 1),
            "canonical_bytes": self.nbytes(),
        }

    def validate(self, triangles: FloatArray | None = None) -> None:
        """Check every invariant; raise :class:`StructureInvariantError` naming the first broken.

        Checks: shapes and dtypes; a finite scene box; children after their parent,
        adjacent and in range; every node reached exactly once; depth ``<= MAX_DEPTH``;
        every split inside its node's cell; every leaf referenced by exactly one node,
        its range inside ``prim_index``; ids in range, none twice in one leaf, every
        primitive listed somewhere. Given ``triangles (F, 3, 3)``: every listed
        triangle (its box, without perfect splits or for a sliver, see :data:`SLIVER`)
        overlaps its leaf's closed cell grown by 1e-6 of the scene's size (clipped
        bounds are rounded outward), and every triangle is listed in each leaf whose
        open cell it overlaps (the cell shrunk by 1e-6 of the scene's size); the size
        is at least the largest coordinate's magnitude, where rounding is relative to.
        """
        n = self.n_nodes
        if n == 0:
            raise StructureInvariantError("kdtree: no nodes")
        if self.nodes.dtype != REAL or self.nodes.shape != (n, 2):
            raise StructureInvariantError("kdtree: nodes must be float32 (n, 2)")
        if not self.nodes.flags.c_contiguous:
            raise StructureInvariantError("kdtree: nodes must be C-contiguous")
        for name in ("leaf_first", "leaf_count", "prim_index"):
            array = getattr(self, name)
            if array.dtype != INDEX or array.ndim != 1 or not array.flags.c_contiguous:
                raise StructureInvariantError(f"kdtree: {name} must be C-contiguous int32 (n,)")
        if self.leaf_first.shape != self.leaf_count.shape:
            raise StructureInvariantError("kdtree: leaf_first and leaf_count differ in length")
        for name in ("lo", "hi"):
            array = getattr(self, name)
            if array.dtype != REAL or array.shape != (3,) or not np.isfinite(array).all():
                raise StructureInvariantError(
                    f"kdtree: scene box {name} must be finite float32 (3,)"
                )
        if (self.lo > self.hi).any():
            raise StructureInvariantError("kdtree: scene box has lo > hi")
        code, where = _check_topology(self.arrays(), MAX_DEPTH)
        if code != 0:
            raise StructureInvariantError(f"kdtree: node {where}: {_TOPOLOGY_ERRORS[code]}")
        check_prims_listed(self.prim_index, self.n_prims, "kdtree")
        leaf_of_ref = np.full(self.n_refs, -1, dtype=np.int64)
        for leaf in np.flatnonzero(self.leaf_count):
            first = self.leaf_first[leaf]
            leaf_of_ref[first : first + self.leaf_count[leaf]] = leaf
        if (leaf_of_ref < 0).any():
            raise StructureInvariantError("kdtree: a reference belongs to no leaf")
        pair = leaf_of_ref * self.n_prims + self.prim_index
        if np.unique(pair).size != self.n_refs:
            raise StructureInvariantError("kdtree: a leaf references a primitive twice")
        if triangles is None:
            return
        tri = np.ascontiguousarray(triangles, dtype=REAL)
        lo, hi, _, _ = self.cells()
        node_of_leaf = np.empty(self.n_leaves, dtype=INDEX)
        leaf_nodes = np.flatnonzero((self.node_bits & 3) == LEAF_AXIS)
        node_of_leaf[self.node_bits[leaf_nodes] >> 2] = leaf_nodes
        # A millionth of the scene's size, or of its coordinates where they are larger (a
        # small scene far from the origin): clipped bounds are padded relative to both.
        magnitude = float(max(np.abs(self.lo).max(), np.abs(self.hi).max()))
        grow = REAL(1e-6) * max(float((self.hi - self.lo).max()), magnitude, 1e-30)
        bad = _check_listed_overlap(
            tri, self.prim_index, leaf_of_ref.astype(INDEX), node_of_leaf, lo, hi,
            self.perfect_splits, grow,
        )  # fmt: skip
        if bad >= 0:
            raise StructureInvariantError(
                f"kdtree: triangle {int(self.prim_index[bad])} does not overlap the cell of "
                f"leaf {int(leaf_of_ref[bad])}"
            )
        sorted_pairs = np.sort(pair)
        prim, leaf = _check_complete(tri, self.arrays(), sorted_pairs, self.n_prims, MAX_DEPTH)
        if prim >= 0:
            raise StructureInvariantError(
                f"kdtree: triangle {prim} overlaps the cell of leaf {leaf} but is not listed there"
            )


_TOPOLOGY_ERRORS = {
    1: "child index out of range or not after its parent",
    2: "node reached twice (not a tree)",
    3: "tree deeper than MAX_DEPTH",
    4: "leaf range outside prim_index",
    5: "leaf referenced by two nodes",
    6: "split outside the node's cell",
    7: "node unreachable from the root",
    8: "leaf index out of range",
    9: "leaf referenced by no node",
}


@cpu_kernel()
def _cells(kd, lo, hi, parent, depth):
    """Fill every node's cell, parent and depth (children follow their parent)."""
    n = kd.node_bits.shape[0]
    for a in range(3):
        lo[0, a] = kd.lo[a]
        hi[0, a] = kd.hi[a]
    for i in range(n):
        bits = kd.node_bits[i]
        axis = bits & 3
        if axis == LEAF_AXIS:
            continue
        child = bits >> 2
        split = kd.node_split[i]
        for c in range(2):
            for a in range(3):
                lo[child + c, a] = lo[i, a]
                hi[child + c, a] = hi[i, a]
            parent[child + c] = i
            depth[child + c] = depth[i] + 1
        hi[child, axis] = split
        lo[child + 1, axis] = split


@cpu_kernel()
def _check_topology(kd, max_depth):
    """Walk the tree from the root; return ``(error code, node)`` or ``(0, -1)``."""
    n = kd.node_bits.shape[0]
    n_leaves = kd.leaf_first.shape[0]
    n_refs = kd.prim_index.shape[0]
    seen = np.zeros(n, dtype=np.uint8)
    leaf_seen = np.zeros(n_leaves, dtype=np.uint8)
    stack, lo, hi = new_descent(max_depth, kd.lo)
    depth_of = np.empty(max_depth + 2, dtype=np.int32)
    depth_of[0] = 0
    sp = start_descent(stack, lo, hi, kd.lo, kd.hi)
    while sp > 0:
        sp -= 1
        node = stack[sp]
        depth = depth_of[sp]
        if seen[node]:
            return 2, node
        seen[node] = 1
        if depth > max_depth:
            return 3, node
        bits = kd.node_bits[node]
        axis = bits & 3
        if axis == LEAF_AXIS:
            leaf = bits >> 2
            if leaf < 0 or leaf >= n_leaves:
                return 8, node
            if leaf_seen[leaf]:
                return 5, node
            leaf_seen[leaf] = 1
            first = kd.leaf_first[leaf]
            count = kd.leaf_count[leaf]
            if first < 0 or count < 0 or first + count > n_refs:
                return 4, node
            continue
        child = bits >> 2
        if child <= node or child + 1 >= n:
            return 1, node
        split = kd.node_split[node]
        if not (lo[sp, axis] <= split <= hi[sp, axis]):
            return 6, node
        # Right (upper) child in slot sp + 1, left (lower) in slot sp.
        for a in range(3):
            lo[sp + 1, a] = lo[sp, a]
            hi[sp + 1, a] = hi[sp, a]
        lo[sp + 1, axis] = split
        hi[sp, axis] = split
        stack[sp] = child
        stack[sp + 1] = child + 1
        depth_of[sp] = depth + 1
        depth_of[sp + 1] = depth + 1
        # Pop the lower child first.
        stack[sp], stack[sp + 1] = stack[sp + 1], stack[sp]
        for a in range(3):
            lo[sp, a], lo[sp + 1, a] = lo[sp + 1, a], lo[sp, a]
            hi[sp, a], hi[sp + 1, a] = hi[sp + 1, a], hi[sp, a]
        sp += 2
    for i in range(n):
        if not seen[i]:
            return 7, i
    for leaf in range(n_leaves):
        if not leaf_seen[leaf]:
            return 9, leaf
    return 0, -1


@cpu_kernel()
def _check_listed_overlap(tri, prim_index, leaf_of_ref, node_of_leaf, lo, hi, exact, grow):
    """Return the first reference whose triangle misses its leaf's closed cell, else -1.

    The cell is grown by ``grow`` on every side: clipped bounds are rounded outward, so
    a triangle touching a cell within rounding is listed there. Without ``exact`` (no
    perfect splits) the triangle's box is tested instead. Zero-area triangles are not
    checked: the watertight test never hits them (its determinant is zero), so the
    leaves that list them cannot change a hit, while clipping and the separating-axis
    test disagree on them. Slivers (twice the area at most :data:`SLIVER` times the
    squared edges) are checked by their box: clipping may round their parts away on
    both sides of a plane, and the builder then keeps them on both by their box.
    """
    g_lo = np.empty(3, dtype=np.float32)
    g_hi = np.empty(3, dtype=np.float32)
    for ref in range(prim_index.shape[0]):
        node = node_of_leaf[leaf_of_ref[ref]]
        p = prim_index[ref]
        e1x, e1y, e1z, e2x, e2y, e2z = triangle_edges64(tri, p)
        area2 = abs(e1y * e2z - e1z * e2y) + abs(e1z * e2x - e1x * e2z) + abs(e1x * e2y - e1y * e2x)
        if exact and area2 == 0.0:
            continue
        e2 = e1x * e1x + e1y * e1y + e1z * e1z + e2x * e2x + e2y * e2y + e2z * e2z
        if exact and area2 > SLIVER * e2:
            for a in range(3):
                g_lo[a] = lo[node, a] - grow
                g_hi[a] = hi[node, a] + grow
            if not triangle_box_overlap(tri, p, g_lo, g_hi):
                return ref
        else:
            for a in range(3):
                t_lo = min(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
                t_hi = max(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
                if t_hi < lo[node, a] or t_lo > hi[node, a]:
                    return ref
    return -1


@cpu_inline
def new_descent(max_depth, box_lo):
    """Return ``(stack, s_lo, s_hi)`` for a walk down a tree of depth ``<= max_depth``.

    Node ids and cell corners, one entry per stack slot; the cells have ``box_lo``'s
    float type. :func:`start_descent` puts the root on the stack.
    """
    n = max_depth + 2
    return (
        np.empty(n, dtype=np.int32),
        np.empty((n, 3), dtype=box_lo.dtype),
        np.empty((n, 3), dtype=box_lo.dtype),
    )


@cpu_inline
def start_descent(stack, s_lo, s_hi, lo, hi):
    """Put the root (node 0, cell ``lo``..``hi``) on a descent's stack; return ``sp = 1``."""
    stack[0] = 0
    for a in range(3):
        s_lo[0, a] = lo[a]
        s_hi[0, a] = hi[a]
    return 1


@cpu_inline
def push_reached_children(stack, s_lo, s_hi, sp, child, axis, split, lower, upper):
    """Replace entry ``sp`` of a descent by a box by the children the box reaches; return ``sp``.

    Entry ``sp`` is an inner node whose cell is ``s_lo[sp]``..``s_hi[sp]``; its upper
    child ``child + 1`` (when ``upper``: the box reaches ``split``) is pushed first,
    then its lower child ``child`` (when ``lower``), each with its cell. Shared by the
    completeness check and the float64 listing of :mod:`rayaccel.kdtree.precision`.
    """
    cell = load_box(s_lo, s_hi, sp)
    if upper:
        stack[sp] = child + 1
        store_box(s_lo, s_hi, sp, cell)
        s_lo[sp, axis] = split
        sp += 1
    if lower:
        stack[sp] = child
        store_box(s_lo, s_hi, sp, cell)
        s_hi[sp, axis] = split
        sp += 1
    return sp


@cpu_kernel()
def _check_complete(tri, kd, sorted_pairs, n_prims, max_depth):
    """Return ``(prim, leaf)`` of a triangle overlapping an open leaf cell it is not listed in.

    Each triangle descends the tree by its bounding box; at each leaf whose cell,
    shrunk on every side (see below), it overlaps exactly, the pair (leaf, prim) must
    be in ``sorted_pairs``. Returns ``(-1, -1)`` when every triangle is complete.
    """
    stack, s_lo, s_hi = new_descent(max_depth, kd.lo)
    c_lo = np.empty(3, dtype=np.float32)
    c_hi = np.empty(3, dtype=np.float32)
    t_lo = np.empty(3, dtype=np.float32)
    t_hi = np.empty(3, dtype=np.float32)
    # Cells are shrunk by a millionth of the scene's size: triangles touching a cell's
    # boundary (listed on one side only) and float64 rounding in the overlap test stay out.
    # A scene small against its coordinates (1e-5 wide at 1.0) shrinks by a millionth of
    # those instead: its size's millionth is below their float32 spacing, so the cells
    # stayed closed and a point on a split plane was missed on the side it is not listed.
    size = max(kd.hi[0] - kd.lo[0], kd.hi[1] - kd.lo[1], kd.hi[2] - kd.lo[2])
    for a in range(3):
        size = max(size, abs(kd.lo[a]), abs(kd.hi[a]))
    shrink = np.float32(1e-6) * max(size, np.float32(1e-30))
    for p in range(tri.shape[0]):
        for a in range(3):
            t_lo[a] = min(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
            t_hi[a] = max(tri[p, 0, a], tri[p, 1, a], tri[p, 2, a])
        sp = start_descent(stack, s_lo, s_hi, kd.lo, kd.hi)
        while sp > 0:
            sp -= 1
            node = stack[sp]
            bits = kd.node_bits[node]
            axis = bits & 3
            if axis == LEAF_AXIS:
                leaf = bits >> 2
                open_cell = True
                for a in range(3):
                    c_lo[a] = s_lo[sp, a] + shrink
                    c_hi[a] = s_hi[sp, a] - shrink
                    if c_lo[a] > c_hi[a]:
                        open_cell = False
                if open_cell and triangle_box_overlap(tri, p, c_lo, c_hi):
                    key = np.int64(leaf) * n_prims + p
                    at = np.searchsorted(sorted_pairs, key)
                    if at >= sorted_pairs.shape[0] or sorted_pairs[at] != key:
                        return p, leaf
                continue
            split = kd.node_split[node]
            sp = push_reached_children(
                stack, s_lo, s_hi, sp, bits >> 2, axis, split, t_lo[axis] <= split,
                t_hi[axis] >= split,
            )  # fmt: skip
    return -1, -1


class KdTraceArrays(NamedTuple):
    """The trace layout as one kernel argument."""

    node_f: FloatArray  # (2n,) float32, the rows flat: node k's split at 2k
    node_i: IntArray  # (2n,) int32 view: node k's packed bits at 2k + 1, a leaf's first at 2k
    tri: FloatArray  # (n_refs, 9)
    tri_prim: IntArray  # (n_refs,)
    root_box: FloatArray  # (6,) interleaved lo/hi


@dataclass(frozen=True, slots=True, eq=False)
class KdTraceLayout:
    """Nodes with leaf ranges, plus triangles in reference order (see the module docstring)."""

    nodes: FloatArray
    tri: FloatArray
    tri_prim: IntArray
    root_box: FloatArray

    def arrays(self) -> KdTraceArrays:
        """Return the arrays as a NamedTuple kernels take as one argument (nodes flat)."""
        return KdTraceArrays(
            self.nodes.reshape(-1),
            self.nodes.view(np.int32).reshape(-1),
            self.tri,
            self.tri_prim,
            self.root_box,
        )

    def nbytes(self) -> int:
        """Return the size in bytes of what this layout adds (node and triangle copies)."""
        return int(self.nodes.nbytes + self.tri.nbytes)


def nodes_with_leaf_ranges(kd: KdTree) -> FloatArray:
    """Return a copy of ``kd.nodes`` whose leaves read ``(first, (count << 2) | 3)``."""
    if int(kd.leaf_count.max(initial=0)) >= 2**29:
        raise StructureInvariantError("a kd leaf lists 2**29 or more triangles")
    nodes = line_aligned_copy(kd.nodes)
    words = nodes.view(np.int32)
    leaf_nodes = np.flatnonzero((words[:, 1] & 3) == LEAF_AXIS)
    leaf = words[leaf_nodes, 1] >> 2
    words[leaf_nodes, 0] = kd.leaf_first[leaf]
    words[leaf_nodes, 1] = (kd.leaf_count[leaf] << 2) | LEAF_AXIS
    return nodes


def trace_layout(kd: KdTree, hit_rows: FloatArray) -> KdTraceLayout:
    """Derive the trace layout from a canonical kd-tree.

    Parameters
    ----------
    kd : KdTree
    hit_rows : (F, 9) float32
        ``TriangleMesh.hit_rows()`` of the mesh the tree was built over.
    """
    root_box = np.empty(6, dtype=REAL)
    root_box[0::2] = kd.lo
    root_box[1::2] = kd.hi
    return KdTraceLayout(
        nodes=nodes_with_leaf_ranges(kd),
        tri=gather_rows(hit_rows, kd.prim_index),
        tri_prim=np.ascontiguousarray(kd.prim_index),
        root_box=root_box,
    )
