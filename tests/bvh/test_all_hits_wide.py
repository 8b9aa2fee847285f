"""The one-pass all-hits walk of the 8-wide BVH against the brute-force oracle."""

from __future__ import annotations

import numba
import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.bvh.traverse import all_hits_wide
from rayaccel.bvh.traverse.all_hits import list_all_hits
from rayaccel.bvh.traverse.all_hits_wide import list_all_hits_wide
from rayaccel.rays.batch import RayBatch
from rayaccel.scene.mesh import TriangleMesh


def _oracle(mesh, rays):
    """Every (ray, t, prim) hit by testing every triangle, sorted by ray, t, prim."""
    tri = reference.tri9(mesh)
    rr = np.repeat(np.arange(rays.n_rays), mesh.n_triangles)
    ff = np.tile(np.arange(mesh.n_triangles), rays.n_rays)
    ev = reference.eval_prims(tri, rays.subset(rr), ff)
    ok = ev.prim >= 0
    ray, t, prim, u, v = rr[ok], ev.t[ok], ev.prim[ok], ev.u[ok], ev.v[ok]
    order = np.lexsort((prim, t, ray))
    return ray[order], t[order], prim[order], u[order], v[order]


def _check(accel, rays):
    splits, t, prim, u, v = list_all_hits_wide(accel.structure, accel.mesh, rays, {})
    assert splits.dtype == np.int64
    assert splits.shape == (rays.n_rays + 1,)
    assert t.dtype == np.float32
    assert prim.dtype == np.int32
    ray = np.repeat(np.arange(rays.n_rays), np.diff(splits))
    ref_ray, ref_t, ref_prim, ref_u, ref_v = _oracle(accel.mesh, rays)
    assert np.array_equal(ray, ref_ray)
    assert np.array_equal(prim, ref_prim)
    assert t.tobytes() == ref_t.tobytes()
    assert u.tobytes() == ref_u.tobytes()
    assert v.tobytes() == ref_v.tobytes()
    return splits, t, prim, u, v


@pytest.mark.parametrize("scene", ["icosphere", "cornell-box", "teapot"])
def test_every_hit_once_in_order(scene):
    mesh = reference.icosphere(2) if scene == "icosphere" else rayaccel.scenes.get(scene)
    accel = rayaccel.build(mesh)
    rays = reference.mixed_rays(mesh, 400, seed=3)
    _check(accel, rays)


@pytest.mark.parametrize(
    ("key", "options"),
    [
        ("bvh2.sbvh", {}),
        ("bvh2.lbvh+presplit+collapse", {"max_leaf_size": 16, "presplit": {"method": "evh"}}),
    ],
)
def test_split_references_are_listed_once(key, options):
    mesh = rayaccel.scenes.get("teapot")
    accel = rayaccel.build(mesh, key, **options)
    if accel.structure.n_refs == mesh.n_triangles:
        pytest.skip(f"{key} made no split references here")
    _check(accel, reference.mixed_rays(mesh, 300, seed=5))


def test_same_as_the_two_pass_walk():
    mesh = rayaccel.scenes.get("cornell-box")
    accel = rayaccel.build(mesh)
    rays = reference.mixed_rays(mesh, 5000, seed=8)  # parallel kernels
    wide = list_all_hits_wide(accel.structure, accel.mesh, rays, {})
    binary = list_all_hits(accel.structure, accel.mesh, rays, {})
    for a, b in zip(wide, binary, strict=True):
        assert a.tobytes() == b.tobytes()


def _stacked_planes(n_planes: int) -> TriangleMesh:
    """``n_planes`` unit squares at z = 0, 1, ..., two triangles each."""
    quad = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
    vertices = np.concatenate(
        [np.column_stack([quad, np.full(4, float(z))]) for z in range(n_planes)]
    )
    faces = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * z for z in range(n_planes)])
    return TriangleMesh(vertices, faces)


def test_many_hits_per_ray_grow_every_buffer():
    # 40 hits a ray: beyond the first output's room, a chunk buffer and insertion sort.
    n_planes = 40
    assert n_planes > all_hits_wide.HITS_PER_RAY
    assert n_planes > all_hits_wide.INSERTION_SORT_MAX
    assert 64 * n_planes > all_hits_wide.CHUNK_BUFFER
    mesh = _stacked_planes(n_planes)
    accel = rayaccel.build(mesh, max_leaf_size=2)
    rng = np.random.default_rng(2)
    n = 300
    origin = np.column_stack([rng.uniform(0.1, 0.9, (n, 2)), np.full(n, -1.0)])
    direction = np.column_stack([rng.uniform(-0.001, 0.001, (n, 2)), np.ones(n)])
    rays = RayBatch(origin, direction)
    splits, t, _, _, _ = _check(accel, rays)
    assert (np.diff(splits) == n_planes).all()
    assert (np.diff(t.reshape(n, n_planes), axis=1) > 0).all()


def test_identical_for_every_thread_count():
    mesh = rayaccel.scenes.get("teapot")
    accel = rayaccel.build(mesh)
    rays = reference.mixed_rays(mesh, 8000, seed=4)
    before = numba.get_num_threads()
    try:
        runs = []
        for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(threads)
            runs.append(list_all_hits_wide(accel.structure, accel.mesh, rays, {}))
    finally:
        numba.set_num_threads(before)
    for a, b in zip(runs[0], runs[-1], strict=True):
        assert a.tobytes() == b.tobytes()


def test_no_rays_and_rays_that_miss():
    accel = rayaccel.build(rayaccel.scenes.get("cornell-box"))
    splits, t, prim, _, _ = list_all_hits_wide(
        accel.structure, accel.mesh, RayBatch(np.zeros((0, 3)), np.zeros((0, 3))), {}
    )
    assert splits.tolist() == [0]
    assert t.shape == prim.shape == (0,)
    far = RayBatch(np.full((3, 3), 1e6), [[1.0, 0, 0], [0, 0, 0], [0, 1.0, 0]])
    splits, t, _, _, _ = list_all_hits_wide(accel.structure, accel.mesh, far, {})
    assert splits.tolist() == [0, 0, 0, 0]
    assert t.shape == (0,)


def test_wide_layout_is_shared_with_the_wide_traversal():
    accel = rayaccel.build(rayaccel.scenes.get("teapot"))
    cache: dict = {}
    rays = reference.mixed_rays(accel.mesh, 50, seed=1)
    list_all_hits_wide(accel.structure, accel.mesh, rays, cache)
    assert "bvh2.wide8" in cache
