"""BVH builders (every registered ``bvh2`` builder) and ``Bvh2`` invariants and validation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2, pack_bvh2
from rayaccel.errors import InvalidInputError, StructureInvariantError
from rayaccel.rays.batch import RayBatch

BUILDERS = [pytest.param(k, id=k) for k in registry.keys("builder", "bvh2")]


def _soup(n: int, seed: int = 0) -> rayaccel.TriangleMesh:
    rng = np.random.default_rng(seed)
    centres = rng.random((n, 1, 3)) * 10
    tri = centres + rng.normal(size=(n, 3, 3)) * 0.2
    return rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3))


MESHES = {
    "soup500": lambda: _soup(500),
    "icosphere2": lambda: reference.icosphere(2),
    "grid": lambda: reference.grid_plane(10),
    "teapot": lambda: rayaccel.scenes.get("teapot"),
}


def _leaf_rows(bvh: Bvh2) -> np.ndarray:
    return np.flatnonzero(bvh.node_count > 0)


def _check_tight(bvh: Bvh2, triangles: np.ndarray) -> None:
    """Leaf boxes are the union of their triangles; inner boxes the union of children."""
    lo_t, hi_t = triangles.min(axis=1), triangles.max(axis=1)
    for leaf in _leaf_rows(bvh):
        prims = bvh.prim_index[bvh.node_first[leaf]:bvh.node_first[leaf] + bvh.node_count[leaf]]
        assert np.array_equal(bvh.node_lo[leaf], lo_t[prims].min(axis=0))
        assert np.array_equal(bvh.node_hi[leaf], hi_t[prims].max(axis=0))
    inner = np.flatnonzero(bvh.node_count == 0)
    left = bvh.node_first[inner]
    assert np.array_equal(bvh.node_lo[inner],
                          np.minimum(bvh.node_lo[left], bvh.node_lo[left + 1]))
    assert np.array_equal(bvh.node_hi[inner],
                          np.maximum(bvh.node_hi[left], bvh.node_hi[left + 1]))


@pytest.mark.parametrize("name", list(MESHES))
@pytest.mark.parametrize("builder", BUILDERS)
@pytest.mark.parametrize("leaf", [1, 4, 8])
def test_structure_invariants(builder, name, leaf):
    mesh = MESHES[name]()
    accel = rayaccel.build(mesh, builder, max_leaf_size=leaf)
    bvh = accel.structure
    assert isinstance(bvh, Bvh2)
    bvh.validate(mesh.triangles())
    assert bvh.n_prims == mesh.n_triangles
    # Every primitive at least once (exactly once without spatial splits), in leaves of
    # at most max_leaf_size.
    assert np.array_equal(np.unique(bvh.prim_index), np.arange(mesh.n_triangles))
    assert bvh.node_count.max() <= leaf
    assert bvh.node_count.sum() == bvh.n_refs
    # Binary tree: n_nodes = 2 * n_leaves - 1.
    assert bvh.n_nodes == 2 * bvh.n_leaves - 1
    assert 0 < bvh.depth() <= MAX_DEPTH
    if bvh.n_refs == mesh.n_triangles:
        _check_tight(bvh, mesh.triangles())
    info = accel.info()
    assert info["n_nodes"] == bvh.n_nodes
    assert info["depth"] == bvh.depth()
    assert info["mean_leaf_size"] == pytest.approx(bvh.n_refs / bvh.n_leaves)


@pytest.mark.parametrize("builder", BUILDERS)
def test_leaf_size_one_gives_one_prim_per_leaf(builder):
    mesh = _soup(300)
    bvh = rayaccel.build(mesh, builder, max_leaf_size=1).structure
    assert (bvh.node_count[_leaf_rows(bvh)] == 1).all()
    assert bvh.n_nodes == 2 * bvh.n_refs - 1


@pytest.mark.parametrize("builder", BUILDERS)
def test_deterministic(builder):
    mesh = _soup(2000, seed=3)
    a = rayaccel.build(mesh, builder).structure
    b = rayaccel.build(mesh, builder).structure
    for field in ("node_lo", "node_hi", "node_first", "node_count", "prim_index"):
        assert getattr(a, field).tobytes() == getattr(b, field).tobytes(), field


@pytest.mark.parametrize("builder", BUILDERS)
def test_single_triangle_is_a_root_leaf(builder):
    mesh = rayaccel.TriangleMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    bvh = rayaccel.build(mesh, builder).structure
    bvh.validate(mesh.triangles())
    assert bvh.n_nodes == 1
    assert bvh.node_count[0] == 1
    assert bvh.depth() == 0
    assert np.array_equal(bvh.node_lo[0], [0, 0, 0])
    assert np.array_equal(bvh.node_hi[0], [1, 1, 0])


@pytest.mark.parametrize("builder", BUILDERS)
@pytest.mark.parametrize("kind", ["identical", "collinear", "points", "coplanar"])
def test_degenerate_inputs_build(builder, kind):
    n = 3000
    if kind == "identical":
        tri = np.broadcast_to([[0, 0, 0], [1, 0, 0], [0, 1, 0]], (n, 3, 3))
    elif kind == "collinear":
        x = np.arange(n, dtype=np.float64)[:, None]
        tri = np.stack([np.hstack([x, x, x]), np.hstack([x + 1, x + 1, x + 1]),
                        np.hstack([x + 2, x + 2, x + 2])], axis=1)
    elif kind == "points":
        tri = np.repeat(np.random.default_rng(0).random((n, 1, 3)), 3, axis=1)
    else:
        tri = np.random.default_rng(1).random((n, 3, 3))
        tri[:, :, 2] = 0.5
    mesh = rayaccel.TriangleMesh(np.ascontiguousarray(tri).reshape(-1, 3),
                                 np.arange(3 * n).reshape(-1, 3))
    bvh = rayaccel.build(mesh, builder, max_leaf_size=2).structure
    bvh.validate(mesh.triangles())
    assert bvh.depth() <= MAX_DEPTH
    assert bvh.node_count.max() <= 2


@pytest.mark.parametrize("builder", BUILDERS)
def test_sah_cost_is_sane(builder):
    mesh = _soup(4000, seed=5)
    bvh = rayaccel.build(mesh, builder).structure
    cost = bvh.sah_cost()
    # Far better than one leaf holding everything, and no better than a perfect split.
    assert 1.0 < cost < 0.2 * mesh.n_triangles
    assert bvh.sah_cost(inner_cost=0.0) <= cost


def test_sweep_sah_is_at_least_as_good_as_binned_on_average():
    keys = registry.keys("builder", "bvh2")
    if not {"bvh2.sweep_sah", "bvh2.binned_sah"} <= set(keys):
        pytest.skip("needs both SAH builders")
    costs = {k: [] for k in ("bvh2.sweep_sah", "bvh2.binned_sah")}
    for seed in range(3):
        mesh = _soup(3000, seed=seed)
        for key in costs:
            costs[key].append(rayaccel.build(mesh, key).structure.sah_cost())
    assert np.mean(costs["bvh2.sweep_sah"]) <= np.mean(costs["bvh2.binned_sah"]) * 1.02


def test_binned_options_are_applied_and_checked():
    mesh = _soup(1500)
    for bins in (2, 8, 256):
        rayaccel.build(mesh, "bvh2.binned_sah", n_bins=bins).validate()
    # A low parallel threshold exercises the parallel top phase.
    rayaccel.build(mesh, "bvh2.binned_sah", parallel_threshold=64).validate()
    for bad in ({"n_bins": 1}, {"n_bins": 257}, {"max_leaf_size": 0},
                {"max_leaf_size": 65}, {"intersection_cost": 0.0},
                {"parallel_threshold": 1}):
        with pytest.raises(InvalidInputError):
            rayaccel.build(mesh, "bvh2.binned_sah", **bad)


def test_sah_cost_by_hand():
    # Root over two unit-box leaves of one prim each.
    bvh = Bvh2(
        node_lo=np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0]], np.float32),
        node_hi=np.array([[2, 1, 1], [1, 1, 1], [2, 1, 1]], np.float32),
        node_first=np.array([1, 0, 1], np.int32),
        node_count=np.array([0, 1, 1], np.int32),
        prim_index=np.array([0, 1], np.int32),
        n_prims=2,
    )
    bvh.validate()
    area_root, area_leaf = 2 * (2 + 1 + 2), 6.0
    expected = (1.2 * area_root + 1.0 * 2 * area_leaf) / area_root
    assert bvh.sah_cost() == pytest.approx(expected)
    assert bvh.depth() == 1
    assert list(bvh.depths()) == [0, 1, 1]
    assert bvh.nbytes() == 3 * 32 + 2 * 4


def _good_tree():
    mesh = _soup(64, seed=9)
    return mesh, rayaccel.build(mesh, "bvh2.sweep_sah", max_leaf_size=2).structure


def _broken(bvh: Bvh2, **changes) -> Bvh2:
    fields = {f.name: getattr(bvh, f.name) for f in dataclasses.fields(bvh)}
    fields = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in fields.items()}
    fields.update(changes)
    return Bvh2(**fields)


def test_validate_catches_corruption():
    mesh, bvh = _good_tree()
    tri = mesh.triangles()
    bvh.validate(tri)
    inner = int(np.flatnonzero(bvh.node_count == 0)[1])
    leaf = int(_leaf_rows(bvh)[0])
    cases = {}
    lo = bvh.node_lo.copy()
    lo[bvh.node_first[inner]] -= 1.0  # child pokes out of its parent
    cases["child outside parent"] = _broken(bvh, node_lo=lo)
    hi = bvh.node_hi.copy()
    hi[leaf] = bvh.node_lo[leaf] - 1.0  # lo > hi
    cases["lo > hi"] = _broken(bvh, node_hi=hi)
    nan = bvh.node_lo.copy()
    nan[leaf, 0] = np.nan
    cases["non-finite"] = _broken(bvh, node_lo=nan)
    first = bvh.node_first.copy()
    first[inner] = 0  # cycle back to the root
    cases["cycle"] = _broken(bvh, node_first=first)
    first = bvh.node_first.copy()
    first[inner] = bvh.n_nodes + 5
    cases["child out of range"] = _broken(bvh, node_first=first)
    index = bvh.prim_index.copy()
    index[0] = index[1]  # a primitive twice, another missing
    cases["duplicate prim"] = _broken(bvh, prim_index=index)
    index = bvh.prim_index.copy()
    index[0] = bvh.n_prims
    cases["prim out of range"] = _broken(bvh, prim_index=index)
    count = bvh.node_count.copy()
    count[leaf] += 1
    cases["leaf range overlaps"] = _broken(bvh, node_count=count)
    cases["wrong dtype"] = _broken(bvh, node_first=bvh.node_first.astype(np.int64))
    for name, broken in cases.items():
        try:
            broken.validate(tri)
        except StructureInvariantError:
            continue
        pytest.fail(f"validate() accepted: {name}")
    # A leaf box that does not contain its triangles (only detectable with triangles).
    lo = bvh.node_lo.copy()
    hi = bvh.node_hi.copy()
    mid = (lo[leaf] + hi[leaf]) / 2
    lo[leaf], hi[leaf] = mid, mid
    shrunk = _broken(bvh, node_lo=lo, node_hi=hi)
    with pytest.raises(StructureInvariantError, match="outside leaf"):
        shrunk.validate(tri)


def test_validate_rejects_too_deep_chain():
    bvh, _ = chain_bvh(MAX_DEPTH + 4)
    with pytest.raises(StructureInvariantError, match="deeper"):
        bvh.validate()


def chain_bvh(depth: int) -> tuple[Bvh2, rayaccel.TriangleMesh]:
    """A caterpillar tree: each inner node has an inner child 0 and a leaf child 1.

    All boxes are the same, so a traversal descending child 0 first pushes one entry
    per level. ``depth`` inner levels over ``depth + 1`` identical triangles.
    """
    n_prims = depth + 1
    n_nodes = 2 * depth + 1
    first = np.empty(n_nodes, np.int32)
    count = np.zeros(n_nodes, np.int32)
    prim_slot = 0
    node = 0
    # Node ids: inner chain nodes 0, 1, 3, 5, ... each with children (2k+1, 2k+2).
    for level in range(depth):
        first[node] = 2 * level + 1
        leaf = 2 * level + 2
        count[leaf] = 1
        first[leaf] = prim_slot
        prim_slot += 1
        node = 2 * level + 1
    count[node] = 1
    first[node] = prim_slot
    # Reorder prim slots so leaves tile prim_index in depth-first order.
    order = []
    stack = [0]
    while stack:
        k = stack.pop()
        if count[k]:
            order.append(k)
        else:
            stack += [first[k] + 1, first[k]]
    for slot, leaf in enumerate(order):
        first[leaf] = slot
    tri = np.tile([[0, 0, 0], [1, 0, 0], [0, 1, 0]], (n_prims, 1)).astype(np.float64)
    mesh = rayaccel.TriangleMesh(tri, np.arange(3 * n_prims).reshape(-1, 3))
    lo = np.tile(np.float32([0, 0, 0]), (n_nodes, 1))
    hi = np.tile(np.float32([1, 1, 0]), (n_nodes, 1))
    bvh = Bvh2(lo, hi, first, count, np.arange(n_prims, dtype=np.int32), n_prims)
    return bvh, mesh


def test_chain_helper_is_a_valid_tree_when_shallow():
    bvh, mesh = chain_bvh(10)
    bvh.validate(mesh.triangles())
    assert bvh.depth() == 10


@pytest.mark.parametrize("builder", BUILDERS)
def test_packed_layout_matches_canonical(builder):
    mesh = MESHES["icosphere2"]()
    bvh = rayaccel.build(mesh, builder, max_leaf_size=2).structure
    packed = pack_bvh2(bvh, mesh.hit_rows())
    arrays = packed.arrays()
    n_inner = bvh.n_nodes - bvh.n_leaves
    assert arrays.inner_box.shape[0] == n_inner
    assert arrays.leaf_first.shape[0] == bvh.n_leaves
    assert np.array_equal(arrays.tri_prim, bvh.prim_index)
    assert np.array_equal(arrays.tri.reshape(-1, 3, 3), mesh.triangles()[bvh.prim_index])
    assert np.array_equal(arrays.root_box[0::2], bvh.node_lo[0])
    assert np.array_equal(arrays.root_box[1::2], bvh.node_hi[0])
    assert packed.nbytes() > 0


def test_default_queries_do_not_make_the_packed_rows():
    """The wide (and pairs) rows come from the canonical tree: the packed rows stay unmade."""
    mesh = MESHES["icosphere2"]()
    accel = rayaccel.build(mesh, "bvh2.binned_sah")
    rays = RayBatch(np.zeros((64, 3)), np.random.default_rng(0).normal(size=(64, 3)))
    hits = {t: accel.trace(rays, traversal=t) for t in ("bvh2.packet", "bvh2.wide")}
    # Packets and single rays share the 8-wide rows: no pairs rows either.
    assert "bvh2.pairs" not in accel.info()["layouts"]
    hits["bvh2.stack"] = accel.trace(rays, traversal="bvh2.stack")
    assert "bvh2.pairs" in accel.info()["layouts"]
    packed = accel.derived("bvh2.packed")
    assert not packed.has_rows
    before = packed.nbytes()
    assert np.array_equal(hits["bvh2.wide"].t, hits["bvh2.stack"].t)
    # A traversal over the packed rows makes them on first use, from the same tree.
    assert np.array_equal(accel.trace(rays, traversal="bvh2.bitstack").t, hits["bvh2.stack"].t)
    assert packed.has_rows
    assert packed.nbytes() == before + packed.rows.nbytes
