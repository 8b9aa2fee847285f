"""Leak test (issue 20): rays aimed exactly at shared edges and vertices never miss.

The CI tier of ``benchmarks/leak_test.py``: the same ray generator
(:mod:`leak_rays`: inside and outside rays through points exactly on the edges and
at the vertices of closed meshes, where float32 allows), on a few thousand rays per
case. Cases: every traversal on its structure's default builder, and every builder
with its structure's default traversal, closest and any hit; every ray must hit,
with the oracle's answer. ``test_watertight.py`` covers the sphere and cube families
through their centres; this file adds non-convex and jittered closed meshes, the
sphereflake's spheres and the closed parts of a file scene, with origins inside and
outside each part. ``--full`` traces every generated ray.
"""

from __future__ import annotations

import numpy as np
import pytest

import leak_rays
import rayaccel
import reference
from conftest import scene_file

pytestmark = pytest.mark.slow

CASES = [pytest.param(b, t, id=f"{b}-{t}") for b, t in leak_rays.leak_cases()]
#: Rays per mesh per case without ``--full``.
CI_RAYS = 700
#: The file scene whose closed parts are used (about 24k triangles in 8 parts).
FILE_SCENE = "living_room"
FILE_RAYS = 1500


def _procedural_meshes() -> dict[str, rayaccel.TriangleMesh]:
    return {
        "icosphere2-offset": reference.icosphere(2, radius=0.37, centre=(0.3, -1.7, 2.9)),
        "cube": reference.cube(),
        "torus": leak_rays.torus(24, 12),
        "icosphere2-jittered": leak_rays.jittered(reference.icosphere(2), 0.02, seed=1),
        "sphereflake1": leak_rays.closed_parts(
            rayaccel.scenes.get("sphereflake", level=1), "sphereflake1"
        ),
    }


class _Sets:
    """Module-wide memo of meshes, ray sets, oracles and accels."""

    def __init__(self) -> None:
        self.meshes: dict[str, rayaccel.TriangleMesh] = {}
        self.rays: dict[str, leak_rays.LeakRays] = {}
        self.oracles: dict[str, rayaccel.HitBatch] = {}
        self.accels: dict[tuple[str, str], rayaccel.Accel] = {}

    def mesh(self, name: str) -> rayaccel.TriangleMesh:
        if name not in self.meshes:
            if name == FILE_SCENE:
                if scene_file(FILE_SCENE) is None:
                    pytest.skip(f"scene {FILE_SCENE!r} not found (RAYACCEL_SCENE_PATH)")
                mesh = leak_rays.closed_parts(rayaccel.scenes.get(FILE_SCENE))
                assert mesh is not None, f"{FILE_SCENE} has no closed part any more"
                self.meshes[name] = mesh
            else:
                self.meshes.update(_procedural_meshes())
        return self.meshes[name]

    def ray_set(self, name: str, n: int | None) -> leak_rays.LeakRays:
        if name not in self.rays:
            full = leak_rays.leak_rays(self.mesh(name), per_edge=2, seed=7, name=name)
            if n is not None and full.n_rays > n:
                pick = np.sort(np.random.default_rng(3).choice(full.n_rays, n, replace=False))
                full = full.subset(pick)
            self.rays[name] = full
        return self.rays[name]

    def oracle(self, name: str) -> rayaccel.HitBatch:
        if name not in self.oracles:
            self.oracles[name] = reference.oracle(self.mesh(name), self.rays[name].rays)
        return self.oracles[name]

    def accel(self, builder: str, name: str) -> rayaccel.Accel:
        if (builder, name) not in self.accels:
            self.accels[builder, name] = rayaccel.build(self.mesh(name), builder)
        return self.accels[builder, name]


@pytest.fixture(scope="module")
def sets() -> _Sets:
    return _Sets()


PROCEDURAL = ("icosphere2-offset", "cube", "torus", "icosphere2-jittered", "sphereflake1")


def _check(sets: _Sets, builder: str, traversal: str, name: str, n: int | None) -> None:
    leaks = sets.ray_set(name, n)
    rays = leaks.rays
    ref = sets.oracle(name)
    assert (ref.prim >= 0).all(), f"the oracle misses rays of {name}: the generator is wrong"
    accel = sets.accel(builder, name)
    tri = reference.tri9(accel.mesh)
    label = f"{builder}/{traversal}/{name}"
    closest = accel.trace(rays, traversal=traversal)
    missed = np.flatnonzero(closest.prim < 0)
    assert missed.size == 0, (
        f"{missed.size}/{rays.n_rays} rays leak [{label}/closest]; first: "
        f"o={rays.origin[missed[0]].tolist()} d={rays.direction[missed[0]].tolist()} "
        f"exact={bool(leaks.exact[missed[0]])} outside={bool(leaks.outside[missed[0]])}"
    )
    reference.assert_closest_matches(tri, rays, closest, ref, label)
    any_hit = accel.trace(rays, query="any", traversal=traversal)
    missed = np.flatnonzero(any_hit.prim < 0)
    assert missed.size == 0, f"{missed.size}/{rays.n_rays} rays leak [{label}/any]"
    reference.assert_any_matches(tri, rays, any_hit, ref, label)


@pytest.mark.parametrize(("builder", "traversal"), CASES)
def test_no_leaks_on_procedural_closed_meshes(sets, full, builder, traversal):
    for name in PROCEDURAL:
        _check(sets, builder, traversal, name, None if full else CI_RAYS)


@pytest.mark.scenes
@pytest.mark.parametrize(("builder", "traversal"), CASES)
def test_no_leaks_on_the_closed_parts_of_a_file_scene(sets, full, builder, traversal):
    _check(sets, builder, traversal, FILE_SCENE, None if full else FILE_RAYS)


@pytest.mark.parametrize("name", PROCEDURAL)
def test_the_generator_aims_exactly_where_float32_allows(sets, name):
    """Inside and outside rays, at vertices and on edges; a share of them exact."""
    leaks = sets.ray_set(name, None)
    assert leaks.dropped["targets without an interior point"] == 0
    assert leaks.outside.any()
    assert (~leaks.outside).any()
    assert (leaks.target_kind == 0).any()
    assert (leaks.target_kind == 1).any()
    # Exact: the float32 target is on the edge (or a vertex) and o + t·d passes through it.
    exact = leaks.exact
    assert exact.mean() > 0.2, f"{name}: only {exact.mean():.0%} of the rays are exact"
    p = leaks.rays.origin[exact].astype(np.float64) + leaks.rays.direction[exact]
    assert np.all(np.isfinite(p))
    if name == "cube":  # integer corners: every edge point at a dyadic fraction is exact
        assert leaks.exact[leaks.target_kind == 1].mean() > 0.9


def test_the_closed_parts_of_a_mesh():
    closed = reference.icosphere(1)
    open_part = reference.grid_plane(2, z=5.0)
    both = rayaccel.TriangleMesh(
        np.concatenate([closed.vertices, open_part.vertices]),
        np.concatenate([closed.faces, open_part.faces + closed.n_vertices]),
    )
    parts = leak_rays.closed_parts(both)
    assert parts is not None
    assert parts.n_triangles == closed.n_triangles
    assert reference.is_closed(parts)
    assert leak_rays.closed_parts(open_part) is None
    # A flipped triangle makes its component inconsistently oriented: dropped.
    flipped = closed.faces.copy()
    flipped[0] = flipped[0, ::-1]
    assert leak_rays.closed_parts(rayaccel.TriangleMesh(closed.vertices, flipped)) is None
