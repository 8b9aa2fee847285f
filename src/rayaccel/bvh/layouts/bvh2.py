"""The canonical binary BVH (``bvh2``) and the packed layout the stack traversal reads.

Canonical layout (:class:`Bvh2`, what every builder emits)
    Root at node 0, siblings adjacent. ``node_count[i] > 0`` marks a leaf over
    ``prim_index[node_first[i] : node_first[i] + node_count[i]]``; otherwise the
    children are ``node_first[i]`` and ``node_first[i] + 1``. Node bounds are
    float32 ``node_lo``/``node_hi`` (24 bytes per node, plus 8 for first/count).
    ``prim_index`` holds primitive ids in leaf order; a primitive may appear in
    several leaves (never twice in one) only for spatial-split builders and pre-split
    input (``n_refs >= n_prims``).

Packed layout (:class:`PackedBvh2`, Aila & Laine 2009 §3, derived once per accel)
    One 64-byte row per *inner* node holding both children's boxes, so one cache
    line serves the two box tests of a traversal step. Columns 0–5 are child 0's
    ``[lo.x, hi.x, lo.y, hi.y, lo.z, hi.z]`` (interleaved so a ray picks its near
    and far plane per axis by an offset, Williams et al. 2005), 6–11 child 1's,
    12–13 the child references and 14–15 padding, stored as int32 in the same
    buffer (``inner_ref`` is an int32 view). A reference ``>= 0`` is an inner row;
    ``< 0`` is ``~leaf`` into ``leaf_first``/``leaf_count``. Triangles are copied
    in leaf order (``tri (n_refs, 9)``: A, B, C) so a leaf streams contiguous
    memory, and ``tri_prim`` maps each back to its mesh triangle.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.config import parallel_section
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray, RealArray
from rayaccel.errors import StructureInvariantError
from rayaccel.kernels.structure_checks import check_prims_listed
from rayaccel.kernels.triangle_rows import gather_rows

#: Deepest tree any builder may emit; traversal stacks hold STACK_SIZE >= MAX_DEPTH entries.
MAX_DEPTH = 56
STACK_SIZE = 64

#: Bytes per element, for ``info()["bytes"]`` and the ``bytes`` counter.
NODE_BYTES = 32
PACKED_ROW_BYTES = 64
LEAF_BYTES = 8
TRIANGLE_BYTES = 36
REF_BYTES = 4
STACK_ENTRY_BYTES = 8


class Bvh2Arrays(NamedTuple):
    """The canonical arrays as one kernel argument."""

    node_lo: FloatArray
    node_hi: FloatArray
    node_first: IntArray
    node_count: IntArray
    prim_index: IntArray


@dataclass(frozen=True, slots=True, eq=False)
class Bvh2:
    """Binary BVH; siblings adjacent; root at node 0.

    Attributes
    ----------
    node_lo, node_hi : (n_nodes, 3) float32
        Node bounds (24 bytes per node).
    node_first : (n_nodes,) int32
        Leaf: first slot in ``prim_index``. Inner: left child index (right = left + 1).
    node_count : (n_nodes,) int32
        Primitive count; 0 marks an inner node.
    prim_index : (n_refs,) int32
        Primitive ids in leaf order.
    n_prims : int
        Number of primitives of the mesh the tree was built over.
    """

    node_lo: FloatArray
    node_hi: FloatArray
    node_first: IntArray
    node_count: IntArray
    prim_index: IntArray
    n_prims: int

    def arrays(self) -> Bvh2Arrays:
        """Return the arrays as a NamedTuple kernels take as one argument."""
        return Bvh2Arrays(
            self.node_lo, self.node_hi, self.node_first, self.node_count, self.prim_index
        )

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return int(self.node_count.shape[0])

    @property
    def n_leaves(self) -> int:
        """Number of leaves."""
        return int(np.count_nonzero(self.node_count))

    @property
    def n_refs(self) -> int:
        """Number of primitive references (``>= n_prims`` with spatial splits)."""
        return int(self.prim_index.shape[0])

    def depths(self) -> IntArray:
        """Return the ``(n_nodes,)`` depth of every node (root 0)."""
        depths: IntArray = _node_depths(self.node_first, self.node_count)
        return depths

    def depth(self) -> int:
        """Return the depth of the deepest leaf (a single-leaf tree has depth 0)."""
        return int(self.depths().max())

    def nbytes(self) -> int:
        """Return the canonical size in bytes held (nodes and references).

        ``n_nodes * NODE_BYTES + n_refs * REF_BYTES``, less the boxes when an accel has
        released them (:mod:`rayaccel.bvh.layouts.released_bounds`).
        """
        arrays = (self.node_lo, self.node_hi, self.node_first, self.node_count, self.prim_index)
        return int(sum(a.nbytes for a in arrays))

    def sah_cost(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> float:
        """Return the SAH cost of the tree (MacDonald & Booth 1990; Aila et al. 2013).

        ``(C_inner · Σ_inner SA(n) + C_prim · Σ_leaf SA(l)·N(l)) / SA(root)``,
        with no per-leaf constant. Computed in float64.
        """
        extent = (self.node_hi - self.node_lo).astype(np.float64)
        area = 2.0 * (
            extent[:, 0] * extent[:, 1] + extent[:, 1] * extent[:, 2] + extent[:, 2] * extent[:, 0]
        )
        leaf = self.node_count > 0
        total = (
            inner_cost * area[~leaf].sum() + prim_cost * (area[leaf] * self.node_count[leaf]).sum()
        )
        root_area = area[0]
        if root_area <= 0.0:
            return float(prim_cost * self.n_refs) if leaf[0] else float(inner_cost + prim_cost)
        return float(total / root_area)

    def info(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> dict[str, Any]:
        """Return node, leaf and reference counts, depth, SAH cost and mean leaf size."""
        return {
            "n_nodes": self.n_nodes,
            "n_leaves": self.n_leaves,
            "n_refs": self.n_refs,
            "depth": self.depth(),
            "sah": self.sah_cost(inner_cost, prim_cost),
            "mean_leaf_size": self.n_refs / max(self.n_leaves, 1),
        }

    def quality(
        self,
        triangles: FloatArray,
        *,
        epo: bool = False,
        segments: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
        inner_cost: float = 1.2,
        prim_cost: float = 1.0,
    ) -> dict[str, Any]:
        """Return the end-point overlap and leaf count variability (:mod:`rayaccel.bvh.metrics`).

        ``epo`` asks for the end-point overlap (seconds to a minute on million-triangle
        scenes); ``segments = (origin, direction, tmin, t_hit)`` for the leaf count
        variability and mean leaves per ray over those ray segments.
        """
        from rayaccel.bvh import metrics

        out: dict[str, Any] = {}
        if epo:
            out["epo"] = metrics.epo(self, triangles, inner_cost, prim_cost)
        if segments is not None:
            counts = metrics.leaf_counts(self, *segments)
            out["lcv"] = metrics.lcv(counts)
            out["mean_leaves_per_ray"] = float(counts.mean()) if counts.size else 0.0
        return out

    def validate(self, triangles: FloatArray | None = None) -> None:
        """Check every invariant; raise :class:`StructureInvariantError` naming the first broken.

        Checks: array shapes and dtypes; children indices in range and adjacent; every
        node reachable exactly once from the root; depth ``<= MAX_DEPTH``; leaves cover
        ``prim_index`` exactly once, in order; every primitive referenced at least once
        and at most once per leaf;
        children boxes inside their parent; and, given ``triangles (F, 3, 3)``, each
        leaf box contains the boxes of its triangles (or, for spatial splits, overlaps them).
        """
        n = self.n_nodes
        if n == 0:
            raise StructureInvariantError("bvh2: no nodes")
        for name in ("node_lo", "node_hi"):
            array = getattr(self, name)
            if array.dtype != REAL or array.shape != (n, 3) or not array.flags.c_contiguous:
                raise StructureInvariantError(f"bvh2: {name} must be C-contiguous float32 (n, 3)")
        for name in ("node_first", "node_count", "prim_index"):
            array = getattr(self, name)
            if array.dtype != INDEX or array.ndim != 1 or not array.flags.c_contiguous:
                raise StructureInvariantError(f"bvh2: {name} must be C-contiguous int32 (n,)")
        if not (np.isfinite(self.node_lo).all() and np.isfinite(self.node_hi).all()):
            raise StructureInvariantError("bvh2: non-finite node bounds")
        if (self.node_lo > self.node_hi).any():
            bad = int(np.argwhere((self.node_lo > self.node_hi).any(axis=1))[0, 0])
            raise StructureInvariantError(f"bvh2: node {bad} has lo > hi")
        code, where = _check_topology(self.arrays(), MAX_DEPTH)
        if code != 0:
            raise StructureInvariantError(f"bvh2: node {where}: {_TOPOLOGY_ERRORS[code]}")
        check_prims_listed(self.prim_index, self.n_prims, "bvh2")
        if self.n_refs == self.n_prims and np.unique(self.prim_index).size != self.n_prims:
            raise StructureInvariantError("bvh2: a primitive appears in two leaves")
        # Leaves tile prim_index in order of their first slot (checked above).
        leaf = np.flatnonzero(self.node_count > 0)
        order = np.argsort(self.node_first[leaf], kind="stable")
        leaf_of_ref = np.repeat(leaf[order], self.node_count[leaf][order])
        if self.n_refs > self.n_prims:
            pair = leaf_of_ref.astype(np.int64) * self.n_prims + self.prim_index
            if np.unique(pair).size != self.n_refs:
                raise StructureInvariantError("bvh2: a leaf references a primitive twice")
        if triangles is not None:
            tri = triangles[self.prim_index]
            tri_lo, tri_hi = tri.min(axis=1), tri.max(axis=1)
            exact = self.n_refs == self.n_prims
            if exact:
                outside = (tri_lo < self.node_lo[leaf_of_ref]) | (
                    tri_hi > self.node_hi[leaf_of_ref]
                )
            else:
                outside = (tri_hi < self.node_lo[leaf_of_ref]) | (
                    tri_lo > self.node_hi[leaf_of_ref]
                )
            if outside.any():
                ref = int(np.argwhere(outside.any(axis=1))[0, 0])
                raise StructureInvariantError(
                    f"bvh2: triangle {int(self.prim_index[ref])} lies outside leaf "
                    f"{int(leaf_of_ref[ref])}"
                )


_TOPOLOGY_ERRORS = {
    1: "child index out of range",
    2: "node reached twice (not a tree)",
    3: "tree deeper than MAX_DEPTH",
    4: "leaf range outside prim_index",
    5: "leaves do not cover prim_index exactly once in order",
    6: "child box not inside parent box",
    7: "node unreachable from the root",
}


@cpu_kernel()
def _check_topology(bvh, max_depth):
    """Walk the tree from the root; return ``(error code, node)`` or ``(0, -1)``."""
    n = bvh.node_count.shape[0]
    seen = np.zeros(n, dtype=np.uint8)
    stack = np.empty(max_depth + 2, dtype=np.int32)
    depth_of = np.empty(max_depth + 2, dtype=np.int32)
    stack[0] = 0
    depth_of[0] = 0
    sp = 1
    next_ref = 0
    n_refs = bvh.prim_index.shape[0]
    while sp > 0:
        sp -= 1
        node = stack[sp]
        depth = depth_of[sp]
        if seen[node]:
            return 2, node
        seen[node] = 1
        if depth > max_depth:
            return 3, node
        count = bvh.node_count[node]
        first = bvh.node_first[node]
        if count > 0:
            # Leaves are visited left to right, so their ranges must tile prim_index.
            if first < 0 or first + count > n_refs:
                return 4, node
            if first != next_ref:
                return 5, node
            next_ref += count
            continue
        if first <= node or first + 1 >= n:
            return 1, node
        for c in range(2):
            child = first + c
            for a in range(3):
                if (
                    bvh.node_lo[child, a] < bvh.node_lo[node, a]
                    or bvh.node_hi[child, a] > bvh.node_hi[node, a]
                ):
                    return 6, child
        # Push right first so the left subtree's leaves come first.
        stack[sp] = first + 1
        depth_of[sp] = depth + 1
        stack[sp + 1] = first
        depth_of[sp + 1] = depth + 1
        sp += 2
    if next_ref != n_refs:
        return 5, -1
    for i in range(n):
        if not seen[i]:
            return 7, i
    return 0, -1


@cpu_kernel()
def _node_depths(node_first, node_count):
    """Return the depth of every node (children always follow their parent)."""
    depth = np.zeros(node_count.shape[0], dtype=np.int32)
    for i in range(node_count.shape[0]):
        if node_count[i] == 0:
            depth[node_first[i]] = depth[i] + 1
            depth[node_first[i] + 1] = depth[i] + 1
    return depth


class PackedArrays(NamedTuple):
    """The packed traversal layout as one kernel argument."""

    inner_box: FloatArray  # (n_inner, 16) float32: child boxes
    inner_ref: IntArray  # (n_inner, 16) int32 view of the same rows: refs at 12, 13
    leaf_first: IntArray
    leaf_count: IntArray
    tri: FloatArray  # (n_refs, 9)
    tri_prim: IntArray  # (n_refs,)
    root_box: FloatArray  # (6,) interleaved lo/hi
    root_ref: IntArray  # (1,)


CACHE_LINE = 64


def aligned_zeros(shape: tuple[int, ...], dtype: type, alignment: int) -> np.ndarray:
    """Return a zeroed C-contiguous array whose data starts on an ``alignment``-byte boundary.

    A 64-byte packed row that straddles two cache lines costs two misses instead of one.
    """
    n_bytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    raw = np.zeros(n_bytes + alignment, dtype=np.uint8)
    offset = (-raw.ctypes.data) % alignment
    return raw[offset : offset + n_bytes].view(dtype).reshape(shape)


@dataclass(frozen=True, slots=True, eq=False)
class PackedBvh2:
    """Aila–Laine style packed BVH2 (see the module docstring).

    The triangle rows are made at once; the leaf tables and the node numbers when
    first read, and the inner rows only when a traversal first reads :attr:`rows`
    (the default queries' wide rows are derived from the canonical tree directly and
    address its leaves, so they need neither).
    """

    tri: RealArray
    tri_prim: IntArray
    root_box: FloatArray
    root_ref: IntArray
    source: Bvh2  # the canonical tree the rows are made from
    _made: list[np.ndarray] = field(default_factory=list)  # the rows, once made
    _tables: list[IntArray] = field(default_factory=list)  # ref_of_node, leaf_first, leaf_count

    def _numbered(self) -> list[IntArray]:
        """Return ``[ref_of_node, leaf_first, leaf_count]``, made on first use."""
        if not self._tables:
            tree = self.source
            ref_of_node = np.empty(tree.n_nodes, dtype=INDEX)
            leaf_first = np.empty(tree.n_leaves, dtype=INDEX)
            leaf_count = np.empty(tree.n_leaves, dtype=INDEX)
            _number_kernel(tree.arrays(), ref_of_node, leaf_first, leaf_count)
            if not self._tables:
                self._tables.extend((ref_of_node, leaf_first, leaf_count))
        return self._tables

    @property
    def ref_of_node(self) -> IntArray:
        """The packed reference of each canonical node (a row, or ``~leaf``)."""
        return self._numbered()[0]

    @property
    def leaf_first(self) -> IntArray:
        """Each leaf's first triangle row, leaves numbered depth-first."""
        return self._numbered()[1]

    @property
    def leaf_count(self) -> IntArray:
        """Each leaf's triangle count."""
        return self._numbered()[2]

    @property
    def rows(self) -> np.ndarray:
        """The ``(n_inner, 16)`` float32 rows (at least one), made on first use."""
        if not self._made:
            n_inner = self.source.n_nodes - self.source.n_leaves
            rows = aligned_zeros((max(n_inner, 1), 16), REAL, CACHE_LINE)
            tables = (self.ref_of_node, self.leaf_first, self.leaf_count)
            with parallel_section():
                child_rows(self.source.arrays(), *tables, rows, False)
            if not self._made:
                self._made.append(rows)
        return self._made[0]

    @property
    def has_rows(self) -> bool:
        """Whether :attr:`rows` has been made."""
        return bool(self._made)

    def arrays(self) -> PackedArrays:
        """Return the arrays as a NamedTuple kernels take as one argument."""
        tables = (self.leaf_first, self.leaf_count)
        return PackedArrays(*row_arrays(self.rows, self, *tables), self.root_ref)

    def nbytes(self) -> int:
        """Return the packed size in bytes (the rows and tables once made).

        The triangle ids count only when they are a copy: usually they are the canonical
        tree's ``prim_index`` itself, which the tree's own bytes count.
        """
        made = [*self._made, *self._tables]
        if not np.shares_memory(self.tri_prim, self.source.prim_index):
            made.append(self.tri_prim)
        return int(sum(a.nbytes for a in made) + self.tri.nbytes)


def row_arrays(
    rows: np.ndarray, packed: PackedBvh2, leaf_first: IntArray, leaf_count: IntArray
) -> tuple[FloatArray, IntArray, IntArray, IntArray, RealArray, IntArray, FloatArray]:
    """Return the first fields of a row layout's kernel argument.

    ``rows`` and their int32 view, the leaf tables its ``~leaf`` references index, then
    ``packed``'s triangle rows and root box, which the layouts derived from the packed
    one share with it.
    """
    return (
        rows,
        rows.view(np.int32),
        leaf_first,
        leaf_count,
        packed.tri,
        packed.tri_prim,
        packed.root_box,
    )


@cpu_kernel()
def _number_kernel(bvh, ref_of_node, leaf_first, leaf_count):
    """Give inner rows and leaves their numbers in canonical (depth-first) order.

    ``ref_of_node`` maps canonical nodes to packed references (a row, or ``~leaf``).
    """
    n_inner = 0
    n_leaf = 0
    for i in range(bvh.node_count.shape[0]):
        if bvh.node_count[i] == 0:
            ref_of_node[i] = n_inner
            n_inner += 1
        else:
            ref_of_node[i] = ~n_leaf
            leaf_first[n_leaf] = bvh.node_first[i]
            leaf_count[n_leaf] = bvh.node_count[i]
            n_leaf += 1


@cpu_kernel(parallel=True)
def child_rows(bvh, ref_of_node, leaf_first, leaf_count, rows, pairs):
    """Fill the 16-float row of every inner node from its two children, one node per iteration.

    ``pairs`` False: the packed layout (child ``c``'s planes interleaved from column
    ``6c``, references at 12 and 13, zeros at 14 and 15); True: the pairs layout of
    :mod:`rayaccel.bvh.layouts.pairs` (plane ``k`` of child ``c`` at column ``2k + c``,
    a leaf child's reference inlined as ``~first triangle`` with its count at ``14 + c``).
    Row ``ref_of_node[i]`` belongs to inner node ``i``.
    """
    ints = rows.view(np.int32)
    for i in prange(bvh.node_count.shape[0]):
        if bvh.node_count[i] != 0:
            continue
        row = ref_of_node[i]
        for c in range(2):
            child = bvh.node_first[i] + c
            for a in range(3):
                lo_column = 4 * a + c if pairs else 6 * c + 2 * a
                rows[row, lo_column] = bvh.node_lo[child, a]
                rows[row, lo_column + (2 if pairs else 1)] = bvh.node_hi[child, a]
            ref = ref_of_node[child]
            count = 0
            if pairs and ref < 0:
                count = leaf_count[~ref]
                ref = ~leaf_first[~ref]
            ints[row, 12 + c] = ref
            ints[row, 14 + c] = count


def pack_bvh2(bvh: Bvh2, hit_rows: RealArray) -> PackedBvh2:
    """Derive the packed traversal layout from a canonical BVH.

    Parameters
    ----------
    bvh : Bvh2
        The canonical tree; it is read, not changed.
    hit_rows : (F, 9) float32 or float64
        ``TriangleMesh.hit_rows()`` of the mesh the tree was built over; the gathered
        ``tri`` keeps their dtype (float64 for a float64 mesh, traced in float64).
    """
    tri = gather_rows(hit_rows, bvh.prim_index)
    root_box = np.empty(6, dtype=REAL)
    root_box[0::2] = bvh.node_lo[0]
    root_box[1::2] = bvh.node_hi[0]
    # The root is row 0, or leaf 0 when it is the only node.
    root_ref = 0 if bvh.node_count[0] == 0 else ~0
    return PackedBvh2(
        tri=tri,
        tri_prim=np.ascontiguousarray(bvh.prim_index),
        root_box=root_box,
        root_ref=np.array([root_ref], dtype=INDEX),
        source=bvh,
    )
