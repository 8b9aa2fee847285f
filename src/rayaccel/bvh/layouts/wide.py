"""The wide layout of a binary BVH: each row holds up to 4 (or 8) child boxes side by side.

Wald, Benthin, Boulos 2008, "Getting Rid of Packets — Efficient SIMD Single-Ray
Traversal using Multi-branching BVHs" (IEEE RT 2008) and Dammertz, Hanika, Keller
2008, "Shallow Bounding Volume Hierarchies for Fast SIMD Ray Tracing of Incoherent
Rays" (EGSR 2008): a 4-ary BVH lets one node visit test four boxes with one SIMD
instruction per slab and halves the number of traversal steps, at the price of
testing some boxes a binary traversal would have skipped; an 8-ary one (the width of
an AVX register, Embree's BVH8) halves them again.

Two collapses of the canonical binary tree:

- ``"sah"`` (the default): the SAH-optimal collapse of Ylitie, Karras, Laine 2017,
  "Efficient Incoherent Ray Traversal on GPUs Through Compressed Wide BVHs" (HPG 2017,
  §3.1). Bottom-up, each binary node ``n`` gets the least cost ``C(n, i)`` of
  representing its subtree by at most ``i`` children of a wide row (``i = 1..width``):
  ``C(n, 1)`` is the cheaper of a leaf (``C_PRIM·A(n)·N(n)``, allowed for at most
  ``MAX_LEAF`` triangles whose rows are contiguous) and a row of its own
  (``C_NODE·A(n)`` plus the best split of ``width`` slots between its two children),
  and ``C(n, i)`` the better of ``C(n, i - 1)`` and every split of ``i`` slots between
  the children. The rows are then read off top-down. Small subtrees become one leaf,
  so a row whose children would all be two-triangle leaves disappears into its parent
  and the rows come out fuller than the greedy ones.
- ``"greedy"`` (Wald et al. 2008 §3.1): a wide node starts from a binary inner node's
  two children and repeatedly replaces the inner child with the largest surface area by
  its two children until it has ``width`` children or only leaves remain; its leaves
  are the binary tree's.

A leaf is a run of triangle rows of :class:`~rayaccel.bvh.layouts.bvh2.PackedBvh2`
(which are in ``prim_index`` order), given by the layout's leaf tables: the canonical
``node_first``/``node_count`` for the greedy collapse (``~node``), tables of its own for
the SAH collapse. Rows are numbered breadth-first with the children of a row adjacent.

Row layout for width ``W`` (``8·W`` float32: 128 bytes for W = 4, 256 for W = 8): columns
``0:W`` are the children's ``lo.x``, ``W:2W`` ``hi.x``, then ``lo.y``, ``hi.y``, ``lo.z``,
``hi.z`` (structure of arrays, so a ray reads the near planes of one axis as W adjacent
floats), ``6W:7W`` the child references as int32 (``>= 0`` a wide row, ``< 0``
``~leaf``), ``7W`` the number of children, then padding. An unused lane holds the empty
box ``lo = +inf, hi = -inf``, which every ray misses, so the box test needs no lane mask.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.layouts.bvh2 import CACHE_LINE, PackedBvh2, aligned_zeros, row_arrays
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.sah import node_half_area

#: Children per wide node that the layout and the traversal support.
WIDTHS = (4, 8)
MAX_WIDTH = 8
#: The collapses of the binary tree (see the module docstring).
COLLAPSES = ("sah", "greedy")
#: The SAH collapse's costs of a row visit and of a triangle test, and its largest leaf
#: (Ylitie et al. 2017 use 1, 0.3 and 3 on GPUs; triangle costs of 0.1–1.0 and leaves
#: of 2–16 measured no better here, see docs/performance.md).
C_NODE = 1.0
C_PRIM = 0.3
MAX_LEAF = 8
#: The SAH collapse costs the subtrees this many levels below the root in parallel.
PLAN_SPLIT_DEPTH = 6


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
    leaf_first: IntArray  # leaf ``~ref``'s first triangle row
    leaf_count: IntArray  # and its number of triangles
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
    leaf_first: IntArray  # the canonical node_first (greedy) or the layout's own table
    leaf_count: IntArray

    @property
    def n_rows(self) -> int:
        """Number of wide inner rows."""
        return int(self.rows.shape[0]) if self.root_ref[0] >= 0 else 0

    def arrays(self) -> WideArrays:
        """Return the arrays kernels take as one argument."""
        return WideArrays(
            *row_arrays(self.rows, self.packed, self.leaf_first, self.leaf_count), self.root_ref
        )

    def nbytes(self) -> int:
        """Bytes of the wide rows and own leaf tables (shared arrays count where they live)."""
        own = self.leaf_first is not self.packed.source.node_first
        return int(self.rows.nbytes) + (self.leaf_first.nbytes + self.leaf_count.nbytes) * own


def store_row_py(rows, ints, w, width, node_lo, node_hi, slot, ref, count):
    """Write row ``w``: the boxes of canonical nodes ``slot[:count]`` and their references.

    Structure of arrays; the empty lanes get the box every ray misses.
    """
    for c in range(width):
        for a in range(3):
            if c < count:
                rows[w, 2 * a * width + c] = node_lo[slot[c], a]
                rows[w, (2 * a + 1) * width + c] = node_hi[slot[c], a]
            else:
                rows[w, 2 * a * width + c] = np.inf
                rows[w, (2 * a + 1) * width + c] = -np.inf
        ints[w, 6 * width + c] = ref[c] if c < count else -2147483648
    ints[w, 7 * width] = count
    for k in range(7 * width + 1, 8 * width):
        ints[w, k] = 0


store_row = cpu_inline(store_row_py)


@cpu_kernel()
def _greedy_kernel(bvh, rows, width):
    """Fill ``rows`` with the greedy wide nodes over the canonical binary tree; return how many.

    The tree's root must be an inner node. A leaf child's reference is ``~node``, its
    canonical node (whose ``node_first`` is its first triangle row).
    """
    ints = rows.view(np.int32)
    n_rows = 1
    queue = np.empty(rows.shape[0], dtype=np.int32)
    queue[0] = 0
    cand = np.empty(MAX_WIDTH, dtype=np.int32)
    ref = np.empty(MAX_WIDTH, dtype=np.int32)
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
        for c in range(count):
            ref[c] = ~cand[c]
            if bvh.node_count[cand[c]] == 0:
                queue[n_rows] = cand[c]
                ref[c] = n_rows
                n_rows += 1
        store_row(rows, ints, w, width, bvh.node_lo, bvh.node_hi, cand, ref, count)
    return n_rows


def sah_costs_py(bvh, root, width, c_node, c_prim, max_leaf, plan, sub_first, sub_count,
                 is_stop, stops, stop_cost, stop_first, stop_end, stop_count, depth):  # fmt: skip
    """Cost the collapse of the subtree at ``root`` bottom-up (Ylitie et al. 2017 §3.1).

    A post-order walk keeps the costs ``C(n, 1..width)`` of the pending subtrees on a
    stack (at most ``depth + 2`` of them). Per node it records in ``plan[n, 0]`` how
    many of a row's ``width`` slots its left child takes when ``n`` becomes a row (0:
    ``n`` becomes a leaf), in ``plan[n, j]`` (``j >= 1``) the left child's share of
    ``j + 1`` slots (0: ``j`` slots do as well), and the run of triangle rows the
    subtree covers in ``sub_first``/``sub_count``. A leaf is allowed for at most
    ``max_leaf`` triangles whose rows are contiguous (always, for a binary leaf). A
    node below ``root`` with ``is_stop`` set is not entered: its costs and run are
    ``stop_cost``/``stop_first``/``stop_end``/``stop_count`` at its index in the sorted
    ``stops``. Returns the root's ``(costs, first row, end of rows, triangles)``.
    """
    cap = depth + 2
    todo = np.empty(2 * cap + 2, dtype=np.int32)
    cost = np.empty((cap, width), dtype=np.float64)
    first = np.empty(cap, dtype=np.int64)
    end = np.empty(cap, dtype=np.int64)
    count = np.empty(cap, dtype=np.int64)
    best_of = np.empty(width, dtype=np.float64)
    todo[0] = root
    t = 1
    v = 0
    while t > 0:
        t -= 1
        x = todo[t]
        if x >= 0 and x != root and is_stop[x]:
            # Costed before: push its values.
            i = np.searchsorted(stops, x)
            for j in range(width):
                cost[v, j] = stop_cost[i, j]
            first[v] = stop_first[i]
            end[v] = stop_end[i]
            count[v] = stop_count[i]
            v += 1
            continue
        if x >= 0 and bvh.node_count[x] == 0:
            # An inner node: its children first (left on top), then the node again.
            todo[t] = ~x
            todo[t + 1] = bvh.node_first[x] + 1
            todo[t + 2] = bvh.node_first[x]
            t += 3
            continue
        node = x if x >= 0 else ~x
        area = node_half_area(bvh.node_lo, bvh.node_hi, node)
        for j in range(width):
            plan[node, j] = 0
        if x >= 0:
            # A binary leaf stays a leaf whatever the slots.
            n = np.int64(bvh.node_count[node])
            first[v] = bvh.node_first[node]
            end[v] = first[v] + n
            count[v] = n
            for j in range(width):
                cost[v, j] = c_prim * area * n
            sub_first[node] = first[v]
            sub_count[node] = n
            v += 1
            continue
        # The children's costs are the top two entries: left at v - 2, right at v - 1.
        lc = v - 2
        rc = v - 1
        n = count[lc] + count[rc]
        lo = min(first[lc], first[rc])
        hi = max(end[lc], end[rc])
        as_leaf = np.inf
        if n <= max_leaf and hi - lo == n:
            as_leaf = c_prim * area * n
        best = np.inf
        best_k = 1
        for k in range(1, width):
            c = cost[lc, k - 1] + cost[rc, width - k - 1]
            if c < best:
                best = c
                best_k = k
        as_row = c_node * area + best
        if as_leaf <= as_row:
            best_of[0] = as_leaf
        else:
            best_of[0] = as_row
            plan[node, 0] = best_k
        for j in range(1, width):
            c_j = best_of[j - 1]
            for k in range(1, j + 1):
                c = cost[lc, k - 1] + cost[rc, j - k]
                if c < c_j:
                    c_j = c
                    plan[node, j] = k
            best_of[j] = c_j
        for j in range(width):
            cost[lc, j] = best_of[j]
        first[lc] = lo
        end[lc] = hi
        count[lc] = n
        sub_first[node] = lo
        sub_count[node] = n
        v -= 1
    return cost[0], first[0], end[0], count[0]


#: Compiled once as a function of its own (the plan kernel calls it twice; inlined, the
#: parallel kernel took 10 s to compile).
sah_costs = cpu_kernel()(sah_costs_py)


@cpu_kernel(parallel=True)
def _sah_plan_kernel(
    bvh, width, depth, c_node, c_prim, max_leaf, stops, n_threads, plan, sub_first, sub_count
):  # fmt: skip
    """Fill the plan of :func:`sah_costs_py` for the whole tree.

    The subtrees at ``stops`` (sorted) are costed in parallel, ``n_threads`` workers
    taking them one at a time, then the levels above them serially.
    """
    m = stops.shape[0]
    stop_cost = np.empty((m, width), dtype=np.float64)
    stop_first = np.empty(m, dtype=np.int64)
    stop_end = np.empty(m, dtype=np.int64)
    stop_count = np.empty(m, dtype=np.int64)
    is_stop = np.zeros(bvh.node_count.shape[0], dtype=np.uint8)
    for i in range(m):
        is_stop[stops[i]] = 1
    counter = new_counter()
    for _worker in prange(worker_count(m, n_threads, True)):
        while True:
            i = next_item(counter, m)
            if i < 0:
                break
            c, f, e, n = sah_costs(
                bvh, stops[i], width, c_node, c_prim, max_leaf, plan, sub_first, sub_count,
                is_stop, stops, stop_cost, stop_first, stop_end, stop_count, depth,
            )  # fmt: skip
            for j in range(width):
                stop_cost[i, j] = c[j]
            stop_first[i] = f
            stop_end[i] = e
            stop_count[i] = n
    sah_costs(
        bvh, 0, width, c_node, c_prim, max_leaf, plan, sub_first, sub_count,
        is_stop, stops, stop_cost, stop_first, stop_end, stop_count, depth,
    )  # fmt: skip


def _inner_nodes_at_depth(tree: Any, depth: int) -> IntArray:
    """Return the sorted inner nodes ``depth`` levels below the root (the plan's subtrees)."""
    level = np.zeros(1, dtype=np.int64)
    for _ in range(depth):
        inner = level[tree.node_count[level] == 0]
        level = np.concatenate([tree.node_first[inner], tree.node_first[inner] + 1])
    return np.sort(level[tree.node_count[level] == 0]).astype(INDEX)


@cpu_kernel()
def _sah_rows_kernel(bvh, rows, width, plan, sub_first, sub_count, leaf_first, leaf_count):
    """Write the rows the plan of :func:`_sah_plan_kernel` chose; return (rows, leaves).

    Breadth-first from the root (an inner node): a row's slots are read off its
    children's plans left to right; a slot whose plan says leaf becomes ``~leaf`` with
    the subtree's run of triangle rows, any other a row of its own.
    """
    ints = rows.view(np.int32)
    n_rows = 1
    n_leaves = 0
    queue = np.empty(rows.shape[0], dtype=np.int32)
    queue[0] = 0
    pending = np.empty(2 * MAX_WIDTH + 2, dtype=np.int32)
    shares = np.empty(2 * MAX_WIDTH + 2, dtype=np.int32)
    slot = np.empty(MAX_WIDTH, dtype=np.int32)
    ref = np.empty(MAX_WIDTH, dtype=np.int32)
    for w in range(rows.shape[0]):
        if w >= n_rows:
            break
        x = queue[w]
        k = np.int32(plan[x, 0])
        pending[0] = bvh.node_first[x] + 1
        shares[0] = width - k
        pending[1] = bvh.node_first[x]
        shares[1] = k
        sp = 2
        count = 0
        while sp > 0:
            sp -= 1
            y = pending[sp]
            j = shares[sp] - 1
            while j >= 1 and plan[y, j] == 0:
                j -= 1
            if j == 0 or bvh.node_count[y] > 0:
                slot[count] = y
                count += 1
            else:
                k = np.int32(plan[y, j])
                pending[sp] = bvh.node_first[y] + 1
                shares[sp] = j + 1 - k
                pending[sp + 1] = bvh.node_first[y]
                shares[sp + 1] = k
                sp += 2
        for c in range(count):
            y = slot[c]
            if bvh.node_count[y] > 0 or plan[y, 0] == 0:
                leaf_first[n_leaves] = sub_first[y]
                leaf_count[n_leaves] = sub_count[y]
                ref[c] = ~n_leaves
                n_leaves += 1
            else:
                queue[n_rows] = y
                ref[c] = n_rows
                n_rows += 1
        store_row(rows, ints, w, width, bvh.node_lo, bvh.node_hi, slot, ref, count)
    return n_rows, n_leaves


def wide_layout(packed: PackedBvh2, width: int = 8, collapse: str = "sah") -> WideBvh:
    """Derive the ``width``-wide rows (4 or 8) of ``packed`` from its canonical tree.

    ``collapse`` is ``"sah"`` or ``"greedy"`` (see the module docstring). The packed
    layout's own rows are not needed (nor made).
    """
    if width not in WIDTHS:
        raise InvalidInputError(f"width: expected one of {WIDTHS}, got {width}")
    if collapse not in COLLAPSES:
        raise InvalidInputError(f"collapse: expected one of {COLLAPSES}, got {collapse!r}")
    root = int(packed.root_ref[0])
    tree = packed.source
    n_inner = tree.n_nodes - tree.n_leaves
    floats = row_floats(width)
    if root < 0:
        # A single leaf: no inner rows; the traversal starts at the leaf.
        rows = aligned_zeros((1, floats), REAL, CACHE_LINE)
        root_ref = np.array([root], dtype=INDEX)
        return WideBvh(rows, packed, root_ref, width, tree.node_first, tree.node_count)
    # At most one wide row per binary inner node. The zeroed buffer's pages past the rows
    # written are never touched, so the view of the rows costs no memory beyond them.
    rows = aligned_zeros((n_inner, floats), REAL, CACHE_LINE)
    root_ref = np.array([0], dtype=INDEX)
    if collapse == "greedy":
        n_rows = _greedy_kernel(tree.arrays(), rows, width)
        return WideBvh(rows[:n_rows], packed, root_ref, width, tree.node_first, tree.node_count)
    plan = np.empty((tree.n_nodes, width), dtype=np.int8)
    sub_first = np.empty(tree.n_nodes, dtype=INDEX)
    sub_count = np.empty(tree.n_nodes, dtype=INDEX)
    _sah_plan_kernel(
        tree.arrays(), width, tree.depth(), C_NODE, C_PRIM, MAX_LEAF,
        _inner_nodes_at_depth(tree, PLAN_SPLIT_DEPTH), numba.get_num_threads(), plan,
        sub_first, sub_count,
    )  # fmt: skip
    if plan[0, 0] == 0:
        # A few triangles that are cheapest as one leaf: no rows, as for a single leaf.
        root_ref = np.array([-1], dtype=INDEX)
        return WideBvh(
            rows[:1], packed, root_ref, width, sub_first[:1].copy(), sub_count[:1].copy()
        )
    leaf_first = np.empty(tree.n_leaves, dtype=INDEX)
    leaf_count = np.empty(tree.n_leaves, dtype=INDEX)
    n_rows, n_leaves = _sah_rows_kernel(
        tree.arrays(), rows, width, plan, sub_first, sub_count, leaf_first, leaf_count
    )
    return WideBvh(
        rows[:n_rows], packed, root_ref, width, leaf_first[:n_leaves].copy(),
        leaf_count[:n_leaves].copy(),
    )  # fmt: skip
