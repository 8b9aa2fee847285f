"""SBVH: bounded duplication, clipped leaf boxes, quality against binned SAH."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.bvh.builders.sbvh import SbvhOptions
from rayaccel.errors import InvalidInputError


def _long_triangles(n=400, seed=0):
    """Long thin diagonal triangles: where spatial splits pay."""
    rng = np.random.default_rng(seed)
    a = rng.random((n, 3)) * 10
    b = a + rng.normal(size=(n, 3)) * 4
    c = a + rng.normal(size=(n, 3)) * 0.05
    tri = np.stack([a, b, c], axis=1)
    return rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3))


@pytest.mark.parametrize("budget", [0.0, 0.1, 0.5, 1.0])
def test_references_bounded_by_the_budget(budget):
    mesh = _long_triangles()
    bvh = rayaccel.build(mesh, "bvh2.sbvh", duplication_budget=budget).structure
    bvh.validate(mesh.triangles())
    assert bvh.n_refs <= mesh.n_triangles + int(budget * mesh.n_triangles)
    if budget == 0.0:
        assert np.array_equal(np.sort(bvh.prim_index), np.arange(mesh.n_triangles))
    else:
        assert bvh.n_refs > mesh.n_triangles  # spatial splits happened


def test_lower_sah_than_binned_sah_on_long_triangles():
    mesh = _long_triangles()
    sbvh = rayaccel.build(mesh, "bvh2.sbvh").structure.sah_cost()
    binned = rayaccel.build(mesh, "bvh2.binned_sah").structure.sah_cost()
    assert sbvh < binned


def test_leaf_boxes_cover_the_triangle_parts_inside_them():
    """Every sample point of every triangle lies in a leaf that references the triangle."""
    mesh = _long_triangles(150, seed=1)
    bvh = rayaccel.build(mesh, "bvh2.sbvh", max_leaf_size=1).structure
    tri = mesh.triangles().astype(np.float64)
    rng = np.random.default_rng(2)
    uv = rng.random((64, 2))
    uv[uv.sum(axis=1) > 1] = 1 - uv[uv.sum(axis=1) > 1]
    leaves = np.flatnonzero(bvh.node_count > 0)
    leaf_of_slot = np.repeat(leaves[np.argsort(bvh.node_first[leaves])],
                             bvh.node_count[leaves][np.argsort(bvh.node_first[leaves])])
    for t in range(mesh.n_triangles):
        e1, e2 = tri[t, 1] - tri[t, 0], tri[t, 2] - tri[t, 0]
        points = tri[t, 0] + uv[:, :1] * e1 + uv[:, 1:] * e2
        points = np.concatenate([points, tri[t]])
        owners = leaf_of_slot[bvh.prim_index == t]
        lo, hi = bvh.node_lo[owners], bvh.node_hi[owners]
        inside = ((points[:, None, :] >= lo[None] ) & (points[:, None, :] <= hi[None])).all(axis=2)
        assert inside.any(axis=1).all(), f"part of triangle {t} is in no leaf referencing it"


def test_traces_like_the_oracle():
    mesh = _long_triangles(300, seed=3)
    lo, hi = mesh.bounds()
    rays = reference.concat(reference.rays_inside(lo, hi, 2000, seed=1),
                            reference.rays_outside(lo, hi, 2000, seed=2))
    accel = rayaccel.build(mesh, "bvh2.sbvh", max_leaf_size=2)
    ref = reference.oracle(mesh, rays)
    reference.assert_closest_matches(reference.tri9(mesh), rays, accel.trace(rays), ref)


def test_bad_options_name_the_option():
    for bad, name in (({"alpha": -1}, "alpha"), ({"duplication_budget": 5}, "duplication_budget"),
                      ({"n_spatial_bins": 1}, "n_spatial_bins"),
                      ({"spatial_depth_limit": 99}, "spatial_depth_limit")):
        with pytest.raises(InvalidInputError, match=name):
            SbvhOptions(**bad)
