"""rayaccel.trimesh.RayMeshIntersector against trimesh's own intersectors and float64 oracles.

On rays that stay clear of edges, every query must give trimesh's ``ray_triangle``
answer (the r-tree intersector, exact there); on rays aimed exactly at shared edges
and vertices, where trimesh reports a crossing twice or lets it slip through, each
crossing must be reported once, checked against a brute-force float64 oracle.
"""

from __future__ import annotations

import copy
import pickle
import re

import numpy as np
import pytest
import trimesh

import rayaccel
import rayaccel.trimesh
from rayaccel.errors import InvalidInputError, UnknownVariantError
from rayaccel.trimesh import RayMeshIntersector

pytest.importorskip("rtree")  # trimesh's ray_triangle intersector needs its r-tree
from trimesh.ray.ray_triangle import RayMeshIntersector as TrimeshIntersector


def _teapot() -> trimesh.Trimesh:
    mesh = rayaccel.scenes.get("teapot")
    return trimesh.Trimesh(mesh.vertices.astype(np.float64), mesh.faces, process=False)


MESHES = {
    "teapot": _teapot,
    "icosphere": lambda: trimesh.creation.icosphere(subdivisions=3),
    "box": lambda: trimesh.creation.box(extents=(1.0, 2.0, 0.5)),
    "torus": lambda: trimesh.creation.torus(major_radius=1.0, minor_radius=0.3),
}


# -- float64 oracle ------------------------------------------------------------------------------


def _oracle_hits(mesh: trimesh.Trimesh, origins, directions, edge_eps=0.0):
    """Brute force in float64 (Möller–Trumbore, edges inclusive): ``(ray, tri, t, bary_min)``."""
    tri = np.asarray(mesh.triangles, dtype=np.float64)
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    rays, tris, ts, edge = [], [], [], []
    for r, (o, d) in enumerate(zip(origins, directions, strict=True)):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-300
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - a
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        w = 1.0 - u - v
        lo = np.minimum(np.minimum(u, v), w)
        hit = ok & (lo >= -edge_eps) & (t >= 0)
        idx = np.flatnonzero(hit)
        rays += [r] * len(idx)
        tris += idx.tolist()
        ts += t[idx].tolist()
        edge += lo[idx].tolist()
    return np.array(rays, int), np.array(tris, int), np.array(ts), np.array(edge)


def _crossing_points(mesh, origins, directions):
    """Distinct float64 hit points of each ray (hits within 1e-9 merged), sorted by t."""
    ray, _, t, _ = _oracle_hits(mesh, origins, directions, edge_eps=1e-12)
    out = []
    for r in range(len(origins)):
        ts = np.sort(t[ray == r])
        distinct = ts[np.concatenate([[True], np.diff(ts) > 1e-9])] if len(ts) else ts
        out.append(origins[r] + distinct[:, None] * directions[r])
    return out


def _clear_rays(mesh: trimesh.Trimesh, n: int, seed: int, margin: float = 1e-4):
    """Random rays whose every hit is at least ``margin`` (barycentric) from an edge and
    not grazing, and whose origin is clear of the surface: trimesh's tolerances then
    cannot change any answer."""
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds
    span = hi - lo
    origins = lo - 0.25 * span + 1.5 * span * rng.random((3 * n, 3))
    targets = lo + span * rng.random((3 * n, 3))
    directions = targets - origins
    directions[::5] *= -1  # some rays point away
    ray, tri, t, edge = _oracle_hits(mesh, origins, directions)
    normals = mesh.face_normals[tri]
    d = directions[ray] / np.linalg.norm(directions[ray], axis=1, keepdims=True)
    grazing = np.abs(np.einsum("ij,ij->i", normals, d)) < 1e-3
    near = (edge < margin) | grazing | (t * np.linalg.norm(directions[ray], axis=1) < 1e-6)
    bad = np.zeros(3 * n, bool)
    bad[ray[near]] = True
    keep = np.flatnonzero(~bad)[:n]
    return origins[keep], directions[keep]


def _pairs(index_tri, index_ray):
    return sorted(zip(np.asarray(index_ray).tolist(), np.asarray(index_tri).tolist(), strict=True))


# -- against trimesh on rays clear of edges -----------------------------------------------------


@pytest.mark.parametrize("name", list(MESHES))
def test_all_hits_match_trimesh(name):
    mesh = MESHES[name]()
    origins, directions = _clear_rays(mesh, 300, seed=1)
    ours = RayMeshIntersector(mesh)
    theirs = TrimeshIntersector(mesh)
    tri, ray, loc = ours.intersects_id(origins, directions, return_locations=True)
    ref_tri, ref_ray, ref_loc = theirs.intersects_id(origins, directions, return_locations=True)
    assert _pairs(tri, ray) == _pairs(ref_tri, ref_ray)
    assert len(_pairs(tri, ray)) > 50
    # Sorted by ray, then distance along it.
    assert (np.diff(ray) >= 0).all()
    dist = np.einsum("ij,ij->i", loc - origins[ray], directions[ray])
    same = np.diff(ray) == 0
    assert (np.diff(dist)[same] >= 0).all()
    # Locations: the same points, matched by (ray, triangle).
    ours_by = {(r, f): p for r, f, p in zip(ray.tolist(), tri.tolist(), loc, strict=True)}
    for r, f, p in zip(ref_ray.tolist(), ref_tri.tolist(), ref_loc, strict=True):
        np.testing.assert_allclose(ours_by[r, f], p, atol=1e-9 * mesh.scale + 1e-12)


@pytest.mark.parametrize("name", list(MESHES))
def test_first_any_and_location_match_trimesh(name):
    mesh = MESHES[name]()
    origins, directions = _clear_rays(mesh, 300, seed=2)
    ours = RayMeshIntersector(mesh)
    theirs = TrimeshIntersector(mesh)
    first = ours.intersects_first(origins, directions)
    assert first.dtype == np.int64
    assert first.shape == (len(origins),)
    assert np.array_equal(first, theirs.intersects_first(origins, directions))
    assert (first >= 0).any()
    assert (first < 0).any()
    hit = ours.intersects_any(origins, directions)
    assert hit.dtype == np.bool_
    assert np.array_equal(hit, theirs.intersects_any(origins, directions))
    # multiple_hits=False: the first hit of each ray that has one, in ray order.
    loc, ray, tri = ours.intersects_location(origins, directions, multiple_hits=False)
    assert np.array_equal(ray, np.flatnonzero(first >= 0))
    assert np.array_equal(tri, first[first >= 0])
    ref_loc, ref_ray, _ = theirs.intersects_location(origins, directions, multiple_hits=False)
    order = np.argsort(ref_ray)
    np.testing.assert_allclose(loc, ref_loc[order], atol=1e-9 * mesh.scale)


def _clearance(name: str, points: np.ndarray) -> np.ndarray:
    """Distance of ``points`` from the exact shape a mesh of ``MESHES`` approximates."""
    if name == "icosphere":
        return np.abs(np.linalg.norm(points, axis=1) - 1.0)
    if name == "box":
        half = np.array([0.5, 1.0, 0.25])
        return np.abs(np.abs(points) - half).min(axis=1)
    ring = np.hypot(points[:, 0], points[:, 1]) - 1.0
    return np.abs(np.hypot(ring, points[:, 2]) - 0.3)


@pytest.mark.parametrize("name", ["icosphere", "box", "torus"])
def test_contains_points_matches_trimesh(name):
    mesh = MESHES[name]()
    assert mesh.is_watertight
    rng = np.random.default_rng(3)
    lo, hi = mesh.bounds
    points = lo - 0.1 + (hi - lo + 0.2) * rng.random((3000, 3))
    # Keep points clear of the surface (there, the answer is undefined).
    points = points[_clearance(name, points) > 0.02]
    ours = RayMeshIntersector(mesh).contains_points(points)
    assert ours.dtype == np.bool_
    assert ours.shape == (len(points),)
    assert np.array_equal(ours, TrimeshIntersector(mesh).contains_points(points))
    assert ours.any()
    assert not ours.all()


def test_contains_points_through_edges_and_vertices(monkeypatch):
    # Along +z from points on a grid of the subdivided box's vertex coordinates, every
    # ray of the first try passes exactly through edges or vertices of the top face.
    monkeypatch.setattr(rayaccel.trimesh, "CONTAINS_DIRECTION", np.array([0.0, 0.0, 1.0]))
    mesh = trimesh.creation.box().subdivide().subdivide()
    grid = np.arange(-3, 4) / 8.0
    points = np.array([[x, y, z] for x in grid for y in grid for z in grid])
    ours = RayMeshIntersector(mesh)
    assert ours.contains_points(points).all()
    moved = 3 * points + [0.0, 0.0, 0.01]
    expected = (np.abs(moved) < 0.5).all(axis=1)
    assert 0 < expected.sum() < len(moved)
    assert np.array_equal(ours.contains_points(moved), expected)


# -- shared edges and vertices: each crossing once ------------------------------------------------


def _axis_rays(values, axis: int, start: float = 2.0):
    """Rays along ``-axis`` from ``start``, through every (a, b) of ``values`` squared."""
    a, b = np.meshgrid(values, values, indexing="ij")
    other = [k for k in range(3) if k != axis]
    origins = np.zeros((a.size, 3))
    origins[:, other[0]] = a.ravel()
    origins[:, other[1]] = b.ravel()
    origins[:, axis] = start
    directions = np.zeros_like(origins)
    directions[:, axis] = -1.0
    return origins, directions


@pytest.mark.parametrize("unmerged", [False, True])
def test_rays_through_shared_edges_and_vertices_hit_once(unmerged):
    mesh = trimesh.creation.box().subdivide().subdivide()  # grid vertices at k / 8
    if unmerged:
        mesh.unmerge_vertices()  # shared corners are equal coordinates, not indices
    ours = RayMeshIntersector(mesh)
    values = np.arange(-3, 4) / 8.0  # every grid vertex and edge midpoint inside the faces
    for axis in range(3):
        origins, directions = _axis_rays(values, axis)
        loc, ray, _ = ours.intersects_location(origins, directions)
        # Exactly the two faces, once each, at the oracle's points.
        assert np.array_equal(np.bincount(ray, minlength=len(origins)), np.full(len(origins), 2))
        expected = _crossing_points(mesh, origins, directions)
        for r in range(len(origins)):
            assert len(expected[r]) == 2
            np.testing.assert_allclose(loc[ray == r], expected[r], atol=1e-12)
        assert ours.intersects_any(origins, directions).all()
        assert (ours.intersects_first(origins, directions) >= 0).all()


def test_rays_through_box_corners_hit_once():
    mesh = trimesh.creation.box()
    ours = RayMeshIntersector(mesh)
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    origins = 3 * corners
    directions = -corners  # through the corner, the centre and the opposite corner
    loc, ray, _ = ours.intersects_location(origins, directions)
    assert np.array_equal(np.bincount(ray, minlength=8), np.full(8, 2))
    np.testing.assert_allclose(loc[0::2], corners, atol=1e-12)
    np.testing.assert_allclose(loc[1::2], -corners, atol=1e-12)


def test_rays_at_icosphere_vertices_and_edges_never_slip_or_repeat():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    edges = mesh.edges_unique
    targets = np.concatenate([
        mesh.vertices,
        mesh.vertices[edges].mean(axis=1),  # edge midpoints
    ])  # fmt: skip
    rng = np.random.default_rng(7)
    origins = 3 * targets + rng.normal(scale=0.2, size=targets.shape)
    directions = targets - origins
    ours = RayMeshIntersector(mesh)
    loc, ray, _ = ours.intersects_location(origins, directions)
    counts = np.bincount(ray, minlength=len(origins))
    expected = _crossing_points(mesh, origins, directions)
    assert [len(e) for e in expected] == counts.tolist()
    assert (counts == 2).mean() > 0.99  # grazing rays (one touch) are the exception
    for r in np.flatnonzero(counts == 2)[:200]:
        np.testing.assert_allclose(loc[ray == r], expected[r], atol=1e-6)


def test_a_ray_touching_a_ridge_keeps_both_faces():
    # A tetrahedron's ridge between its base and its slanted face, touched from above:
    # the ray enters and leaves there, so both hits stay and parity stays even.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    ours = RayMeshIntersector(mesh)
    tri, ray = ours.intersects_id([[0.5, 0.5, 2.0]], [[0.0, 0.0, -1.0]])
    assert sorted(tri.tolist()) == [0, 3]
    assert ray.tolist() == [0, 0]
    # Its neighbours: just inside, the ray enters and leaves (two hits); just outside,
    # none. The touch between them has the parity of the inside.
    tri, _ = ours.intersects_id([[0.499, 0.499, 2.0]], [[0.0, 0.0, -1.0]])
    assert sorted(tri.tolist()) == [0, 3]
    assert len(ours.intersects_id([[0.501, 0.501, 2.0]], [[0.0, 0.0, -1.0]])[0]) == 0


# -- trimesh integration ------------------------------------------------------------------------


def test_mesh_ray_assignment():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.ray = RayMeshIntersector(mesh)
    assert mesh.ray.mesh is mesh
    points = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, 0.1], [2.0, 0.0, 0.0], [0.0, 0.9, 0.05]])
    assert mesh.contains(points).tolist() == [True, True, False, True]
    loc, ray, _ = mesh.ray.intersects_location([[0.1, 0.05, -5.0]], [[0, 0, 1.0]])
    assert ray.tolist() == [0, 0]
    assert loc[0, 2] < 0 < loc[1, 2]
    # trimesh's own functions that go through mesh.ray
    length = trimesh.proximity.longest_ray(mesh, [[0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(length, [1.0], atol=0.01)
    thickness = trimesh.proximity.thickness(
        mesh, mesh.vertices[:5], normals=mesh.vertex_normals[:5], method="ray"
    )
    assert thickness.shape == (5,)
    assert (thickness > 1.5).all()


def test_rebuilds_when_the_mesh_changes():
    mesh = trimesh.creation.box()
    ours = RayMeshIntersector(mesh)
    origin, direction = [[0.0, 0.0, 5.0]], [[0.0, 0.0, -1.0]]
    before = ours.intersects_location(origin, direction)[0]
    mesh.apply_translation([0.0, 0.0, 1.0])
    after = ours.intersects_location(origin, direction)[0]
    np.testing.assert_allclose(after, before + np.array([0.0, 0.0, 1.0]))
    mesh.apply_translation([10.0, 0.0, 0.0])
    assert not ours.intersects_any(origin, direction).any()


def test_far_from_the_origin_keeps_precision():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    origins, directions = _clear_rays(mesh, 200, seed=4)
    near = RayMeshIntersector(mesh).intersects_location(origins, directions)
    offset = np.array([1e7, -3e7, 2e7])
    moved = mesh.copy()
    moved.apply_translation(offset)
    far = RayMeshIntersector(moved).intersects_location(origins + offset, directions)
    assert np.array_equal(near[1], far[1])
    assert np.array_equal(near[2], far[2])
    np.testing.assert_allclose(far[0] - offset, near[0], atol=1e-7)


def test_max_hits_and_builder_options():
    mesh = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    origins = np.array([[-3.0, 0.0, 0.0], [-3.0, 0.05, 0.0]])
    directions = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    ours = RayMeshIntersector(mesh, "bvh2.sbvh", max_leaf_size=2)
    tri, ray = ours.intersects_id(origins, directions)
    assert np.bincount(ray).tolist() == [4, 4]
    tri2, ray2 = ours.intersects_id(origins, directions, max_hits=3)
    assert np.bincount(ray2).tolist() == [3, 3]
    keep = np.concatenate([np.arange(3), 4 + np.arange(3)])
    assert np.array_equal(tri2, tri[keep])
    assert ours.accel is not None
    assert ours.accel.key == "bvh2.sbvh"


def test_pickle_and_copy():
    mesh = trimesh.creation.icosphere()
    ours = RayMeshIntersector(mesh)
    origins, directions = [[0, 0, -3.0]], [[0, 0, 1.0]]
    expected = ours.intersects_id(origins, directions)
    for clone in (pickle.loads(pickle.dumps(ours)), copy.copy(ours), copy.deepcopy(ours)):
        got = clone.intersects_id(origins, directions)
        assert all(np.array_equal(a, b) for a, b in zip(got, expected, strict=True))
    assert copy.copy(ours).mesh is mesh
    assert copy.deepcopy(ours).mesh is not mesh


# -- shapes, dtypes, empty and bad input ---------------------------------------------------------


def test_dtypes_and_shapes_match_trimesh():
    mesh = trimesh.creation.icosphere()
    ours, theirs = RayMeshIntersector(mesh), TrimeshIntersector(mesh)
    origins = np.array([[0.1, 0.05, -3.0], [5, 5, 5]], dtype=np.float32)
    directions = np.array([[0, 0, 1], [1, 0, 0]])  # ints are fine
    for a, b in zip(ours.intersects_id(origins, directions, return_locations=True),
                    theirs.intersects_id(origins, directions, return_locations=True),
                    strict=True):  # fmt: skip
        assert a.dtype == b.dtype
        assert a.shape == b.shape
    for a, b in zip(ours.intersects_location(origins, directions),
                    theirs.intersects_location(origins, directions), strict=True):  # fmt: skip
        assert a.dtype == b.dtype
        assert a.shape == b.shape
    assert len(ours.intersects_id(origins, directions)) == 2


@pytest.mark.parametrize("empty", [np.zeros((0, 3)), [], np.zeros((0, 3), dtype=np.float32)])
def test_empty_inputs(empty):
    ours = RayMeshIntersector(trimesh.creation.box())
    tri, ray, loc = ours.intersects_id(empty, empty, return_locations=True)
    assert tri.dtype == ray.dtype == np.int64
    assert tri.shape == ray.shape == (0,)
    assert loc.dtype == np.float64
    assert loc.shape == (0, 3)
    loc, ray, tri = ours.intersects_location(empty, empty)
    assert loc.shape == (0, 3)
    assert ray.shape == tri.shape == (0,)
    first = ours.intersects_first(empty, empty)
    assert first.dtype == np.int64
    assert first.shape == (0,)
    assert ours.intersects_any(empty, empty).shape == (0,)
    contains = ours.contains_points(empty)
    assert contains.dtype == np.bool_
    assert contains.shape == (0,)


def test_zero_directions_miss_and_a_mesh_without_faces():
    ours = RayMeshIntersector(trimesh.creation.box())
    assert not ours.intersects_any([[0, 0, 3.0]], [[0, 0, 0.0]]).any()
    empty = RayMeshIntersector(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)))
    assert empty.accel is None
    assert empty.intersects_first([[0, 0, 0.0]], [[1.0, 0, 0]]).tolist() == [-1]
    assert empty.intersects_id([[0, 0, 0.0]], [[1.0, 0, 0]])[0].shape == (0,)
    assert not empty.contains_points([[0, 0, 0.0]]).any()


@pytest.mark.parametrize(
    ("origins", "directions", "message"),
    [
        ([[0, 0, np.nan]], [[0, 0, 1.0]], "ray_origins: row 0 holds NaN"),
        ([[0, 0, 0.0], [1, 1, 1]], [[0, 0, 1.0], [np.inf, 0, 0]], "ray_directions: row 1"),
        ([[0, 0, 0.0]], [[0, 0, 1.0], [0, 1.0, 0]], "ray_directions: expected 1 rows"),
        ([[0, 0]], [[0, 1]], "ray_origins: expected shape (n, 3)"),
        ([[0, 0, 0.0]], [[0, 0]], "ray_directions: expected shape (n, 3)"),
        ([["a", "b", "c"]], [[0, 0, 1.0]], "ray_origins: expected a float array"),
        ([[True, False, True]], [[0, 0, 1.0]], "ray_origins: expected a float array"),
    ],
)
def test_bad_rays_raise_naming_the_argument(origins, directions, message):
    ours = RayMeshIntersector(trimesh.creation.box())
    for call in (
        lambda: ours.intersects_id(origins, directions),
        lambda: ours.intersects_location(origins, directions),
        lambda: ours.intersects_first(origins, directions),
        lambda: ours.intersects_any(origins, directions),
    ):
        with pytest.raises(InvalidInputError, match=re.escape(message)):
            call()


def test_bad_points_max_hits_mesh_and_builder():
    mesh = trimesh.creation.box()
    ours = RayMeshIntersector(mesh)
    with pytest.raises(InvalidInputError, match="points: row 1 holds NaN"):
        ours.contains_points([[0, 0, 0], [np.nan, 0, 0]])
    with pytest.raises(InvalidInputError, match="points: expected shape"):
        ours.contains_points([0.0, 0.0, 0.0])
    with pytest.raises(InvalidInputError, match="max_hits"):
        ours.intersects_id([[0, 0, 3.0]], [[0, 0, -1.0]], max_hits=0)
    with pytest.raises(InvalidInputError, match=r"mesh: expected a trimesh\.Trimesh"):
        RayMeshIntersector(rayaccel.scenes.get("cornell-box"))
    with pytest.raises(InvalidInputError, match="bvh2 builder"):
        RayMeshIntersector(mesh, "kdtree.sah")
    with pytest.raises(UnknownVariantError):
        RayMeshIntersector(mesh, "bvh2.binned_sha")
    with pytest.raises(UnknownVariantError):
        RayMeshIntersector(mesh, max_leaf_sise=4)
    with pytest.raises(TypeError):
        ours.intersects_location([[0, 0, 3.0]], [[0, 0, -1.0]], multiple_hit=True)
    # Nothing was built wrong: the intersector still answers.
    assert ours.intersects_any([[0, 0, 3.0]], [[0, 0, -1.0]]).tolist() == [True]


def test_float64_precision_gives_the_same_answers():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    origins, directions = _clear_rays(mesh, 300, seed=6)
    single = RayMeshIntersector(mesh)
    double = RayMeshIntersector(mesh, precision="float64")
    assert double.accel is not None
    assert double.accel.mesh.precision == "float64"
    for a, b in zip(single.intersects_id(origins, directions, return_locations=True),
                    double.intersects_id(origins, directions, return_locations=True),
                    strict=True):  # fmt: skip
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert np.array_equal(
        single.intersects_first(origins, directions), double.intersects_first(origins, directions)
    )
    points = np.random.default_rng(1).uniform(-1.2, 1.2, (500, 3))
    points = points[_clearance("icosphere", points) > 0.02]
    assert np.array_equal(single.contains_points(points), double.contains_points(points))
    assert "precision='float64'" in repr(double)
    with pytest.raises(InvalidInputError, match="precision"):
        RayMeshIntersector(mesh, precision="float16")


def test_a_face_listed_twice_is_hit_once():
    box = trimesh.creation.box()
    faces = np.concatenate([box.faces, box.faces[::2], box.faces[1::2, ::-1]])  # all twice
    mesh = trimesh.Trimesh(box.vertices, faces, process=False)
    ours = RayMeshIntersector(mesh)
    origins, directions = _axis_rays(np.array([-0.3, 0.1, 0.2]), axis=0)
    origins = origins + np.array([0.0, 0.01, -0.02])
    _, ray, _ = ours.intersects_location(origins, directions)
    assert np.bincount(ray, minlength=len(origins)).tolist() == [2] * len(origins)
    assert ours.contains_points([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0]]).all()
