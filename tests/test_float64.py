"""``precision="float64"``: huge coordinates (geospatial, CAD) traced in float64 end to end.

Meshes translated to 1e7 (a float32 ulp there is 1): the float64 accel's hits equal a
float64 Möller–Trumbore oracle (``reference.mt_float64``) ray for ray, the same mesh in
float32 visibly does not, and the widened float32 boxes (``rayaccel.bvh.precision``) let
no ray aimed at an edge or a vertex slip through. Only ``bvh2.stack`` and ``bvh2.wide``
run by default (each traversal compiles a float64 kernel); ``--full`` adds every other
``bvh2`` traversal.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.api import Accel
from rayaccel.bvh.builders.refit_vertices import refit_bvh2
from rayaccel.errors import InvalidInputError
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene import catalog

SHIFT = np.array([1.0e7, -1.0e7, 1.0e7])
CORE_TRAVERSALS = ("bvh2.stack", "bvh2.wide")
N_RAYS = 300


def _traversal_params() -> list:
    params = []
    for key in registry.keys("traversal", "bvh2"):
        marks = () if key in CORE_TRAVERSALS else (pytest.mark.cross,)
        params.append(pytest.param(key, id=key, marks=marks))
    return params


def _teapot() -> tuple[np.ndarray, np.ndarray]:
    """The teapot's vertices scaled to about 10 m, and its faces."""
    mesh = catalog.get("teapot")
    v = mesh.vertices.astype(np.float64)
    v = (v - v.min(axis=0)) / np.ptp(v, axis=0).max() * 10.0
    return v, mesh.faces


def _icosphere() -> tuple[np.ndarray, np.ndarray]:
    mesh = reference.icosphere(3)
    return mesh.vertices.astype(np.float64) * 5.0, mesh.faces


def _terrain(n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A 240 m square of terrain with a few metres of relief (heights to the millimetre)."""
    rng = np.random.default_rng(7)
    xs = np.arange(n + 1) * 10.0
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    relief = 2.0 * np.sin(gx / 37.0) * np.cos(gy / 23.0) + rng.random(gx.shape) * 0.5
    v = np.stack([gx.ravel(), gy.ravel(), np.round(relief.ravel(), 3)], axis=1)
    return v, reference.grid_plane(n).faces


SCENES = {"teapot": _teapot, "icosphere": _icosphere, "terrain": _terrain}


def _scene(name: str, precision: str) -> rayaccel.TriangleMesh:
    v, faces = SCENES[name]()
    return rayaccel.TriangleMesh(v + SHIFT, faces, name, precision=precision)


def _rays(mesh: rayaccel.TriangleMesh, n: int = N_RAYS, seed: int = 0) -> RayBatch:
    """Rays from within 30 m of the mesh towards random points of its triangles."""
    rng = np.random.default_rng(seed)
    v = mesh.vertices64
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    o = centre + (rng.random((n, 3)) - 0.5) * (hi - lo + 30.0)
    o[:, 2] = hi[2] + 1.0 + rng.random(n) * 30.0  # above: the terrain is seen from the air
    tri = v[mesh.faces[rng.integers(0, mesh.n_triangles, n)]]
    w = rng.dirichlet((1.0, 1.0, 1.0), n)
    target = np.einsum("rk,rkc->rc", w, tri)
    return RayBatch(o, target - o, precision="float64")


_ACCELS: dict[tuple[str, str], Accel] = {}


def _accel(name: str, precision: str = "float64") -> Accel:
    key = (name, precision)
    if key not in _ACCELS:
        _ACCELS[key] = rayaccel.build(_scene(name, precision), "bvh2.binned_sah")
    return _ACCELS[key]


def _oracle(mesh: rayaccel.TriangleMesh, rays: RayBatch):
    return reference.mt_float64(_scene(mesh.name, "float64").hit_rows(), rays)


def _check_against_oracle(mesh, rays: RayBatch, hits: HitBatch) -> None:
    ref_t, ref_prim, margin = _oracle(mesh, rays)
    assert hits.t.dtype == np.float64
    assert hits.u.dtype == np.float64
    hit = np.isfinite(ref_t)
    assert hit.sum() > 0.9 * rays.n_rays, "the rays are aimed at the mesh"
    np.testing.assert_array_equal(hits.prim >= 0, hit)
    rel = np.abs(hits.t[hit] - ref_t[hit]) / ref_t[hit]
    assert rel.max() < 1e-9, rel.max()
    # The same triangle, except for hits within a rounding error of an edge (ties).
    differ = (hits.prim != ref_prim) & (margin > 1e-9)
    assert not differ.any(), np.flatnonzero(differ)
    # Barycentrics: the hit point on the float64 triangle is the point on the ray.
    tri = mesh.vertices64[mesh.faces[hits.prim[hit]]]
    u, v = hits.u[hit, None], hits.v[hit, None]
    on_triangle = (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
    on_ray = rays.origin[hit] + hits.t[hit, None] * rays.direction[hit]
    assert np.abs(on_triangle - on_ray).max() < 1e-6


@pytest.mark.parametrize("traversal", _traversal_params())
@pytest.mark.parametrize("name", list(SCENES))
def test_float64_hits_match_float64_oracle(name, traversal):
    accel = _accel(name)
    accel.validate()
    assert accel.precision == "float64"
    assert accel.info()["precision"] == "float64"
    rays = _rays(accel.mesh)
    hits = accel.trace(rays, traversal=traversal)
    _check_against_oracle(accel.mesh, rays, hits)
    # The same through intersect() with plain float64 arrays.
    again = accel.intersect(rays.origin, rays.direction, traversal=traversal)
    np.testing.assert_array_equal(again.prim, hits.prim)
    np.testing.assert_array_equal(again.t, hits.t)


def test_float64_any_hit_and_stats():
    accel = _accel("icosphere")
    rays = _rays(accel.mesh, seed=3)
    ref_t, _, _ = _oracle(accel.mesh, rays)
    blocked = accel.occluded(rays.origin, rays.direction, tmax=np.where(np.isfinite(ref_t), 1e9, 1))
    np.testing.assert_array_equal(blocked, np.isfinite(ref_t))
    with_stats = accel.intersect(rays.origin, rays.direction, stats=True)
    plain = accel.intersect(rays.origin, rays.direction)
    np.testing.assert_array_equal(with_stats.t, plain.t)
    assert (with_stats.stats["prim_tests"] >= plain.hit).all()


@pytest.mark.parametrize("name", list(SCENES))
def test_float32_loses_what_float64_keeps(name):
    """The same scene in float32: vertices and ray origins snap to a 1 m grid at 1e7."""
    accel32 = _accel(name, "float32")
    rays = _rays(_accel(name).mesh, seed=1)
    hits = accel32.intersect(rays.origin, rays.direction)
    assert hits.t.dtype == np.float32
    ref_t, ref_prim, _ = _oracle(accel32.mesh, rays)
    hit = np.isfinite(ref_t)
    rel = np.full(rays.n_rays, np.inf)
    rel[hit] = np.abs(hits.t[hit].astype(np.float64) - ref_t[hit]) / ref_t[hit]
    wrong = (hits.prim != ref_prim) | (rel > 1e-3)
    assert wrong.mean() > 0.25, wrong.mean()


def _edge_and_vertex_rays(mesh: rayaccel.TriangleMesh) -> RayBatch:
    """Rays from outside through every vertex and every edge midpoint, in float64."""
    v = mesh.vertices64
    edges, _ = reference.edges_of(mesh)
    targets = np.concatenate([v, (v[edges[:, 0]] + v[edges[:, 1]]) / 2])
    centre = v.mean(axis=0)
    rng = np.random.default_rng(5)
    outward = targets - centre
    outward /= np.linalg.norm(outward, axis=1, keepdims=True)
    o = targets + 20.0 * outward + rng.normal(size=targets.shape) * 3.0
    return RayBatch(o, targets - o, precision="float64")


def test_rays_at_edges_and_vertices_do_not_slip_through():
    """A closed float64 sphere at 1e7: every ray through a vertex or an edge hits it.

    The control: the same tree with its boxes recomputed from the float32 vertices but
    not widened (``rayaccel.bvh.precision``) loses some of these rays, so the widening is
    what keeps them.
    """
    v, faces = _icosphere()
    mesh = rayaccel.TriangleMesh(v + SHIFT + 0.37, faces, "ico", precision="float64")
    assert reference.is_closed(mesh)
    accel = rayaccel.build(mesh, "bvh2.binned_sah", max_leaf_size=1)
    rays = _edge_and_vertex_rays(mesh)
    for traversal in CORE_TRAVERSALS:
        hits = accel.trace(rays, traversal=traversal)
        assert hits.hit.all(), (traversal, np.flatnonzero(~hits.hit))
        np.testing.assert_allclose(hits.t, 1.0, rtol=1e-6)  # at the target, t = 1
    # Control: boxes of the float32 rounding only.
    narrow = refit_bvh2(accel.structure, mesh.vertices, mesh.faces)
    control = Accel(accel.key, mesh, narrow, accel.options, 0.0)
    lost = ~control.trace(rays, traversal="bvh2.stack").hit
    assert lost.sum() > 0


@pytest.mark.parametrize("key", ["bvh2.binned_sah", "bvh2.sbvh", "bvh2.binned_sah+presplit"])
def test_boxes_contain_the_float64_triangles(key):
    """Every leaf box holds its triangles' float64 corners (split references included)."""
    mesh = _scene("icosphere", "float64")
    accel = rayaccel.build(mesh, key)
    accel.validate()
    bvh = accel.structure
    for node in np.flatnonzero(bvh.node_count > 0):
        first, count = bvh.node_first[node], bvh.node_count[node]
        corners = mesh.vertices64[mesh.faces[bvh.prim_index[first : first + count]]]
        corners = corners.reshape(-1, 3)
        assert (corners >= bvh.node_lo[node]).all()
        assert (corners <= bvh.node_hi[node]).all()


def test_precision_is_checked():
    v, faces = _icosphere()
    for bad in ("float16", "double", None, np.float64):
        with pytest.raises(InvalidInputError, match="precision"):
            rayaccel.TriangleMesh(v, faces, precision=bad)
        with pytest.raises(InvalidInputError, match="precision"):
            RayBatch(v, v, precision=bad)
    mesh = rayaccel.TriangleMesh(v + SHIFT, faces, precision="float64")
    with pytest.raises(InvalidInputError, match=r"float64.*grid\.uniform"):
        rayaccel.build(mesh, "grid.irregular")
    # The pausable traversal (a float32 debugging view) refuses rather than round.
    accel = _accel("icosphere")
    o, d = SHIFT + 20.0, -np.ones(3)
    with pytest.raises(InvalidInputError, match=r"traversal_state.*float64 accel"):
        accel.traversal_state(o[None], d[None])


def test_float32_default_is_unchanged():
    v, faces = _icosphere()
    mesh = rayaccel.TriangleMesh(v, faces)
    assert mesh.precision == "float32"
    assert mesh.vertices64 is None
    assert mesh.hit_rows().dtype == np.float32
    rays = RayBatch(np.zeros((4, 3)) + 20.0, -np.ones((4, 3)))
    assert rays.precision == "float32"
    assert rays.origin.dtype == np.float32
    accel = rayaccel.build(mesh)
    assert accel.info()["precision"] == "float32"
    assert accel.intersect(rays.origin, rays.direction).t.dtype == np.float32


def test_float64_accel_keeps_its_precision(tmp_path):
    """float32 batches are promoted; pickling, saving and refitting keep float64."""
    accel = _accel("icosphere")
    mesh = accel.mesh
    assert mesh.vertices.dtype == np.float32
    assert mesh.vertices64.dtype == np.float64
    assert mesh.hit_rows().dtype == np.float64
    rays = _rays(mesh, n=64, seed=4)
    hits = accel.trace(rays)
    # A float32 batch is traced as float64 (its values are then float32-rounded).
    rays32 = rays.astype("float32")
    assert rays32.precision == "float32"
    assert accel.trace(rays32).t.dtype == np.float64
    copy = pickle.loads(pickle.dumps(accel))
    assert copy.precision == "float64"
    np.testing.assert_array_equal(copy.trace(rays).t, hits.t)
    loaded = rayaccel.load_accel(accel.save(tmp_path / "ico64.npz"))
    assert loaded.precision == "float64"
    np.testing.assert_array_equal(loaded.mesh.vertices64, mesh.vertices64)
    np.testing.assert_array_equal(loaded.trace(rays).t, hits.t)
    # Refit to moved float64 vertices: the boxes still hold the float64 triangles.
    moved = mesh.vertices64 + np.array([0.3, -0.2, 0.45])
    refitted = pickle.loads(pickle.dumps(accel))
    refitted.refit(moved)
    assert refitted.precision == "float64"
    fresh = rayaccel.build(rayaccel.TriangleMesh(moved, mesh.faces, precision="float64"), accel.key)
    shifted = rays.origin + np.array([0.3, -0.2, 0.45])
    moved_rays = RayBatch(shifted, rays.direction, precision="float64")
    np.testing.assert_array_equal(refitted.trace(moved_rays).prim, fresh.trace(moved_rays).prim)


# -- Open3D-style geometry queries in float64 ------------------------------------------------


def _all_hits_float64(tri: np.ndarray, rays: RayBatch) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every ``(t, prim)`` of each ray by float64 Möller–Trumbore, sorted by ``t``."""
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = []
    for o, d in zip(rays.origin, rays.direction, strict=True):
        p = np.cross(d, e2)
        det = (e1 * p).sum(1)
        inv = 1.0 / np.where(det != 0, det, 1.0)
        s = o - a
        u = (s * p).sum(1) * inv
        q = np.cross(s, e1)
        v = (q * d).sum(1) * inv
        t = (q * e2).sum(1) * inv
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0)
        idx = np.flatnonzero(hit)
        order = np.argsort(t[idx], kind="stable")
        out.append((t[idx][order], idx[order]))
    return out


def _point_triangle_d2(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Squared float64 distance from ``p`` to every triangle (interior or nearest edge)."""
    a, b, c = tri[:, 0] - p, tri[:, 1] - p, tri[:, 2] - p  # moved to the point: exact-ish
    best = np.full(len(tri), np.inf)
    for s, e in ((a, b), (b, c), (c, a)):
        d = e - s
        t = np.clip(-(s * d).sum(1) / (d * d).sum(1), 0.0, 1.0)
        best = np.minimum(best, ((s + t[:, None] * d) ** 2).sum(1))
    n = np.cross(b - a, c - a)
    h = (a * n).sum(1) / (n * n).sum(1)
    q = h[:, None] * n
    inside = np.ones(len(tri), dtype=bool)
    for s, e in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(e - s, q - s) * n).sum(1) >= 0
    return np.where(inside, np.minimum(best, (q**2).sum(1)), best)


def _shell_points(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points inside (radius < 4.3) and outside (radius > 5.5) the sphere of radius 5."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radius = np.where(np.arange(n) % 2 == 0, rng.uniform(3.0, 4.3, n), rng.uniform(5.5, 7.0, n))
    return SHIFT + d * radius[:, None], np.arange(n) % 2 == 0


@pytest.mark.parametrize("key", ["bvh2.binned_sah", "bvh2.sbvh", "kdtree.sah", "grid.uniform"])
def test_geometry_queries_answer_in_float64(key):
    """count/list intersections, closest points, distances, signed distance and occupancy
    of a sphere at 1e7 equal float64 numpy oracles (a companion BVH serves kd and grid)."""
    mesh = _scene("icosphere", "float64")
    accel = rayaccel.build(mesh, key)
    tri = mesh.vertices64[mesh.faces]
    rays = _rays(mesh, n=64, seed=6)
    listed = accel.list_intersections(rays.origin, rays.direction)
    counts = accel.count_intersections(rays.origin, rays.direction)
    assert listed.t_hit.dtype == np.float64
    assert listed.primitive_uvs.dtype == np.float64
    for r, (ref_t, ref_prim) in enumerate(_all_hits_float64(tri, rays)):
        got = slice(listed.ray_splits[r], listed.ray_splits[r + 1])
        assert counts[r] == ref_t.size
        np.testing.assert_array_equal(listed.primitive_ids[got], ref_prim)
        np.testing.assert_allclose(listed.t_hit[got], ref_t, rtol=1e-9)
    points, inside = _shell_points(60, seed=8)
    near = SHIFT + (points - SHIFT) * 5.0 / np.linalg.norm(points - SHIFT, axis=1)[:, None]
    near += np.random.default_rng(9).normal(size=near.shape) * 0.3
    points = np.concatenate([points, near])
    d2 = np.array([_point_triangle_d2(tri, p) for p in points])
    ref = np.sqrt(d2.min(axis=1))
    closest = accel.compute_closest_points(points)
    for name in ("points", "primitive_uvs", "primitive_normals", "distance"):
        assert closest[name].dtype == np.float64, name
    np.testing.assert_allclose(closest.distance, ref, rtol=0, atol=1e-7)
    np.testing.assert_allclose(
        np.linalg.norm(closest.points - points, axis=1), closest.distance, rtol=0, atol=1e-7
    )
    same = d2[np.arange(len(points)), closest.primitive_ids] <= d2.min(axis=1) + 1e-9
    assert same.all()
    distance = accel.compute_distance(points)
    assert distance.dtype == np.float64
    np.testing.assert_allclose(distance, ref, rtol=0, atol=1e-7)
    shells = points[:60]
    for method in ("winding", "parity"):
        signed = accel.compute_signed_distance(shells, method=method)
        assert signed.dtype == np.float64
        np.testing.assert_allclose(signed, np.where(inside, -ref[:60], ref[:60]), atol=1e-7)
        occupancy = accel.compute_occupancy(shells, method=method)
        assert occupancy.dtype == np.float64
        np.testing.assert_array_equal(occupancy, inside.astype(float))


def test_float32_geometry_queries_lose_what_float64_keeps():
    """The same sphere in float32: its vertices snap to a 1 m grid, distances err by ~0.5 m."""
    mesh64 = _scene("icosphere", "float64")
    accel32 = rayaccel.build(_scene("icosphere", "float32"), "bvh2.binned_sah")
    points, _ = _shell_points(60, seed=8)
    ref = np.sqrt(np.array([_point_triangle_d2(mesh64.vertices64[mesh64.faces], p).min()
                            for p in points]))  # fmt: skip
    err32 = np.abs(accel32.compute_distance(points).astype(np.float64) - ref)
    err64 = np.abs(_accel("icosphere").compute_distance(points) - ref)
    assert err64.max() < 1e-7
    assert np.median(err32) > 0.05, np.median(err32)
