"""A fan of coplanar slivers around one shared vertex, on every builder (issue 20).

Vertex 0 at the origin, the others on the unit circle, triangles ``(0, i, i + 1)``:
every triangle's box holds the origin, the boxes nest, and every triangle crosses
every cell on its way out. It broke three builders: ``bvh2.ploc`` merged one pair
per iteration (``tests/bvh/test_ploc.py``); ``bvh2.insertion`` builds a linked
tree hundreds of levels deep, and the refit of such trees lost subtrees or raised
``SystemError`` (a numba miscompilation of the growable walk stack, see
:func:`rayaccel.bvh.builders.refit._push_py`); and the kd-trees' references grew
as ``N²`` (5.2M for 4000 triangles with ``kdtree.median``) until the duplication
budget of :mod:`rayaccel.kdtree.builders.sweep` bounded them.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.bvh.builders.refit import refit_collapse
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.bvh.layouts.linked_tree import LinkedTree, linked_to_canonical
from rayaccel.errors import InvalidInputError
from rayaccel.kdtree.builders.sweep import MAX_DUPLICATION


def fan(n: int) -> rayaccel.TriangleMesh:
    """``n`` coplanar triangles around vertex 0 (a disc in ``z = 0``)."""
    angle = np.linspace(0.0, 2.0 * np.pi, n + 1)
    vertices = np.zeros((n + 2, 3))
    vertices[1:, 0] = np.cos(angle)
    vertices[1:, 1] = np.sin(angle)
    ring = np.arange(1, n + 1)
    faces = np.stack([np.zeros(n, dtype=np.int64), ring, ring + 1], axis=1)
    return rayaccel.TriangleMesh(vertices, faces, name=f"fan{n}")


def fan_rays(mesh: rayaccel.TriangleMesh, n: int = 400, seed: int = 0) -> rayaccel.RayBatch:
    """Vertical rays: random points of the disc, the centre, and points exactly on the
    spokes (``v / 2**k`` lies on the edge from the origin to ``v`` in float32)."""
    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    disc = np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
    spokes = mesh.vertices[1 + rng.integers(0, mesh.n_vertices - 1, n), :2]
    spokes = spokes * (2.0 ** -rng.integers(0, 12, n))[:, None]
    points = np.concatenate([disc, spokes, [[0.0, 0.0]]]).astype(np.float32)
    m = points.shape[0]
    down = rayaccel.RayBatch(
        np.column_stack([points, np.ones(m, np.float32)]), np.tile([0.0, 0.0, -1.0], (m, 1))
    )
    up = rayaccel.RayBatch(
        np.column_stack([points, -np.ones(m, np.float32)]), np.tile([0.0, 0.0, 1.0], (m, 1))
    )
    return reference.concat(down, up)


def _check(accel: rayaccel.Accel, rays: rayaccel.RayBatch, label: str) -> None:
    accel.validate()
    mesh = accel.mesh
    ref = reference.oracle(mesh, rays)
    assert (ref.prim >= 0).all()
    traversal = registry.default_traversal(accel.structure_name)
    tri = reference.tri9(mesh)
    reference.assert_closest_matches(tri, rays, accel.trace(rays, traversal=traversal), ref, label)
    any_hit = accel.trace(rays, query="any", traversal=traversal)
    reference.assert_any_matches(tri, rays, any_hit, ref, label)


def test_insertion_on_a_20k_fan():
    """Raised SystemError (or crashed) in the refit of its 340-level linked tree."""
    mesh = fan(20_000)
    accel = rayaccel.build(mesh, "bvh2.insertion")
    assert accel.structure.depth() <= MAX_DEPTH
    _check(accel, fan_rays(mesh), "insertion fan")


@pytest.mark.parametrize("builder", registry.keys("builder"))
def test_every_builder_on_a_fan(builder):
    mesh = fan(3000)
    accel = rayaccel.build(mesh, builder)
    _check(accel, fan_rays(mesh, seed=1), f"{builder} fan")
    if accel.structure_name == "kdtree":
        # Without the duplication budget: 1.3M references (kdtree.median, 430 per triangle).
        assert accel.structure.prim_index.size <= MAX_DUPLICATION * mesh.n_triangles


@pytest.mark.parametrize("builder", ["kdtree.sah", "kdtree.median"])
@pytest.mark.parametrize("budget", [1.0, 4.0])
def test_the_kd_duplication_budget_bounds_the_references(builder, budget):
    mesh = fan(2000)
    accel = rayaccel.build(mesh, builder, max_duplication=budget)
    assert accel.structure.prim_index.size <= budget * mesh.n_triangles
    _check(accel, fan_rays(mesh, 200, seed=2), f"{builder} fan, budget {budget}")


@pytest.mark.parametrize("builder", ["kdtree.sah", "kdtree.median"])
@pytest.mark.parametrize("value", [0.5, 0.0, -3.0])
def test_a_duplication_budget_below_one_is_refused(builder, value):
    with pytest.raises(InvalidInputError, match="max_duplication"):
        rayaccel.build(reference.cube(), builder, max_duplication=value)


def _comb(n_chains: int, depth: int) -> tuple[LinkedTree, int, int]:
    """Balanced top over ``n_chains`` subtrees ``(leaf, chain of depth depth)``.

    Returns ``(tree, root, n_refs)``. The walk of each subtree starts with a leaf
    popped, so every chain node is expanded at an even stack pointer and the stack
    grows at the first of the two pushes. Before the fix, a chain of ``3·MAX_DEPTH``
    (one growth) refitted correctly and one of ``5·MAX_DEPTH`` (two growths) did
    not; chains expanded at odd stack pointers always did.
    """
    left: list[int] = []
    right: list[int] = []

    def node(a: int = -1, b: int = -1) -> int:
        left.append(a)
        right.append(b)
        return len(left) - 1

    def subtree() -> int:
        x = node()
        for _ in range(depth):
            x = node(x, node())
        return node(node(), x)

    level = [subtree() for _ in range(n_chains)]
    while len(level) > 1:
        level = [node(level[i], level[i + 1]) for i in range(0, len(level), 2)]
    lt = np.array(left, np.int32)
    rt = np.array(right, np.int32)
    leaf = lt < 0
    n = lt.size
    first = np.zeros(n, np.int32)
    first[leaf] = np.arange(int(leaf.sum()))
    rng = np.random.default_rng(0)
    lo = rng.uniform(-1, 0, (n, 3)).astype(np.float32)
    tree = LinkedTree(
        lt,
        rt,
        lo,
        lo + np.float32(1),
        first,
        leaf.astype(np.int32),
        np.arange(int(leaf.sum()), dtype=np.int32),
    )
    return tree, level[0], int(leaf.sum())


@pytest.mark.parametrize("n_threads", [1, 2])
def test_the_refit_grows_its_walk_stack(threads, n_threads):
    """Subtrees needing over three times the initial stack (2·MAX_DEPTH + 64), many at once."""
    threads(n_threads)
    tree, root, n_refs = _comb(256, 5 * MAX_DEPTH)
    _, height, _, n_prim, _ = refit_collapse(
        np.int32(root), tree.left, tree.right, tree.lo.copy(), tree.hi.copy(), tree.count,
        np.int32(8), np.float64(1.2), np.float64(1.0), False,
    )  # fmt: skip
    assert n_prim[root] == n_refs  # was 0, or SystemError
    assert height[root] == 8 + 5 * MAX_DEPTH + 1
    bvh = linked_to_canonical(tree, root, n_refs)
    assert np.array_equal(np.sort(bvh.prim_index), np.arange(n_refs))
    assert bvh.depth() <= MAX_DEPTH
    assert numba.get_num_threads() == n_threads
