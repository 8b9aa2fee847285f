"""Open3D's query set on Accel (issue 19, item 2): each query against a float64 numpy oracle.

count/list_intersections against a brute-force Möller–Trumbore over every triangle
(no duplicates with spatial splits and pre-splitting), closest points against every
point–triangle distance, winding numbers against the exact solid-angle sum, signed
distance and occupancy inside/outside closed meshes, the open-box case the docs
describe, Open3D's RaycastingScene on the same queries, empty and bad inputs.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

import rayaccel as ra
from rayaccel.bvh import geometry
from rayaccel.bvh.traverse.winding import winding_numbers, winding_numbers_brute

BUILDERS = ("bvh2.binned_sah", "bvh2.sbvh", "bvh2.lbvh+presplit", "kdtree.sah", "grid.uniform")
#: Builders whose trees reference some triangles from several leaves (checked below).
DUPLICATING = ("bvh2.sbvh", "bvh2.lbvh+presplit")


def _icosphere(subdivisions: int = 2) -> ra.TriangleMesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return ra.TriangleMesh(m.vertices, m.faces, name="icosphere")


def _open_box() -> ra.TriangleMesh:
    """A unit cube centred at the origin with its top (+z) face removed."""
    m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    keep = ~(m.triangles_center[:, 2] > 0.49)
    return ra.TriangleMesh(m.vertices, m.faces[keep], name="open-box")


MESHES = {
    "teapot": lambda: ra.scenes.get("teapot", subdivisions=6),
    "icosphere": _icosphere,
}


@pytest.fixture(scope="module", params=sorted(MESHES))
def mesh(request):
    return MESHES[request.param]()


_ACCELS: dict = {}


def _accel(mesh, key):
    cache_key = (mesh.name, mesh.n_triangles, key)
    if cache_key not in _ACCELS:
        _ACCELS[cache_key] = ra.build(mesh, key)
    return _ACCELS[cache_key]


def _rays(mesh, n, seed):
    lo, hi = (b.astype(np.float64) for b in mesh.bounds())
    rng = np.random.default_rng(seed)
    span = hi - lo
    origins = rng.uniform(lo - 0.3 * span, hi + 0.3 * span, size=(n, 3))
    # Aim at points of the box so that most rays cross the mesh.
    targets = rng.uniform(lo, hi, size=(n, 3))
    return origins, targets - origins


def _points(mesh, n, seed):
    lo, hi = (b.astype(np.float64) for b in mesh.bounds())
    span = hi - lo
    return np.random.default_rng(seed).uniform(lo - 0.2 * span, hi + 0.2 * span, size=(n, 3))


# -- oracles (float64 numpy) -------------------------------------------------------------------


def all_hits_oracle(mesh, origins, directions, tmin, tmax):
    """Every (t, prim) per ray by Möller–Trumbore in float64, sorted by t then prim."""
    tri = mesh.triangles().astype(np.float64)
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = []
    for o, d in zip(origins.astype(np.float32).astype(np.float64),
                    directions.astype(np.float32).astype(np.float64), strict=True):  # fmt: skip
        p = np.cross(d, e2)
        det = (e1 * p).sum(1)
        ok = det != 0
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - a
        u = (s * p).sum(1) * inv
        q = np.cross(s, e1)
        v = (q * d).sum(1) * inv
        t = (q * e2).sum(1) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= tmin) & (t <= tmax)
        idx = np.flatnonzero(hit)
        order = np.lexsort((idx, t[idx]))
        out.append((t[idx][order], idx[order]))
    return out


def point_triangle_d2(tri, p):
    """Squared float64 distance from ``p`` to every triangle (face interior or nearest edge)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    best = np.full(len(tri), np.inf)
    for s, e in ((a, b), (b, c), (c, a)):
        d = e - s
        dd = (d * d).sum(1)
        t = np.clip(((p - s) * d).sum(1) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        best = np.minimum(best, ((p - (s + t[:, None] * d)) ** 2).sum(1))
    n = np.cross(b - a, c - a)
    nn = (n * n).sum(1)
    ok = nn > 0
    h = np.where(ok, ((p - a) * n).sum(1) / np.where(ok, nn, 1.0), 0.0)
    q = p - h[:, None] * n
    inside = ok.copy()
    for s, e in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(e - s, q - s) * n).sum(1) >= 0
    return np.where(inside, np.minimum(best, ((p - q) ** 2).sum(1)), best)


def winding_oracle(mesh, points):
    """Exact generalised winding numbers (Van Oosterom & Strackee solid angles, float64)."""
    tri = mesh.triangles().astype(np.float64)
    out = []
    for p in points:
        a, b, c = tri[:, 0] - p, tri[:, 1] - p, tri[:, 2] - p
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        det = (a * np.cross(b, c)).sum(1)
        den = la * lb * lc + (a * b).sum(1) * lc + (a * c).sum(1) * lb + (b * c).sum(1) * la
        out.append((2.0 * np.arctan2(det, den)).sum() / (4.0 * math.pi))
    return np.array(out)


# -- all hits ----------------------------------------------------------------------------------


@pytest.mark.parametrize("key", BUILDERS)
def test_list_and_count_match_the_oracle(mesh, key):
    accel = _accel(mesh, key)
    if key in DUPLICATING and mesh.name == "teapot":
        # The no-duplicate check below only means something if references repeat.
        assert accel.info()["n_refs"] > mesh.n_triangles
    origins, directions = _rays(mesh, 200, seed=1)
    tmin, tmax = 0.05, 2.5
    hits = accel.list_intersections(origins, directions, tmin, tmax)
    counts = accel.count_intersections(origins, directions, tmin, tmax)
    expected = all_hits_oracle(mesh, origins, directions, tmin, tmax)
    assert hits.ray_splits.shape == (201,)
    assert hits.ray_splits[0] == 0
    np.testing.assert_array_equal(np.diff(hits.ray_splits), counts)
    assert sum(len(p) for _, p in expected) > 100  # the rays do cross the mesh
    for r, (t_ref, prim_ref) in enumerate(expected):
        lo, hi = hits.ray_splits[r], hits.ray_splits[r + 1]
        prims = hits.primitive_ids[lo:hi]
        # Each triangle once, sorted by t then primitive.
        assert len(set(prims.tolist())) == len(prims), f"ray {r}: duplicate hits {prims}"
        assert sorted(prims.tolist()) == sorted(prim_ref.tolist()), f"ray {r}"
        np.testing.assert_array_equal(hits.ray_ids[lo:hi], r)
        t = hits.t_hit[lo:hi]
        assert np.all(np.diff(t) >= 0)
        np.testing.assert_allclose(np.sort(t), t_ref, rtol=1e-4, atol=1e-5)
    # Barycentrics reproduce the hit points o + t·d.
    tri = mesh.triangles().astype(np.float64)[hits.primitive_ids]
    u, v = hits.primitive_uvs[:, 0:1].astype(np.float64), hits.primitive_uvs[:, 1:2]
    on_tri = (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
    along = origins[hits.ray_ids] + hits.t_hit[:, None] * directions[hits.ray_ids]
    np.testing.assert_allclose(on_tri, along, atol=1e-4)
    # The dict-like view Open3D users index.
    assert hits["t_hit"] is hits.t_hit
    assert set(hits.keys()) >= {"ray_splits", "primitive_uvs"}


def test_first_listed_hit_is_the_closest_hit(mesh):
    accel = _accel(mesh, "bvh2.sbvh")
    origins, directions = _rays(mesh, 300, seed=2)
    hits = accel.list_intersections(origins, directions)
    closest = accel.intersect(origins, directions)
    n = np.diff(hits.ray_splits)
    np.testing.assert_array_equal(n > 0, closest.hit)
    first = hits.ray_splits[:-1][n > 0]
    np.testing.assert_array_equal(hits.t_hit[first], closest.t[closest.hit])


def test_parallel_count_equals_serial():
    mesh = _icosphere(3)
    accel = _accel(mesh, "bvh2.sbvh")
    origins, directions = _rays(mesh, 5000, seed=3)  # above PARALLEL_MIN_RAYS
    counts = accel.count_intersections(origins, directions)
    serial = np.concatenate(
        [accel.count_intersections(origins[i : i + 1000], directions[i : i + 1000])
         for i in range(0, 5000, 1000)]
    )  # fmt: skip
    np.testing.assert_array_equal(counts, serial)
    # A sphere is crossed 0 or 2 times (a tangent ray may touch one or two triangles).
    assert set(np.unique(counts).tolist()) <= {0, 1, 2, 3, 4}
    assert (counts == 2).mean() > 0.5


# -- closest points ----------------------------------------------------------------------------


@pytest.mark.parametrize("key", BUILDERS)
def test_closest_points_match_the_oracle(mesh, key):
    accel = _accel(mesh, key)
    points = _points(mesh, 150, seed=4)
    result = accel.compute_closest_points(points)
    tri = mesh.triangles().astype(np.float64)
    scale = float(np.abs(tri).max())
    for i, p in enumerate(points):
        d2 = point_triangle_d2(tri, p)
        best = math.sqrt(d2.min())
        assert result.distance[i] == pytest.approx(best, abs=1e-5 * scale)
        # The triangle reported is at that distance (ties may pick another one).
        assert math.sqrt(d2[result.primitive_ids[i]]) == pytest.approx(best, abs=1e-5 * scale)
    # The point lies on its triangle at its barycentrics, at the reported distance.
    u, v = (result.primitive_uvs[:, k : k + 1].astype(np.float64) for k in (0, 1))
    assert (u >= -1e-6).all()
    assert (v >= -1e-6).all()
    assert (u + v <= 1 + 1e-6).all()
    t = tri[result.primitive_ids]
    np.testing.assert_allclose(
        result.points, (1 - u - v) * t[:, 0] + u * t[:, 1] + v * t[:, 2], atol=1e-5 * scale
    )
    np.testing.assert_allclose(
        np.linalg.norm(result.points - points, axis=1), result.distance, atol=1e-5 * scale
    )
    np.testing.assert_allclose(accel.compute_distance(points), result.distance, rtol=1e-6)
    np.testing.assert_allclose(
        result.primitive_normals, mesh.normals()[result.primitive_ids], atol=1e-6
    )


def test_closest_points_are_the_same_for_every_builder_and_in_parallel():
    mesh = ra.scenes.get("teapot", subdivisions=6)
    points = _points(mesh, 1500, seed=5)  # above the parallel threshold
    reference = _accel(mesh, "bvh2.binned_sah").compute_closest_points(points)
    for key in BUILDERS[1:]:
        other = _accel(mesh, key).compute_closest_points(points)
        # Ties go to the lowest primitive id whatever the tree.
        np.testing.assert_array_equal(other.primitive_ids, reference.primitive_ids)
        np.testing.assert_array_equal(other.distance, reference.distance)
    serial = _accel(mesh, "bvh2.sbvh").compute_closest_points(points[:500])
    np.testing.assert_array_equal(serial.distance, reference.distance[:500])


# -- winding numbers, signed distance, occupancy -----------------------------------------------


def test_winding_numbers_match_the_exact_sum(mesh):
    points = _points(mesh, 200, seed=6)
    exact = winding_oracle(mesh, points)
    rows = mesh.hit_rows()
    np.testing.assert_allclose(winding_numbers_brute(rows, points), exact, atol=1e-9)
    fast = winding_numbers(_accel(mesh, "bvh2.binned_sah").structure, rows, points)
    # First-order far field at beta = 2 (Barill et al. 2018): within a few hundredths.
    np.testing.assert_allclose(fast, exact, atol=0.08)
    assert ((fast > 0.5) == (exact > 0.5)).all()


@pytest.mark.parametrize("key", ["bvh2.binned_sah", "bvh2.sbvh", "grid.uniform"])
@pytest.mark.parametrize("method", ["winding", "parity"])
def test_signed_distance_and_occupancy_on_a_closed_sphere(key, method):
    mesh = _icosphere(3)
    accel = _accel(mesh, key)
    rng = np.random.default_rng(7)
    directions = rng.normal(size=(300, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radius = rng.uniform(0.0, 1.6, size=300)
    points = directions * radius[:, None]
    # The inscribed sphere of the icosphere is within 1% of the unit sphere.
    clear = np.abs(radius - 1.0) > 0.02
    inside = radius < 1.0
    occupancy = accel.compute_occupancy(points, method=method)
    assert occupancy.dtype == np.float32
    np.testing.assert_array_equal(occupancy[clear], inside[clear].astype(np.float32))
    signed = accel.compute_signed_distance(points, method=method)
    tri = mesh.triangles().astype(np.float64)
    unsigned = np.array([math.sqrt(point_triangle_d2(tri, p).min()) for p in points])
    expected = np.where(inside, -unsigned, unsigned)
    np.testing.assert_allclose(signed[clear], expected[clear], atol=1e-5)
    np.testing.assert_allclose(np.abs(signed), unsigned, atol=1e-5)


def test_open_mesh_winding_number_is_the_documented_fraction():
    """An open box: the centre sees 5 of 6 faces (w = 5/6, inside); above the hole it is out."""
    mesh = _open_box()
    accel = _accel(mesh, "bvh2.binned_sah")
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.45], [0.0, 0.0, 0.8], [2.0, 0.0, 0.0]])
    w = geometry.winding_number(accel.structure, mesh, points, accel._cache)
    np.testing.assert_allclose(w[0], 5.0 / 6.0, atol=1e-9)  # leaves are summed exactly
    np.testing.assert_allclose(w, winding_oracle(mesh, points), atol=0.05)
    np.testing.assert_array_equal(accel.compute_occupancy(points), [1.0, 1.0, 0.0, 0.0])
    # Parity ignores how much of the point is wrapped: a vote of rays, some of which
    # leave through the hole. Far outside it still agrees.
    parity = accel.compute_occupancy(points, method="parity", n_rays=5)
    assert parity[3] == 0.0
    assert set(parity.tolist()) <= {0.0, 1.0}


# -- Open3D on the same queries ----------------------------------------------------------------


@pytest.mark.peers
def test_same_answers_as_open3d():
    o3d = pytest.importorskip("open3d")
    mesh = _icosphere(3)
    accel = _accel(mesh, "bvh2.sbvh")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices), o3d.core.Tensor(mesh.faces.astype(np.uint32))
    )
    origins, directions = _rays(mesh, 300, seed=8)
    rays = o3d.core.Tensor(np.hstack([origins, directions]).astype(np.float32))
    np.testing.assert_array_equal(
        accel.count_intersections(origins, directions), scene.count_intersections(rays).numpy()
    )
    theirs = scene.list_intersections(rays)
    ours = accel.list_intersections(origins, directions)
    np.testing.assert_array_equal(ours.ray_splits, theirs["ray_splits"].numpy())
    np.testing.assert_array_equal(ours.ray_ids, theirs["ray_ids"].numpy())
    # Open3D lists a ray's hits in its own order: compare per ray sorted by t.
    their_t = theirs["t_hit"].numpy()
    their_prim = theirs["primitive_ids"].numpy().astype(np.int32)
    for r in range(len(origins)):
        lo, hi = ours.ray_splits[r], ours.ray_splits[r + 1]
        order = np.argsort(their_t[lo:hi], kind="stable")
        np.testing.assert_array_equal(ours.primitive_ids[lo:hi], their_prim[lo:hi][order])
        np.testing.assert_allclose(ours.t_hit[lo:hi], their_t[lo:hi][order], rtol=1e-5)
    points = _points(mesh, 400, seed=9).astype(np.float32)
    query = o3d.core.Tensor(points)
    closest = scene.compute_closest_points(query)
    ours_cp = accel.compute_closest_points(points)
    # Same distances; the points themselves may differ where several triangles are
    # (nearly) equidistant, e.g. near the sphere's centre.
    their_d = np.linalg.norm(closest["points"].numpy() - points, axis=1)
    np.testing.assert_allclose(ours_cp.distance, their_d, atol=2e-6)
    assert (ours_cp.distance <= their_d + 2e-6).all()
    np.testing.assert_allclose(
        accel.compute_distance(points), scene.compute_distance(query).numpy(), atol=2e-5
    )
    near = np.abs(np.linalg.norm(points, axis=1) - 1.0) < 0.02
    np.testing.assert_allclose(
        accel.compute_signed_distance(points)[~near],
        scene.compute_signed_distance(query, nsamples=3).numpy()[~near],
        atol=2e-5,
    )
    np.testing.assert_array_equal(
        accel.compute_occupancy(points)[~near],
        scene.compute_occupancy(query, nsamples=3).numpy()[~near],
    )


# -- empty and bad inputs ----------------------------------------------------------------------


def test_empty_inputs():
    accel = _accel(_icosphere(), "bvh2.binned_sah")
    empty = np.zeros((0, 3))
    assert accel.count_intersections(empty, empty).shape == (0,)
    hits = accel.list_intersections(empty, empty)
    np.testing.assert_array_equal(hits.ray_splits, [0])
    assert hits.t_hit.shape == (0,)
    assert hits.primitive_uvs.shape == (0, 2)
    cp = accel.compute_closest_points(empty)
    assert cp.points.shape == (0, 3)
    assert cp.primitive_ids.shape == (0,)
    assert accel.compute_distance(empty).shape == (0,)
    for method in geometry.SIGN_METHODS:
        assert accel.compute_signed_distance(empty, method=method).shape == (0,)
        assert accel.compute_occupancy(empty, method=method).shape == (0,)


def test_degenerate_rays_miss_and_count_nothing():
    accel = _accel(_icosphere(), "bvh2.binned_sah")
    origins = np.array([[0.1, 0.2, -3.0], [0.1, 0.2, -3.0], [np.nan, 0.0, 0.0], [0.1, 0.2, -3.0]])
    directions = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0, 0, 1.0]])
    tmax = np.array([np.inf, np.inf, np.inf, 1.0])  # the last stops short of the sphere
    np.testing.assert_array_equal(
        accel.count_intersections(origins, directions, 0.0, tmax), [2, 0, 0, 0]
    )


@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.zeros((4, 2)), r"points: expected shape \(n, 3\)"),
        (np.zeros(3), r"points: expected shape \(n, 3\)"),
        (np.array([[0.0, np.nan, 0.0]]), "points: point 0 is not finite"),
        (np.array([[0.0, 0.0, 0.0], [np.inf, 0.0, 0.0]]), "points: point 1 is not finite"),
        (np.array([["a", "b", "c"]]), "points: expected a float array"),
        ([[0, 0], [1]], "points: expected"),
    ],
)
def test_bad_points_raise_naming_the_argument(points, match):
    accel = _accel(_icosphere(), "bvh2.binned_sah")
    for query in (
        accel.compute_closest_points, accel.compute_distance,
        accel.compute_signed_distance, accel.compute_occupancy,
    ):  # fmt: skip
        with pytest.raises(ra.InvalidInputError, match=match):
            query(points)


def test_bad_options_and_rays_raise():
    accel = _accel(_icosphere(), "bvh2.binned_sah")
    p = np.zeros((2, 3))
    with pytest.raises(ra.InvalidInputError, match="method: expected one of"):
        accel.compute_signed_distance(p, method="sdf")
    for n_rays in (0, 2, -1, 1.5, True):
        with pytest.raises(ra.InvalidInputError, match="n_rays: expected an odd"):
            accel.compute_occupancy(p, method="parity", n_rays=n_rays)
    with pytest.raises(ra.InvalidInputError, match="directions: expected"):
        accel.count_intersections(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(ra.InvalidInputError, match="tmin: contains NaN"):
        accel.list_intersections(np.zeros((1, 3)), np.ones((1, 3)), np.nan)
