"""EPO and LCV against brute-force computations on small scenes; info() keys."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.bvh.metrics import epo, lcv, leaf_counts


def _clip(poly, axis, value, above):
    out = []
    for i in range(len(poly)):
        p, q = poly[i], poly[(i + 1) % len(poly)]
        dp = (p[axis] - value) * (1 if above else -1)
        dq = (q[axis] - value) * (1 if above else -1)
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            out.append(p + dp / (dp - dq) * (q - p))
    return out


def _area_in_box(tri, lo, hi):
    poly = list(tri.astype(np.float64))
    for a in range(3):
        poly = _clip(poly, a, float(lo[a]), True)
        if len(poly) < 3:
            return 0.0
        poly = _clip(poly, a, float(hi[a]), False)
        if len(poly) < 3:
            return 0.0
    cross = sum(np.cross(poly[i] - poly[0], poly[i + 1] - poly[0]) for i in range(1, len(poly) - 1))
    return 0.5 * float(np.linalg.norm(cross))


def _brute_epo(bvh, tri, c_inner=1.2, c_prim=1.0):
    n = bvh.n_nodes
    members = [set() for _ in range(n)]
    for i in range(n - 1, -1, -1):
        if bvh.node_count[i] > 0:
            f = bvh.node_first[i]
            members[i] = set(bvh.prim_index[f:f + bvh.node_count[i]].tolist())
        else:
            c = bvh.node_first[i]
            members[i] = members[c] | members[c + 1]
    total = 0.0
    for i in range(n):
        cost = c_inner if bvh.node_count[i] == 0 else c_prim * bvh.node_count[i]
        for t in range(tri.shape[0]):
            if t not in members[i]:
                total += cost * _area_in_box(tri[t], bvh.node_lo[i], bvh.node_hi[i])
    surface = sum(_area_in_box(t, t.min(axis=0), t.max(axis=0)) for t in tri)
    return total / surface


@pytest.mark.parametrize("key", ["bvh2.lbvh", "bvh2.binned_sah", "bvh2.sbvh"])
def test_epo_matches_brute_force(key):
    rng = np.random.default_rng(4)
    tri = rng.random((60, 1, 3)) * 4 + rng.normal(size=(60, 3, 3)) * 0.6
    mesh = rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(180).reshape(-1, 3))
    bvh = rayaccel.build(mesh, key, max_leaf_size=2).structure
    tri32 = mesh.triangles()
    expected = _brute_epo(bvh, tri32) if bvh.n_refs == bvh.n_prims else None
    value = epo(bvh, tri32)
    assert value >= 0
    if expected is not None:
        assert value == pytest.approx(expected, rel=1e-6, abs=1e-9)


def test_sbvh_has_lower_epo_than_binned_sah():
    mesh = rayaccel.scenes.get("cornell-box")
    values = {k: epo(rayaccel.build(mesh, k).structure, mesh.triangles())
              for k in ("bvh2.binned_sah", "bvh2.sbvh")}
    assert values["bvh2.sbvh"] <= values["bvh2.binned_sah"]


def test_leaf_counts_and_lcv_match_brute_force():
    mesh = rayaccel.scenes.get("teapot")
    accel = rayaccel.build(mesh, "bvh2.binned_sah")
    bvh = accel.structure
    lo, hi = mesh.bounds()
    rays = reference.concat(reference.rays_inside(lo, hi, 300, seed=1),
                            reference.rays_outside(lo, hi, 300, seed=2))
    t_hit = np.minimum(accel.trace(rays).t, rays.tmax)
    counts = leaf_counts(bvh, rays.origin, rays.direction, rays.tmin, t_hit)
    leaves = np.flatnonzero(bvh.node_count > 0)
    o = rays.origin.astype(np.float64)[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / rays.direction.astype(np.float64)[:, None, :]
        a = (bvh.node_lo[leaves][None].astype(np.float64) - o) * inv
        b = (bvh.node_hi[leaves][None].astype(np.float64) - o) * inv
    near = np.nanmax(np.minimum(a, b), axis=2)
    far = np.nanmin(np.maximum(a, b), axis=2)
    near = np.maximum(near, rays.tmin[:, None])
    far = np.minimum(far, t_hit[:, None])
    expected = (near <= far).sum(axis=1)
    # A leaf only counts when its ancestors are crossed too; boxes nest, so equal.
    assert np.array_equal(counts, expected)
    assert lcv(counts) == pytest.approx(np.std(expected))
    info = accel.info(epo=True, lcv_rays=rays)
    assert info["lcv"] == pytest.approx(np.std(expected))
    assert info["epo"] > 0
    assert info["refs_per_prim"] == 1.0
    assert accel.info(inner_cost=0.0)["sah"] < info["sah"]
