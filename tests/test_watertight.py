"""Watertightness: rays through shared edges and vertices of closed meshes never miss.

The watertight triangle test (Woop et al. 2013) classifies a point on a shared edge
identically from both triangles, and the robust slab test (Ize 2013) never culls a
box such a ray passes through, so a ray that enters a closed mesh must hit it. Rays
are built so that they pass *exactly* through the target whenever float32 allows
(``o = 2p, d = -p``; integer cube and grid coordinates), and within rounding of it
otherwise (edge midpoints on spheres), plus tiny jitter around each target.
"""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.rays.batch import RayBatch

PAIRS = reference.builder_traversal_pairs()


def _closed_meshes() -> dict[str, rayaccel.TriangleMesh]:
    return {
        "icosphere3": reference.icosphere(3),
        "icosphere1-offset": reference.icosphere(1, radius=0.37, centre=(0.3, -1.7, 2.9)),
        "uv_sphere": reference.uv_sphere(16, 32),
        "cube": reference.cube(),
    }


MESHES = _closed_meshes()


@pytest.fixture(scope="module")
def accels():
    cache: dict[tuple[str, str], rayaccel.Accel] = {}

    def get(builder: str, name: str, mesh=None) -> rayaccel.Accel:
        if (builder, name) not in cache:
            # max_leaf_size=1 puts neighbouring triangles in different leaves and boxes.
            cache[builder, name] = rayaccel.build(mesh or MESHES[name], builder,
                                                  **reference.fine_options(builder))
        return cache[builder, name]

    return get


def _targets(mesh: rayaccel.TriangleMesh) -> np.ndarray:
    """Vertices and edge midpoints (float32)."""
    edges, _ = reference.edges_of(mesh)
    v = mesh.vertices
    mid = (v[edges[:, 0]].astype(np.float64) + v[edges[:, 1]]) / 2
    return np.concatenate([v, mid.astype(np.float32)])


def _check_all_hit(accel, rays: RayBatch, traversal: str, label: str) -> None:
    closest = accel.trace(rays, traversal=traversal)
    missed = np.flatnonzero(~closest.hit)
    assert missed.size == 0, (
        f"{missed.size}/{rays.n_rays} rays slipped through [{label}]; first o="
        f"{rays.origin[missed[0]].tolist()} d={rays.direction[missed[0]].tolist()}"
    )
    assert accel.trace(rays, query="any", traversal=traversal).hit.all(), label
    ref = reference.oracle(accel.mesh, rays)
    assert ref.hit.all(), f"the oracle itself is not watertight [{label}]"
    reference.assert_closest_matches(reference.tri9(accel.mesh), rays, closest, ref, label)


@pytest.mark.parametrize("name", list(MESHES))
@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_rays_from_outside_through_vertices_and_edges(accels, builder, traversal, name):
    mesh = MESHES[name]
    accel = accels(builder, name)
    lo, hi = mesh.bounds()
    centre = ((lo.astype(np.float64) + hi) / 2).astype(np.float32)
    p = _targets(mesh) - centre  # relative to the centre: o = c + 2p, d = -p is exact-ish
    rng = np.random.default_rng(0)
    jitter = rng.normal(size=p.shape).astype(np.float32) * np.float32(1e-6)
    origin = np.concatenate([centre + 2 * p, centre + 2 * p])
    direction = np.concatenate([-p, -p + jitter * np.abs(p).max()])
    rays = RayBatch(origin, direction)
    _check_all_hit(accel, rays, traversal, f"{name}/outside")
    # The first hit is at the target (t = 1), within rounding.
    hits = accel.trace(rays.subset(slice(0, len(p))), traversal=traversal)
    assert np.allclose(hits.t, 1.0, atol=1e-4)


@pytest.mark.parametrize("name", list(MESHES))
@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_rays_from_centre_never_miss(accels, builder, traversal, name):
    mesh = MESHES[name]
    accel = accels(builder, name)
    lo, hi = mesh.bounds()
    centre = ((lo.astype(np.float64) + hi) / 2).astype(np.float32)
    rng = np.random.default_rng(1)
    axes = np.array([[s * (i == k) for k in range(3)] for i in range(3) for s in (1.0, -1.0)])
    axes = np.where(axes == 0, np.where(rng.random(axes.shape) < 0.5, 0.0, -0.0), axes)
    direction = np.concatenate([
        _targets(mesh) - centre,
        reference.random_unit(rng, 4000),
        axes,
    ]).astype(np.float32)
    rays = RayBatch(np.broadcast_to(centre, direction.shape), direction)
    _check_all_hit(accel, rays, traversal, f"{name}/centre")


def _cube_rays(size: float = 1.0) -> RayBatch:
    """Exact rays through every cube vertex, edge midpoint and face-diagonal point."""
    s = size
    points = []
    values = (-s, -s / 2, 0.0, s / 2, s)
    for x in values:
        for y in values:
            for z in values:
                p = np.array([x, y, z])
                if np.sum(np.abs(p) == s) >= 1:  # on the surface
                    points.append(p)
    points = np.array(points)
    outward = np.sign(points) * (np.abs(points) == s)
    rays_o, rays_d = [], []
    for perturb in ((0, 0, 0), (1, 0, -1), (-1, 1, 0), (0, -1, 1)):
        d = -(4 * outward + np.asarray(perturb))
        rays_o.append(points - 2 * d)
        rays_d.append(d)
    return RayBatch(np.concatenate(rays_o), np.concatenate(rays_d))


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_cube_exact_edges_and_corners(accels, builder, traversal):
    accel = accels(builder, "cube")
    rays = _cube_rays()
    _check_all_hit(accel, rays, traversal, "cube/exact")
    hits = accel.trace(rays, traversal=traversal)
    assert np.array_equal(hits.t, np.full(rays.n_rays, 2.0, np.float32))


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_grid_plane_exact_vertices_and_edges(accels, builder, traversal):
    n = 12
    mesh = reference.grid_plane(n, z=0.0)
    accel = accels(builder, "grid", mesh)
    half = np.arange(0, 2 * n + 1) / 2.0  # vertices, edge midpoints, diagonal midpoints
    gx, gy = np.meshgrid(half, half, indexing="ij")
    targets = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    batches = []
    for d in ((0, 0, -1), (0, 0, 1), (1, -2, -4), (-3, 1, 4), (0.0, -0.0, -1)):
        d = np.asarray(d, dtype=np.float64)
        batches.append(RayBatch(targets - 2 * d, np.broadcast_to(d, targets.shape)))
    rays = reference.concat(*batches)
    _check_all_hit(accel, rays, traversal, "grid/exact")
    hits = accel.trace(rays, traversal=traversal)
    assert np.array_equal(hits.t, np.full(rays.n_rays, 2.0, np.float32))


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_sphereflake_rays_from_each_centre(accels, builder, traversal):
    from rayaccel.scene.procedural import sphereflake_spheres

    mesh = rayaccel.scenes.get("sphereflake", level=1)
    accel = accels(builder, "sphereflake1", mesh)
    centres, _radii = sphereflake_spheres(1)
    rng = np.random.default_rng(2)
    per = 500
    origin = np.repeat(centres, per, axis=0)
    direction = reference.random_unit(rng, origin.shape[0])
    rays = RayBatch(origin, direction)
    _check_all_hit(accel, rays, traversal, "sphereflake/centres")


def test_teapot_is_not_closed():
    """The teapot (open patches, pole seams) cannot be used for watertightness."""
    mesh = rayaccel.scenes.get("teapot")
    if reference.is_closed(mesh):
        pytest.fail("the teapot is closed now: add it to MESHES in test_watertight.py")
