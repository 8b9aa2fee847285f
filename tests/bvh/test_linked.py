"""The parallel refit and emission of a linked tree against a serial Python oracle.

:func:`rayaccel.bvh.layouts.linked_tree.linked_to_canonical` splits the tree below a top frontier
and works on the subtrees in parallel; its output must be exactly that of the plain
serial depth-first conversion written out here, for balanced, random and chain-like
trees (the last triggers the depth guard), on 1 and 2 threads.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from rayaccel._hugepages import empty_huge, full_huge, zeros_huge
from rayaccel._jit import cpu_kernel
from rayaccel.bvh.builders.common import primitive_bounds, triangle_bounds, triangle_ref_rows
from rayaccel.bvh.builders.refit import FRONTIER_SIZE, top_frontier
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.bvh.layouts.linked_tree import LinkedTree, linked_to_canonical
from rayaccel.kernels.box_grow import grow_box_row
from rayaccel.scene.procedural import triangle_soup


def random_linked_tree(n_leaves: int, shape: str, seed: int) -> tuple[LinkedTree, int]:
    """A linked tree over ``n_leaves`` leaves (1–3 references each) and its root id.

    ``shape``: ``"random"`` merges random pairs of clusters, ``"chain"`` merges the
    newest cluster with the next leaf (depth ``n_leaves - 1``).
    """
    rng = np.random.default_rng(seed)
    n = 2 * n_leaves - 1
    left = np.full(n, -1, np.int32)
    right = np.full(n, -1, np.int32)
    lo = rng.uniform(-1, 0, (n, 3)).astype(np.float32)
    hi = (lo + rng.uniform(0, 1, (n, 3))).astype(np.float32)
    count = np.zeros(n, np.int32)
    count[:n_leaves] = rng.integers(1, 4, n_leaves)
    first = np.zeros(n, np.int32)
    first[:n_leaves] = np.concatenate(([0], np.cumsum(count[:n_leaves])[:-1]))
    prim_index = rng.permutation(int(count.sum())).astype(np.int32)
    clusters = list(range(n_leaves))
    for node in range(n_leaves, n):
        if shape == "chain":
            a, b = clusters.pop(), clusters.pop(0)
        else:
            i, j = sorted(rng.choice(len(clusters), 2, replace=False))
            a, b = clusters.pop(j), clusters.pop(i)
        left[node], right[node] = a, b
        clusters.append(node)
    return LinkedTree(left, right, lo, hi, first, count, prim_index), n - 1


def serial_canonical(tree: LinkedTree, root: int) -> tuple[np.ndarray, ...]:
    """The serial conversion without collapsing: refit, depth-first emission, depth guard."""
    left, right, count = tree.left, tree.right, tree.count
    lo, hi = tree.lo.copy(), tree.hi.copy()
    n_leaf, height = {}, {}
    order, stack = [], [root]
    while stack:
        x = stack.pop()
        order.append(x)
        if left[x] >= 0:
            stack += [left[x], right[x]]
    for x in reversed(order):
        if left[x] < 0:
            n_leaf[x], height[x] = 1, 0
        else:
            a, b = left[x], right[x]
            lo[x], hi[x] = np.minimum(lo[a], lo[b]), np.maximum(hi[a], hi[b])
            n_leaf[x], height[x] = n_leaf[a] + n_leaf[b], 1 + max(height[a], height[b])

    def leaves_under(x: int) -> list[int]:
        out, stack = [], [x]
        while stack:
            y = stack.pop()
            if left[y] < 0:
                out.append(y)
            else:
                stack += [right[y], left[y]]
        return out

    n_out = 2 * n_leaf[root] - 1
    out_lo, out_hi = np.empty((n_out, 3), np.float32), np.empty((n_out, 3), np.float32)
    out_first, out_count = np.empty(n_out, np.int32), np.empty(n_out, np.int32)
    out_prim: list[int] = []
    next_id = 1
    # Work items: ("node", id, slot, depth) or ("range", leaf list, slot, depth).
    work = [("node", root, 0, 0)]
    while work:
        kind, item, slot, depth = work.pop()
        if kind == "range" and len(item) > 1:
            mid = len(item) // 2
            out_first[slot], out_count[slot] = next_id, 0
            work += [("range", item[mid:], next_id + 1, depth + 1)]
            work += [("range", item[:mid], next_id, depth + 1)]
            next_id += 2
            continue
        x = item[0] if kind == "range" else item
        if left[x] < 0:
            out_lo[slot], out_hi[slot] = lo[x], hi[x]
            out_first[slot], out_count[slot] = len(out_prim), count[x]
            out_prim += list(tree.prim_index[tree.first[x] : tree.first[x] + count[x]])
            continue
        if (
            depth + height[x] > MAX_DEPTH
            and depth + math.ceil(math.log2(n_leaf[x])) >= MAX_DEPTH - 1
        ):
            work.append(("range", leaves_under(x), slot, depth))
            continue
        out_first[slot], out_count[slot] = next_id, 0
        work += [("node", right[x], next_id + 1, depth + 1), ("node", left[x], next_id, depth + 1)]
        next_id += 2
    for i in range(n_out - 1, -1, -1):
        if out_count[i] == 0:
            c = out_first[i]
            out_lo[i] = np.minimum(out_lo[c], out_lo[c + 1])
            out_hi[i] = np.maximum(out_hi[c], out_hi[c + 1])
    return out_lo, out_hi, out_first, out_count, np.array(out_prim, np.int32)


@pytest.mark.parametrize("n_threads", [1, 2])
@pytest.mark.parametrize(("shape", "n_leaves"), [("random", 1500), ("random", 40), ("chain", 600)])
def test_parallel_conversion_equals_the_serial_one(threads, n_threads, shape, n_leaves):
    threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
    tree, root = random_linked_tree(n_leaves, shape, seed=n_leaves)
    expected = serial_canonical(tree, root)
    n_prims = int(tree.count.sum())
    bvh = linked_to_canonical(tree, root, n_prims)
    got = (bvh.node_lo, bvh.node_hi, bvh.node_first, bvh.node_count, bvh.prim_index)
    for name, a, b in zip(("lo", "hi", "first", "count", "prim"), got, expected, strict=True):
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert bvh.depth() <= MAX_DEPTH


@cpu_kernel()
def _frontier_of(root, left, right):
    # Called as the package's kernels call it (a literal target), so it keeps one signature.
    return top_frontier(root, left, right, FRONTIER_SIZE)


@pytest.mark.parametrize(("shape", "n_leaves"), [("random", 2000), ("chain", 300), ("random", 3)])
def test_top_frontier_cuts_the_tree_into_disjoint_subtrees(shape, n_leaves):
    tree, root = random_linked_tree(n_leaves, shape, seed=7)
    frontier, top = _frontier_of(np.int32(root), tree.left, tree.right)
    # Every leaf lies under exactly one frontier node; top nodes are inner, parents first.
    owner = {}
    for f in frontier:
        stack = [f]
        while stack:
            x = stack.pop()
            assert x not in owner
            owner[x] = f
            if tree.left[x] >= 0:
                stack += [tree.left[x], tree.right[x]]
    assert sum(1 for x in owner if tree.left[x] < 0) == n_leaves
    assert not set(top) & set(owner)
    seen = {root}
    for x in top:
        assert tree.left[x] >= 0
        assert x in seen
        seen |= {tree.left[x], tree.right[x]}
    assert set(frontier) <= seen
    if shape == "random":
        assert len(frontier) >= min(FRONTIER_SIZE, n_leaves)


@cpu_kernel()
def _huge_arrays(n):
    a = empty_huge(n, np.int32)
    a[:] = 3
    return a, zeros_huge((n, 3), np.float64), full_huge(n, -1, np.int8)


@pytest.mark.parametrize("n", [0, 5, 3_000_000])
def test_huge_page_arrays_behave_like_numpy(n):
    a, z, f = _huge_arrays(n)
    assert a.shape == (n,)
    assert a.dtype == np.int32
    assert (a == 3).all()
    assert z.shape == (n, 3)
    assert z.dtype == np.float64
    assert not z.any()
    assert f.dtype == np.int8
    assert (f == -1).all()


@cpu_kernel()
def _grow_all(bins, rows, slots):
    for i in range(rows.shape[0]):
        grow_box_row(bins, i % 3, slots[i], rows, i)


def test_vector_box_grow_matches_scalar_min_max():
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(500, 8)).astype(np.float32)
    rows[::7, 0] = -0.0
    slots = rng.integers(0, 4, 500)
    bins = np.empty((3, 4, 8), np.float32)
    bins[..., :4], bins[..., 4:] = np.inf, -np.inf
    expected = bins.copy()
    for i, row in enumerate(rows):
        box = expected[i % 3, slots[i]]
        box[:3] = np.minimum(box[:3], row[:3])
        box[4:7] = np.maximum(box[4:7], row[4:7])
    _grow_all(bins, rows, slots)
    np.testing.assert_array_equal(bins[..., [0, 1, 2, 4, 5, 6]], expected[..., [0, 1, 2, 4, 5, 6]])


def test_triangle_bounds_read_through_faces():
    mesh = triangle_soup(300, seed=5)
    lo, hi, _ = primitive_bounds(mesh.triangles())
    lo2, hi2 = triangle_bounds(mesh.vertices, mesh.faces)
    rows = triangle_ref_rows(mesh.vertices, mesh.faces)
    np.testing.assert_array_equal(lo, lo2)
    np.testing.assert_array_equal(hi, hi2)
    np.testing.assert_array_equal(rows[:, 0:3], lo)
    np.testing.assert_array_equal(rows[:, 4:7], hi)
    np.testing.assert_array_equal(rows.view(np.int32)[:, 3], np.arange(300))
