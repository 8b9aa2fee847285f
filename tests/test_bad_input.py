"""Bad and degenerate input: rejected with a clear message, or defined to miss."""

from __future__ import annotations

import re

import numpy as np
import pytest

import rayaccel
import reference
from bvh.test_build import chain_bvh
from rayaccel import registry
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, STACK_SIZE
from rayaccel.errors import (
    InvalidInputError,
    TraversalOverflowError,
    UnknownVariantError,
)
from rayaccel.rays.batch import RayBatch

PAIRS = reference.builder_traversal_pairs()
BUILDERS = [pytest.param(k, id=k) for k in registry.keys("builder")]

VERTS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=np.float64)
FACES = np.array([[0, 1, 2], [1, 3, 2]])


@pytest.fixture(scope="module")
def quad():
    return rayaccel.build(rayaccel.TriangleMesh(VERTS, FACES))


# ----------------------------------------------------------------------------- meshes


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e39])
def test_non_finite_vertex_rejected_naming_the_index(bad):
    v = VERTS.copy()
    v[2, 1] = bad
    with pytest.raises(InvalidInputError, match=r"vertex 2\b"):
        rayaccel.TriangleMesh(v, FACES)


@pytest.mark.parametrize("faces", [[[0, 1, 4]], [[0, -1, 2]], [[0, 1, 2], [7, 0, 1]]])
def test_face_index_out_of_range_rejected_naming_the_face(faces):
    with pytest.raises(InvalidInputError, match=r"face \d+ .*out of range"):
        rayaccel.TriangleMesh(VERTS, faces)


def test_face_index_naming_is_precise():
    with pytest.raises(InvalidInputError, match=r"face 1 "):
        rayaccel.TriangleMesh(VERTS, [[0, 1, 2], [0, 9, 1]])


@pytest.mark.parametrize("faces", [np.zeros((0, 3), int), []])
def test_empty_mesh_rejected(faces):
    with pytest.raises(InvalidInputError, match=r"empty|shape"):
        rayaccel.TriangleMesh(VERTS, faces)


@pytest.mark.parametrize(
    ("vertices", "faces"),
    [(VERTS[:, :2], FACES), (VERTS, FACES[:, :2]), (VERTS.ravel(), FACES),
     (VERTS.astype(str), FACES), (VERTS, [[0.5, 1, 2]]), (VERTS, [["a", "b", "c"]])],
)
def test_bad_mesh_shapes_and_dtypes(vertices, faces):
    with pytest.raises(InvalidInputError):
        rayaccel.TriangleMesh(vertices, faces)


def test_mesh_coerces_once_and_is_read_only():
    mesh = rayaccel.TriangleMesh(VERTS, FACES.astype(np.int64))
    assert mesh.vertices.dtype == np.float32
    assert mesh.vertices.flags.c_contiguous
    assert mesh.faces.dtype == np.int32
    assert mesh.faces.flags.c_contiguous
    with pytest.raises(ValueError, match="read-only"):
        mesh.vertices[0, 0] = 5


def test_build_rejects_non_mesh():
    with pytest.raises(InvalidInputError, match="TriangleMesh"):
        rayaccel.build(VERTS, "bvh2.binned_sah")


DEGENERATE = [
    pytest.param([[0, 0, 0], [0, 0, 0], [0, 1, 0]], id="repeated-vertex"),
    pytest.param([[0, 1, 0], [0, 1, 0], [0, 1, 0]], id="point"),
    pytest.param([[0, 0, 0], [1, 0, 0], [2, 0, 0]], id="collinear"),
]


@pytest.mark.parametrize("corners", DEGENERATE)
@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_zero_area_triangles_kept_and_never_hit(builder, traversal, corners):
    v = np.array([*corners, [5, 5, 5], [6, 5, 5], [5, 6, 5]], np.float64)
    mesh = rayaccel.TriangleMesh(v, [[0, 1, 2], [3, 4, 5]])
    assert mesh.n_triangles == 2
    assert mesh.areas()[0] == 0
    accel = rayaccel.build(mesh, builder, **reference.fine_options(builder))
    accel.validate()
    rng = np.random.default_rng(0)
    # Rays straight at points of the degenerate triangle, from all sides.
    c = np.asarray(corners, np.float64)
    targets = np.concatenate([c, (c[[0, 1, 2]] + c[[1, 2, 0]]) / 2])
    targets = np.repeat(targets, 200, axis=0)
    o = targets + reference.random_unit(rng, len(targets)) * 2
    for query in ("closest", "any"):
        hits = accel.trace(RayBatch(o, targets - o), query=query, traversal=traversal)
        assert not hits.hit.any(), f"{int(hits.hit.sum())} hits on a zero-area triangle"
    assert not reference.oracle(mesh, RayBatch(o, targets - o)).hit.any()


# ------------------------------------------------------------------------------- rays


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_degenerate_rays_miss(builder, traversal):
    accel = rayaccel.build(rayaccel.TriangleMesh(VERTS, FACES), builder)
    nan, inf = np.nan, np.inf
    o = np.array([[0.5, 0.5, 1]] * 10 + [[nan, 0.5, 1], [0.5, inf, 1], [0.5, 0.5, -inf]])
    d = np.array([[0, 0, -1]] * 13, dtype=np.float64)
    d[1] = (0, 0, 0)
    d[2] = (0, -0.0, 0)
    d[3] = (nan, 0, -1)
    d[4] = (0, 0, -inf)
    d[5] = (inf, inf, inf)
    d[6] = (0, nan, 0)
    tmin = np.zeros(13)
    tmax = np.full(13, np.inf)
    tmin[7], tmax[7] = 2.0, 1.0  # tmin > tmax
    tmin[8], tmax[8] = 1.0, 1.0 - 1e-6
    tmin[9], tmax[9] = np.inf, np.inf  # nothing at infinity
    hits = accel.intersect(o, d, tmin, tmax, traversal=traversal, stats=True)
    expect_hit = np.zeros(13, bool)
    expect_hit[0] = True
    assert np.array_equal(hits.hit, expect_hit)
    assert np.isposinf(hits.t[1:]).all()
    assert (hits.prim[1:] == -1).all()
    assert (hits.u[1:] == 0).all()
    assert (hits.v[1:] == 0).all()
    rays = RayBatch(o, d, tmin, tmax)
    assert np.array_equal(rays.valid()[:7], [True] + [False] * 6)
    for query in ("closest", "any"):
        r = accel.trace(rays, query=query, traversal=traversal, stats=True)
        assert np.array_equal(r.hit, expect_hit)
        for name, column in r.stats.items():
            assert (column[~rays.valid()] == 0).all(), name


def test_nan_interval_rejected_naming_the_index():
    with pytest.raises(InvalidInputError, match=r"tmin.*index 1"):
        RayBatch(np.zeros((3, 3)), np.ones((3, 3)), [0, np.nan, 0], np.inf)
    with pytest.raises(InvalidInputError, match="tmax"):
        RayBatch(np.zeros((3, 3)), np.ones((3, 3)), 0, [1, 1, np.nan])


def test_float64_and_int_inputs_are_coerced_once(quad):
    o = np.array([[0.25, 0.25, 1.0]])
    d = np.array([[0, 0, -1]])
    for origin, direction in ((o, d), (o.astype(np.float32), d.astype(np.float32)),
                              (o.tolist(), d.tolist()), (np.asfortranarray(o), d * 2),
                              (o[:, ::1], np.array([[0, 0, -1]], dtype=np.int64))):
        rays = RayBatch(origin, direction)
        assert rays.origin.dtype == np.float32
        assert rays.origin.flags.c_contiguous
        assert rays.direction.dtype == np.float32
        assert rays.direction.flags.c_contiguous
        assert rays.tmin.dtype == np.float32
        assert rays.tmax.dtype == np.float32
        assert quad.intersect(origin, direction).prim[0] == 0


def test_non_contiguous_views_accepted(quad):
    big = np.zeros((6, 6))
    big[::2, 0:3] = [0.25, 0.25, 1.0]
    big[::2, 3:6] = [0, 0, -1]
    hits = quad.intersect(big[::2, 0:3], big[::2, 3:6])
    assert (hits.prim == 0).all()


@pytest.mark.parametrize(
    ("origins", "directions", "pattern"),
    [(np.zeros((4, 2)), np.ones((4, 3)), "origins"),
     (np.zeros((4, 3)), np.ones((4, 2)), "directions"),
     (np.zeros((4, 3)), np.ones((5, 3)), "directions.*5"),
     (np.zeros((4, 3, 1)), np.ones((4, 3)), "origins"),
     (np.zeros((4, 3), dtype=complex), np.ones((4, 3)), "dtype"),
     (np.array([["a", "b", "c"]]), np.ones((1, 3)), "origins")],
)
def test_wrong_ray_shapes_rejected(quad, origins, directions, pattern):
    with pytest.raises(InvalidInputError, match=pattern):
        quad.intersect(origins, directions)


def test_mismatched_interval_length_rejected(quad):
    with pytest.raises(InvalidInputError, match="tmin"):
        quad.intersect(np.zeros((4, 3)), np.ones((4, 3)), tmin=np.zeros(3))
    with pytest.raises(InvalidInputError, match="tmax"):
        quad.intersect(np.zeros((4, 3)), np.ones((4, 3)), tmax=np.zeros((4, 1)))


def test_single_vector_broadcasts(quad):
    o = np.array([[0.25, 0.25, 1.0], [0.75, 0.75, 1.0], [2.0, 2.0, 1.0]])
    hits = quad.intersect(o, (0, 0, -1))
    assert list(hits.prim) == [0, 1, -1]
    hits = quad.intersect((0.5, 0.5, 1.0), np.array([[0, 0, -1], [0, 0, 1]]))
    assert list(hits.hit) == [True, False]


# ------------------------------------------------------------------- keys and options


@pytest.mark.parametrize(
    ("key", "close"),
    [("bvh2.binned", "bvh2.binned_sah"), ("bvh2.sweep", "bvh2.sweep_sah"),
     ("binned_sah", "bvh2.binned_sah")],
)
def test_unknown_builder_suggests(key, close):
    mesh = rayaccel.TriangleMesh(VERTS, FACES)
    with pytest.raises(UnknownVariantError, match=re.escape(close)) as info:
        rayaccel.build(mesh, key)
    assert "did you mean" in str(info.value)
    assert isinstance(info.value, KeyError)


def test_unknown_builder_without_close_match_lists_known():
    with pytest.raises(UnknownVariantError, match=r"known: .*bvh2\.binned_sah"):
        rayaccel.build(rayaccel.TriangleMesh(VERTS, FACES), "octree.magic")


def test_unknown_traversal_suggests(quad):
    with pytest.raises(UnknownVariantError, match=r"did you mean bvh2\.stack"):
        quad.intersect(np.zeros((1, 3)), np.ones((1, 3)), traversal="bvh2.stak")
    # A builder key is not a traversal.
    with pytest.raises(UnknownVariantError):
        quad.intersect(np.zeros((1, 3)), np.ones((1, 3)), traversal="bvh2.binned_sah")


def test_unknown_options_suggest(quad):
    mesh = rayaccel.TriangleMesh(VERTS, FACES)
    with pytest.raises(UnknownVariantError, match="did you mean max_leaf_size"):
        rayaccel.build(mesh, "bvh2.binned_sah", max_leaf=4)
    with pytest.raises(UnknownVariantError, match="unknown option 'n_bins'"):
        rayaccel.build(mesh, "bvh2.sweep_sah", n_bins=8)
    with pytest.raises(UnknownVariantError, match="unknown option"):
        quad.intersect(np.zeros((1, 3)), np.ones((1, 3)), stack_size=12)


def test_bad_query_rejected(quad):
    rays = RayBatch(np.zeros((1, 3)), np.ones((1, 3)))
    with pytest.raises(InvalidInputError, match="query"):
        quad.trace(rays, query="nearest")
    with pytest.raises(InvalidInputError, match="RayBatch"):
        quad.trace((np.zeros((1, 3)), np.ones((1, 3))))


# ------------------------------------------------------------------ degenerate scenes


@pytest.mark.parametrize("builder", BUILDERS)
def test_many_identical_triangles(builder, full):
    n = 100_000 if full or builder == "bvh2.binned_sah" else 20_000
    tri = np.broadcast_to(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64), (n, 3, 3))
    mesh = rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3))
    accel = rayaccel.build(mesh, builder)
    accel.validate()
    if builder == "grid.two_level":
        # The leaf level's reference budget coarsens the one crowded top cell.
        refs = accel.structure.prim_index.shape[0]
        assert refs <= 16 * n, refs
    if hasattr(accel.structure, "depth"):  # hierarchies (grids have no depth)
        assert accel.structure.depth() <= MAX_DEPTH
    rng = np.random.default_rng(0)
    o = np.column_stack([rng.random(64) * 1.5 - 0.25, rng.random(64) * 1.5 - 0.25,
                         np.where(rng.random(64) < 0.5, 1.0, -1.0)])
    d = np.column_stack([rng.normal(size=64) * 0.1, rng.normal(size=64) * 0.1, -o[:, 2]])
    rays = RayBatch(o, d)
    ref = reference.oracle(mesh, rays)
    assert ref.hit.any()
    assert (~ref.hit).any()
    tri9 = reference.tri9(mesh)
    for traversal in registry.keys("traversal", registry.get(builder).structure):
        reference.assert_closest_matches(tri9, rays, accel.trace(rays, traversal=traversal),
                                         ref)
        reference.assert_any_matches(tri9, rays, accel.trace(rays, query="any",
                                                             traversal=traversal), ref)


@pytest.mark.parametrize("traversal", registry.keys("traversal", "bvh2"))
def test_tree_deeper_than_stack_overflows_cleanly(traversal):
    """A hand-made chain deeper than STACK_SIZE: raise TraversalOverflowError or be right."""
    depth = STACK_SIZE + 6
    bvh, mesh = chain_bvh(depth)
    rays = RayBatch(np.array([[0.2, 0.2, 1.0], [0.2, 0.2, -1.0], [3, 3, 1]]),
                    np.array([[0, 0, -1.0], [0, 0, 1.0], [0, 0, -1.0]]))
    func = registry.get(traversal, "traversal").func
    try:
        hits = func(bvh, mesh, rays, query="closest", stats=False, options=None, cache=None)
    except TraversalOverflowError as exc:
        message = str(exc)
    else:
        message = None
    if message is not None:
        assert str(STACK_SIZE) in message
        return
    ref = reference.oracle(mesh, rays)
    reference.assert_closest_matches(reference.tri9(mesh), rays, hits, ref)


@pytest.mark.parametrize("traversal", registry.keys("traversal", "bvh2"))
def test_tree_as_deep_as_the_stack_allows_traces_correctly(traversal):
    bvh, mesh = chain_bvh(MAX_DEPTH)
    rays = RayBatch(np.array([[0.2, 0.2, 1.0], [3, 3, 1]]), np.array([[0, 0, -1.0]] * 2))
    func = registry.get(traversal, "traversal").func
    hits = func(bvh, mesh, rays, query="closest", stats=True, options=None, cache=None)
    ref = reference.oracle(mesh, rays)
    reference.assert_closest_matches(reference.tri9(mesh), rays, hits, ref)
    if traversal == "bvh2.stack":
        # Stackless traversals have no stack (restart_trail reports its short stack).
        assert hits.stats["stack_peak"][0] == MAX_DEPTH
