"""kd-trees: builder invariants, degenerate input, and every traversal against the oracle.

The registry-driven conformance suite checks every kd builder and traversal on the
procedural and bundled scenes; here the kd-specific edge cases: triangles in split
planes and flat cells, rays lying in split planes or starting on them, axis-parallel
rays with ±0 components, many copies of one triangle, termination of the stackless
traversals, short-stack sizes, and ropes against the stack bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.errors import InvalidInputError, StructureInvariantError
from rayaccel.kdtree.builders import sweep
from rayaccel.kdtree.layouts.kdtree import (
    LEAF_AXIS,
    MAX_DEPTH,
    KdTree,
    max_depth_for,
    nodes_with_leaf_ranges,
)
from rayaccel.kdtree.layouts.node_order import (
    LINE_BYTES,
    PAIRS_PER_BLOCK,
    blocked_node_order,
    line_aligned_copy,
)
from rayaccel.kdtree.traverse.ropes import rope_layout
from rayaccel.rays.batch import RayBatch

BUILDS = [
    ("kdtree.sah", {}),
    ("kdtree.sah", {"perfect_splits": False}),
    ("kdtree.median", {}),
]
TRAVERSALS = [
    ("kdtree.stack", {}),
    ("kdtree.stack", {"order": "position"}),
    ("kdtree.restart", {}),
    ("kdtree.backtrack", {}),
    ("kdtree.short_stack", {}),
    ("kdtree.ropes", {}),
    ("kdtree.ropes", {"optimize": False}),
]
STACKLESS = ["kdtree.restart", "kdtree.backtrack", "kdtree.short_stack", "kdtree.ropes"]


def _ids(pairs):
    return [f"{k}-{'-'.join(f'{a}={b}' for a, b in o.items())}" if o else k for k, o in pairs]


@pytest.fixture(scope="module")
def sphere_accels():
    mesh = reference.icosphere(2)
    return {(k, tuple(o.items())): rayaccel.build(mesh, k, **o) for k, o in BUILDS}


def _check_all(accel, rays, label=""):
    """Every kd traversal returns the oracle's closest and any hits."""
    mesh = accel.mesh
    ref = reference.oracle(mesh, rays)
    tri9 = reference.tri9(mesh)
    for key, opts in TRAVERSALS:
        closest = accel.trace(rays, traversal=key, **opts)
        reference.assert_closest_matches(tri9, rays, closest, ref, f"{label} {key} {opts}")
        any_hit = accel.trace(rays, query="any", traversal=key, **opts)
        reference.assert_any_matches(tri9, rays, any_hit, ref, f"{label} {key} {opts}")
    return ref


def test_registered():
    assert registry.default_builder("kdtree") == "kdtree.sah"
    assert registry.default_traversal("kdtree") == "kdtree.stack"
    keys = set(registry.keys("traversal", "kdtree"))
    assert {"kdtree.stack", *STACKLESS} <= keys


@pytest.mark.parametrize(("key", "opts"), BUILDS, ids=_ids(BUILDS))
def test_builders_validate_and_report(sphere_accels, key, opts):
    accel = sphere_accels[key, tuple(opts.items())]
    accel.validate()
    kd = accel.structure
    assert isinstance(kd, KdTree)
    info = accel.info()
    for name in ("n_nodes", "n_leaves", "n_empty_leaves", "n_refs", "depth", "sah", "bytes"):
        assert name in info, name
    assert info["n_refs"] >= accel.mesh.n_triangles
    assert info["n_nodes"] == 2 * info["n_leaves"] - 1
    assert info["depth"] <= max_depth_for(accel.mesh.n_triangles)
    assert kd.nbytes() == 8 * kd.n_nodes + 8 * kd.n_leaves + 4 * kd.n_refs


def test_perfect_splits_list_fewer_references(sphere_accels):
    perfect = sphere_accels["kdtree.sah", ()].structure
    boxes = sphere_accels["kdtree.sah", (("perfect_splits", False),)].structure
    assert perfect.perfect_splits
    assert not boxes.perfect_splits
    assert perfect.sah_cost() < boxes.sah_cost()


def test_trace_layout_leaves_carry_their_ranges(sphere_accels):
    """The trace layout's leaves read (first, count << 2 | 3); inner nodes are the tree's."""
    kd = sphere_accels["kdtree.sah", ()].structure
    words = nodes_with_leaf_ranges(kd).view(np.int32)
    bits = kd.node_bits
    leaf = (bits & 3) == LEAF_AXIS
    assert leaf.any()
    assert (~leaf).any()
    assert np.array_equal(words[~leaf], kd.nodes.view(np.int32)[~leaf])
    ids = bits[leaf] >> 2
    assert np.array_equal(words[leaf, 0], kd.leaf_first[ids])
    assert np.array_equal(words[leaf, 1], (kd.leaf_count[ids] << 2) | LEAF_AXIS)
    # The ropes find a leaf node's box and ropes through their own index.
    ropes = rope_layout(kd, True)
    assert np.array_equal(ropes.leaf_index[leaf], ids)
    assert (ropes.leaf_index[~leaf] == -1).all()


def test_validate_catches_a_missing_reference(sphere_accels):
    kd = sphere_accels["kdtree.sah", ()].structure
    leaf = int(np.argmax(kd.leaf_count))
    count = kd.leaf_count.copy()
    count[leaf] -= 1
    broken = KdTree(kd.nodes, kd.leaf_first, count, kd.prim_index, kd.lo, kd.hi, kd.n_prims)
    with pytest.raises(StructureInvariantError):
        broken.validate(reference.icosphere(2).triangles())
    bad_split = kd.nodes.copy()
    bad_split[0, 0] = kd.hi[kd.node_bits[0] & 3] + 1
    broken = KdTree(
        bad_split, kd.leaf_first, kd.leaf_count, kd.prim_index, kd.lo, kd.hi, kd.n_prims
    )
    with pytest.raises(StructureInvariantError, match="split outside"):
        broken.validate()


def test_options_checked():
    mesh = reference.icosphere(1)
    with pytest.raises(InvalidInputError):
        rayaccel.build(mesh, "kdtree.sah", empty_bonus=0.0)
    with pytest.raises(InvalidInputError):
        rayaccel.build(mesh, "kdtree.sah", max_depth=MAX_DEPTH + 1)
    with pytest.raises(InvalidInputError):
        rayaccel.build(mesh, "kdtree.median", max_leaf_size=0)
    accel = rayaccel.build(mesh, "kdtree.sah")
    rays = RayBatch(np.zeros((1, 3)), np.ones((1, 3)))
    with pytest.raises(InvalidInputError):
        accel.trace(rays, traversal="kdtree.stack", order="sideways")
    with pytest.raises(InvalidInputError):
        accel.trace(rays, traversal="kdtree.short_stack", size=0)


@pytest.mark.parametrize(("key", "opts"), BUILDS, ids=_ids(BUILDS))
def test_every_traversal_matches_the_oracle(sphere_accels, key, opts):
    accel = sphere_accels[key, tuple(opts.items())]
    rays = reference.mixed_rays(accel.mesh, 700, seed=3)
    _check_all(accel, rays, key)


def _split_plane_rays(kd: KdTree, n: int, seed: int) -> RayBatch:
    """Rays lying in the first inner splits (zero component, ±0) and starting on them."""
    rng = np.random.default_rng(seed)
    inner = np.flatnonzero((kd.node_bits & 3) != 3)[:16]
    origins, directions = [], []
    lo, hi = kd.lo.astype(np.float64), kd.hi.astype(np.float64)
    for node in inner:
        axis = int(kd.node_bits[node] & 3)
        split = float(kd.node_split[node])
        o = lo + rng.random((n, 3)) * (hi - lo)
        o[:, axis] = split
        d = rng.normal(size=(n, 3))
        in_plane = d.copy()
        in_plane[:, axis] = np.where(rng.random(n) < 0.5, 0.0, -0.0)
        origins += [o, o]
        directions += [in_plane, d]
    return RayBatch(np.concatenate(origins), np.concatenate(directions))


@pytest.mark.parametrize(("key", "opts"), BUILDS, ids=_ids(BUILDS))
def test_rays_in_and_from_split_planes(sphere_accels, key, opts):
    accel = sphere_accels[key, tuple(opts.items())]
    rays = _split_plane_rays(accel.structure, 24, seed=5)
    ref = _check_all(accel, rays, key)
    assert ref.hit.any()


def test_all_triangles_in_one_plane():
    """A flat scene: every triangle planar on z; rays from both sides and in the plane."""
    mesh = reference.grid_plane(8, z=0.5)
    for key, opts in BUILDS:
        accel = rayaccel.build(mesh, key, **opts)
        accel.validate()
        rng = np.random.default_rng(1)
        n = 300
        target = np.column_stack([rng.random(n) * 8, rng.random(n) * 8, np.full(n, 0.5)])
        # Exactly at vertices and edges of the grid too.
        target[: n // 3, :2] = np.round(target[: n // 3, :2] * 2) / 2
        o = target + reference.random_unit(rng, n) * 3
        in_plane_o = np.column_stack(
            [rng.random(n) * 10 - 1, rng.random(n) * 10 - 1, np.full(n, 0.5)]
        )
        in_plane_d = np.column_stack(
            [rng.normal(size=n), rng.normal(size=n), np.where(rng.random(n) < 0.5, 0.0, -0.0)]
        )
        rays = RayBatch(np.concatenate([o, in_plane_o]), np.concatenate([target - o, in_plane_d]))
        ref = _check_all(accel, rays, key)
        assert ref.hit[:n].mean() > 0.9


def _canonical(kd: KdTree, node: int = 0) -> tuple:
    """The tree below ``node`` as nested tuples, independent of node numbering."""
    bits = int(kd.node_bits[node])
    if bits & 3 == LEAF_AXIS:
        leaf = bits >> 2
        first = kd.leaf_first[leaf]
        return tuple(sorted(kd.prim_index[first : first + kd.leaf_count[leaf]].tolist()))
    child = bits >> 2
    return (bits & 3, float(kd.nodes[node, 0]), _canonical(kd, child), _canonical(kd, child + 1))


def test_blocked_node_order_depends_on_the_tree_alone(sphere_accels):
    """Any numbering of a tree's child pairs comes out as the builder's blocked order: the
    same tree, the root's children at 1 and 2, the first treelet breadth first; the trace
    layout's copy puts node 1 at the start of a cache line."""
    kd = sphere_accels["kdtree.sah", ()].structure
    words = kd.nodes.view(np.int32)
    n_pairs = (kd.n_nodes - 1) // 2
    perm = np.random.default_rng(5).permutation(n_pairs)
    new = np.concatenate([[0], (1 + 2 * perm[:, None] + np.arange(2)).reshape(-1)])
    shuffled = np.empty_like(kd.nodes)
    shuffled[new] = kd.nodes
    inner = (kd.node_bits & 3) != LEAF_AXIS
    shuffled.view(np.int32)[new[inner], 1] = (new[kd.node_bits[inner] >> 2] << 2) | (
        kd.node_bits[inner] & 3
    )
    moved = KdTree(shuffled, kd.leaf_first, kd.leaf_count, kd.prim_index, kd.lo, kd.hi, kd.n_prims)
    assert _canonical(moved) == _canonical(kd)
    assert not np.array_equal(shuffled, kd.nodes)
    assert np.array_equal(blocked_node_order(shuffled), kd.nodes)
    with pytest.raises(StructureInvariantError, match="2 kd nodes are not reached"):
        blocked_node_order(np.concatenate([kd.nodes, kd.nodes[-2:]]))
    looped = kd.nodes.copy()
    inner_nodes = np.flatnonzero(inner)
    looped.view(np.int32)[inner_nodes[-1], 1] = (1 << 2) | 0  # back to the root's children
    with pytest.raises(StructureInvariantError, match="not a tree"):
        blocked_node_order(looped)
    looped.view(np.int32)[inner_nodes[-1], 1] = (kd.n_nodes << 2) | 0  # past the end
    with pytest.raises(StructureInvariantError, match="not a tree"):
        blocked_node_order(looped)
    assert words[0, 1] >> 2 == 1
    # The first treelet holds the root's children and the pairs below them, breadth first.
    first_pairs = [1]
    for pair in first_pairs:
        for node in (pair, pair + 1):
            if (words[node, 1] & 3) != LEAF_AXIS and len(first_pairs) < PAIRS_PER_BLOCK:
                first_pairs.append(int(words[node, 1] >> 2))
    assert first_pairs == list(range(1, 1 + 2 * len(first_pairs), 2))
    copy = line_aligned_copy(kd.nodes)
    assert np.array_equal(copy, kd.nodes)
    assert (copy.ctypes.data + copy.strides[0]) % LINE_BYTES == 0


@pytest.mark.parametrize("key", ["kdtree.sah", "kdtree.median"])
def test_parallel_build_is_the_serial_tree(key, monkeypatch):
    """Frontier subtrees built on a thread pool give the serial build's tree and the
    same arrays for every thread count."""
    mesh = reference.icosphere(3)
    serial = rayaccel.build(mesh, key, parallel_threshold=0).structure
    frontier_builds = []
    build_frontier = sweep._build_frontier

    def counted(*args):
        frontier_builds.append(1)
        return build_frontier(*args)

    monkeypatch.setattr(sweep, "_build_frontier", counted)
    threads = numba.get_num_threads()
    trees = []
    for count in sorted({1, threads, 2}):
        numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))
        try:
            trees.append(rayaccel.build(mesh, key, parallel_threshold=16).structure)
        finally:
            numba.set_num_threads(threads)
    assert len(frontier_builds) == len(trees)  # the frontier was used
    trees[0].validate(mesh.triangles())
    # The blocked node order numbers the nodes by the tree's shape alone.
    for tree in trees:
        for name in ("nodes", "leaf_first", "leaf_count", "prim_index"):
            assert np.array_equal(getattr(tree, name), getattr(serial, name)), name


def test_perfect_splits_pad_crossings_that_round_near_zero():
    """Regression (issue 16, found by ``test_properties.py --full``): Sutherland–Hodgman
    computes a crossing that should be z = 0 as about 5e-26, and padding the clipped bounds
    only by their own magnitude left the true crossing outside them. The sweep then split
    at -5.5e-24 and 5.2e-26 and the leaves around z = 0 listed nothing. The bounds are now
    padded by the float64 error relative to the scene's coordinates."""
    vertices = np.array(
        [[-2, -0.5, -2], [-2, -2, -2], [-2, -2, 0], [-2, -2, -2], [-2, -2, -2], [-2, -2, -2],
         [-2, -2, -2], [-0.5, -2, 1], [-2, -2, -2], [-2, 0, -3.34375]], dtype=np.float64,
    )  # fmt: skip
    faces = np.array([[9, 0, 7], [0, 0, 0], [9, 0, 7], [9, 0, 7], [0, 0, 0], [2, 2, 7],
                      [0, 0, 0], [0, 0, 2], [9, 0, 7]])  # fmt: skip
    mesh = rayaccel.TriangleMesh(vertices, faces)
    rays = RayBatch(np.array([[-1.0, -2.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    accel = rayaccel.build(mesh, "kdtree.sah", max_leaf_size=1)
    accel.validate()
    ref = _check_all(accel, rays, "kdtree.sah")
    assert ref.hit[0]
    assert ref.t[0] == pytest.approx(0.5)


def test_validate_checks_slivers_by_their_box():
    """Regression (issue 16, ``test_properties.py --full``): triangle 0 is collinear but
    for 2.2e-16 in one coordinate. Clipping rounds its parts away on both sides of a
    plane, the builder keeps it on both by its box, and ``validate()`` rejected that
    listing by the exact separating-axis test. Slivers are now checked by their box."""
    vertices = np.array(
        [[-1, -2, 2.220446e-16], [-2, -2, -2], [-2, -2, -2], [-2, -2, -2], [-2, -0.5, -1],
         [-1.5, -1.25, -0.5]], dtype=np.float32,
    )  # fmt: skip
    mesh = rayaccel.TriangleMesh(vertices, np.array([[0, 4, 5], [0, 0, 0], [0, 0, 5]]))
    origin = vertices[[0, 4, 5]].astype(np.float64)
    rays = RayBatch(origin + np.array([0.25, 0.0, 0.0]), np.tile([-1.0, 0.0, 0.0], (3, 1)))
    accel = rayaccel.build(mesh, "kdtree.sah", max_leaf_size=1)
    accel.validate()
    _check_all(accel, rays, "kdtree.sah")


@pytest.mark.parametrize("key", ["kdtree.sah", "kdtree.median"])
def test_many_copies_of_one_triangle(key, full):
    n = 100_000 if full or key == "kdtree.sah" else 20_000
    tri = np.broadcast_to(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64), (n, 3, 3))
    mesh = rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3))
    accel = rayaccel.build(mesh, key)
    accel.validate()
    assert accel.structure.depth() <= MAX_DEPTH
    rng = np.random.default_rng(0)
    o = np.column_stack(
        [
            rng.random(64) * 1.5 - 0.25,
            rng.random(64) * 1.5 - 0.25,
            np.where(rng.random(64) < 0.5, 1.0, -1.0),
        ]
    )
    d = np.column_stack([rng.normal(size=64) * 0.1, rng.normal(size=64) * 0.1, -o[:, 2]])
    ref = _check_all(accel, RayBatch(o, d), key)
    assert ref.hit.any()
    assert (~ref.hit).any()


def test_axis_parallel_rays_with_signed_zeros(sphere_accels):
    accel = sphere_accels["kdtree.sah", ()]
    kd = accel.structure
    rng = np.random.default_rng(7)
    n = 400
    d = np.zeros((n, 3))
    axis = rng.integers(0, 3, n)
    d[np.arange(n), axis] = rng.choice([-1.0, 1.0], n)
    d[rng.random((n, 3)) < 0.5] *= -1.0  # -0.0 on the zero components
    o = kd.lo + rng.random((n, 3)) * (kd.hi - kd.lo)
    # Half of them start on vertices' coordinates (planes of perfect splits).
    v = accel.mesh.vertices[rng.integers(0, accel.mesh.n_vertices, n // 2)]
    o[: n // 2] = v
    o[np.arange(n // 2), axis[: n // 2]] -= 3 * d[np.arange(n // 2), axis[: n // 2]]
    ref = _check_all(accel, RayBatch(o, d), "axis-parallel")
    assert ref.hit.any()


@pytest.mark.parametrize("key", STACKLESS)
def test_stackless_terminate_with_bounded_descents(sphere_accels, key):
    """kd-restart always finishes: at most one descent per leaf (x8 passes in planes)."""
    accel = sphere_accels["kdtree.sah", ()]
    kd = accel.structure
    rays = reference.concat(
        reference.mixed_rays(accel.mesh, 400, seed=9), _split_plane_rays(kd, 8, seed=2)
    )
    hits = accel.trace(rays, traversal=key, stats=True)
    descents = hits.stats["restarts"] + hits.stats["rope_steps"] + 1
    assert descents.max() <= 8 * kd.n_leaves
    assert (hits.stats["leaves"] <= 8 * kd.n_leaves).all()
    assert (hits.stats["nodes"] <= 8 * kd.n_leaves * (kd.depth() + 1)).all()


@pytest.mark.parametrize("size", [1, 64])  # 3 (the default) runs in _check_all
def test_short_stack_sizes_identical_to_stack(sphere_accels, size):
    accel = sphere_accels["kdtree.sah", ()]
    rays = reference.mixed_rays(accel.mesh, 500, seed=11)
    stack = accel.trace(rays, traversal="kdtree.stack", stats=True)
    short = accel.trace(rays, traversal="kdtree.short_stack", size=size, stats=True)
    assert np.array_equal(stack.t, short.t)
    assert np.array_equal(stack.prim, short.prim)
    assert (short.stats["stack_peak"] <= size).all()
    if size == 64:
        assert (short.stats["restarts"] == 0).all()


@pytest.mark.parametrize("optimize", [True, False])
def test_ropes_identical_to_stack(sphere_accels, optimize):
    accel = sphere_accels["kdtree.sah", ()]
    rays = reference.mixed_rays(accel.mesh, 700, seed=13)
    stack = accel.trace(rays, traversal="kdtree.stack")
    ropes = accel.trace(rays, traversal="kdtree.ropes", optimize=optimize, stats=True)
    assert np.array_equal(stack.t, ropes.t)
    assert np.array_equal(stack.prim, ropes.prim)
    assert np.array_equal(stack.u, ropes.u)
    info = accel.info()
    assert info["bytes"] > accel.structure.nbytes()


def _quadrant_mesh() -> rayaccel.TriangleMesh:
    """A triangle touching the edge ``{x = 0, z = 1}`` with its vertex ``(0, 0, 1)`` from
    the cell ``x < 0, z > 1``, and thin triangles at ``y >= 0.3`` filling the four cells
    around that edge so the SAH splits at ``z = 1`` and ``x = 0``."""
    tris = [[[0, 0, 1], [-1, 0, 2], [-1, 0.5, 1]]]
    for x0, x1 in ((-1, 0), (0, 1)):
        for z0, z1 in ((0, 1), (1, 2)):
            for k in range(4):
                a = x0 + (x1 - x0) * k / 4
                b = x0 + (x1 - x0) * (k + 1) / 4
                tris.append([[a, 0.3, z0], [b, 0.5, z0], [a, 0.4, z1]])
    v = np.array(tris, dtype=np.float64).reshape(-1, 3)
    return rayaccel.TriangleMesh(v, np.arange(len(v)).reshape(-1, 3))


@pytest.mark.parametrize("optimize", [True, False])
def test_ropes_find_hits_on_edges_and_corners(optimize):
    """Regression (issue 16): ``kdtree.ropes`` lost hits where the ray leaves a leaf
    through an edge or a corner. One rope leads to one neighbour, so a cell the ray only
    touches at the edge was never visited, nor a cell behind a null rope chosen on an
    exact tie with the scene boundary, and a cell beginning exactly at the end of the
    segment was cut (``>=``); a triangle touching that edge, listed only there (perfect
    splits), was missed. The stack and the oracle hit it."""
    cases = []
    # (1) Through an interior edge where four cells meet; the hit cell is only touched.
    p = np.array([0.0, 0.0, 1.0])
    d = np.array([[1, 0.25, 1], [1, -0.25, 1], [1, 0.125, 1], [2, 0.25, 1], [1, 0.25, 2],
                  [1, 0, 1], [-1, 0.25, -1]], dtype=np.float64)
    cases.append((_quadrant_mesh(), RayBatch(p - d, d)))
    # (2) Through a corner of the scene box: x and y faces (null ropes) tie with the
    # split z = 1 whose far side holds the hit; and from that corner outwards (the
    # segment ends at t = 0, where the hit is).
    corner = rayaccel.TriangleMesh(
        np.array([[-2, -2, 1], [-2, 0, 3], [0, -1, 1], [2, 2, -2], [2, 1, -2], [1, 2, -2]],
                 dtype=np.float64),
        np.array([[0, 1, 2], [3, 4, 5]]),
    )
    o = np.array([[1, 2, -1], [-2, -2, 1], [-2, 2, -1]], dtype=np.float64)
    d = np.array([[-3, -4, 2], [-1, -1, 1], [0, -4, 2]], dtype=np.float64)
    cases.append((corner, RayBatch(o, d)))
    # (3) A flat scene (the culling pad is zero): from a vertex on a cell corner.
    flat = rayaccel.TriangleMesh(
        np.array([[0, -2, 1], [0, 0, 3], [0, -1, 1], [0, 2, -2], [0, 1, -2], [0, 2, -1]],
                 dtype=np.float64),
        np.array([[0, 1, 2], [3, 4, 5]]),
    )
    o = np.array([[0, -2, 1], [0, -2, 1], [0, -2, 1], [-1, -1, 0]], dtype=np.float64)
    d = np.array([[1, -0.5, 0.5], [-1, -0.5, 0.5], [-1, 0.5, 0.5], [1, -1, 1]],
                 dtype=np.float64)
    cases.append((flat, RayBatch(o, d)))
    for mesh, rays in cases:
        accel = rayaccel.build(mesh, "kdtree.sah", max_leaf_size=1)
        accel.validate()
        ref = reference.oracle(mesh, rays)
        assert (ref.prim == 0).all()
        stack = accel.trace(rays, traversal="kdtree.stack")
        assert (stack.prim == 0).all()
        ropes = accel.trace(rays, traversal="kdtree.ropes", optimize=optimize)
        reference.assert_hits_identical(stack, ropes, "ropes")
        any_hit = accel.trace(rays, query="any", traversal="kdtree.ropes", optimize=optimize)
        reference.assert_any_matches(reference.tri9(mesh), rays, any_hit, ref)


def test_stats_counters_consistent(sphere_accels):
    accel = sphere_accels["kdtree.sah", ()]
    rays = reference.mixed_rays(accel.mesh, 400, seed=17)
    for key, opts in TRAVERSALS:
        plain = accel.trace(rays, traversal=key, **opts)
        counted = accel.trace(rays, traversal=key, stats=True, **opts)
        reference.assert_hits_identical(plain, counted, key)
        s = counted.stats
        assert (s["empty_leaves"] <= s["leaves"]).all()
        assert (s["nodes"] >= s["leaves"]).all()
