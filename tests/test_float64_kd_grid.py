"""``precision="float64"`` on kd-trees and grids: the float32 structures hold float64 triangles.

Meshes translated to 1e7 (a float32 ulp there is 1, so a float64 triangle sticks out of
its float32 rounding by up to half a unit): every kd and grid builder with each of its
traversals returns the float64 oracle's closest hit (``reference.mt_float64``) and the
oracle's any-hit answer, on the scenes of ``test_float64`` and on a crate of axis-aligned
squares placed half a unit off the float32 planes (the kd splits and the squares' float32
twins lie exactly on those planes). Rays aimed at every vertex and edge of a closed
sphere all hit; a kd-tree without the added references (``rayaccel.kdtree.precision``)
loses some of them and fails ``validate()``. By default each layout's default traversal
runs (the kernels the edge-and-vertex test compiles anyway; each float64 kernel is a
compile of its own); ``--full`` runs every builder × traversal pair.
"""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.api import Accel
from rayaccel.errors import InvalidInputError, StructureInvariantError
from rayaccel.kdtree.layouts.kdtree import KdTree
from rayaccel.rays.batch import RayBatch
from rayaccel.scene import procedural
from test_float64 import (
    SHIFT,
    _check_against_oracle,
    _edge_and_vertex_rays,
    _icosphere,
    _oracle,
    _rays,
)
from test_float64 import _scene as _named_scene

KD_BUILDERS = ("kdtree.sah", "kdtree.median")
GRID_BUILDERS = ("grid.uniform", "grid.distance", "grid.macro_regions", "grid.mipmap",
                 "grid.two_level")  # fmt: skip
CORE = {
    ("kdtree.sah", "kdtree.stack"),
    ("grid.uniform", "grid.dda"),
    ("grid.two_level", "grid.dda"),
}


def _pairs() -> list:
    params = []
    for builder in (*KD_BUILDERS, *GRID_BUILDERS):
        structure = registry.get(builder, "builder").structure
        for traversal in registry.keys("traversal", structure):
            marks = () if (builder, traversal) in CORE else (pytest.mark.cross,)
            params.append(
                pytest.param(builder, traversal, id=f"{builder}-{traversal}", marks=marks)
            )
    return params


def _crate() -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned unit squares (two triangles each) on planes at half-integers.

    Each square lies in a plane ``x``, ``y`` or ``z = k + 0.5`` and spans half-integer
    bounds on its other axes; at 1e7 float32 rounds every coordinate to an even integer,
    so the float32 squares (and the kd splits and cell planes placed at them) lie half a
    unit off the float64 ones.
    """
    rng = np.random.default_rng(11)
    verts = []
    faces = []
    for i in range(60):
        axis = i % 3
        u, v = (axis + 1) % 3, (axis + 2) % 3
        base = rng.integers(0, 8, 3) + 0.5
        size = rng.integers(1, 4, 2).astype(float)
        corners = np.repeat(base[None], 4, axis=0)
        corners[1, u] += size[0]
        corners[2, u] += size[0]
        corners[2, v] += size[1]
        corners[3, v] += size[1]
        first = len(verts) * 4
        verts.append(corners)
        faces += [[first, first + 1, first + 2], [first, first + 2, first + 3]]
    return np.concatenate(verts), np.array(faces)


def _scene(name: str, precision: str = "float64") -> rayaccel.TriangleMesh:
    if name == "crate":
        v, faces = _crate()
        return rayaccel.TriangleMesh(v + SHIFT, faces, "crate", precision=precision)
    return _named_scene(name, precision)


_ACCELS: dict[tuple[str, str, str], Accel] = {}


def _accel(name: str, key: str, precision: str = "float64") -> Accel:
    if (name, key, precision) not in _ACCELS:
        _ACCELS[name, key, precision] = rayaccel.build(_scene(name, precision), key)
    return _ACCELS[name, key, precision]


def _crate_rays(mesh: rayaccel.TriangleMesh, n: int = 300) -> RayBatch:
    """Rays along the axes and at random, aimed at points near the squares' float64 edges."""
    rng = np.random.default_rng(2)
    v = mesh.vertices64
    tri = v[mesh.faces[rng.integers(0, mesh.n_triangles, n)]]
    # Points within 0.4 of a corner: on the part of the square beyond its float32 twin.
    w = np.zeros((n, 3))
    w[np.arange(n), rng.integers(0, 3, n)] = 1.0
    w = 0.9 * w + 0.1 * rng.dirichlet((1.0, 1.0, 1.0), n)
    target = np.einsum("rk,rkc->rc", w, tri)
    d = rng.normal(size=(n, 3))
    axis_aligned = rng.random(n) < 0.5
    d[axis_aligned] = np.eye(3)[rng.integers(0, 3, axis_aligned.sum())]
    d[axis_aligned] += rng.normal(size=(axis_aligned.sum(), 3)) * 1e-3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return RayBatch(target - 25.0 * d, 25.0 * d, precision="float64")


@pytest.mark.parametrize(("builder", "traversal"), _pairs())
@pytest.mark.parametrize("name", ["icosphere", "crate"])
def test_float64_hits_match_float64_oracle(name, builder, traversal):
    accel = _accel(name, builder)
    accel.validate()
    assert accel.precision == "float64"
    rays = _rays(accel.mesh) if name != "crate" else _crate_rays(accel.mesh)
    hits = accel.trace(rays, traversal=traversal)
    if name == "crate":
        _check_crate(accel.mesh, rays, hits)
    else:
        _check_against_oracle(accel.mesh, rays, hits)
    ref_t, _, _ = _oracle_any(accel.mesh, rays)
    blocked = accel.occluded(rays.origin, rays.direction, traversal=traversal)
    np.testing.assert_array_equal(blocked, np.isfinite(ref_t))


def _oracle_any(mesh: rayaccel.TriangleMesh, rays: RayBatch):
    return reference.mt_float64(mesh.hit_rows(), rays)


def _check_crate(mesh, rays: RayBatch, hits) -> None:
    """The oracle's nearest hit; squares overlap, so ties are only by distance."""
    ref_t, ref_prim, margin = _oracle_any(mesh, rays)
    hit = np.isfinite(ref_t)
    assert hit.mean() > 0.9
    np.testing.assert_array_equal(hits.prim >= 0, hit)
    np.testing.assert_allclose(hits.t[hit], ref_t[hit], rtol=1e-9)
    differ = (hits.prim != ref_prim) & (margin > 1e-9)
    same_t = np.abs(hits.t - ref_t) <= 1e-9 * np.abs(ref_t)
    assert not (differ & ~same_t).any()


@pytest.mark.parametrize("builder", ["kdtree.sah", "grid.uniform", "grid.two_level"])
def test_rays_at_edges_and_vertices_do_not_slip_through(builder):
    v, faces = _icosphere()
    mesh = rayaccel.TriangleMesh(v + SHIFT + 0.37, faces, "ico", precision="float64")
    assert reference.is_closed(mesh)
    options = {"max_leaf_size": 1} if builder.startswith("kd") else {}
    accel = rayaccel.build(mesh, builder, **options)
    accel.validate()
    rays = _edge_and_vertex_rays(mesh)
    hits = accel.trace(rays)
    assert hits.hit.all(), np.flatnonzero(~hits.hit)
    np.testing.assert_allclose(hits.t, 1.0, rtol=1e-6)


def test_kdtree_without_added_references_loses_rays():
    """The control: the same kd-tree with its box widened but no references added."""
    v, faces = _icosphere()
    mesh = rayaccel.TriangleMesh(v + SHIFT + 0.37, faces, "ico", precision="float64")
    accel = rayaccel.build(mesh, "kdtree.sah", max_leaf_size=1)
    kd = accel.structure
    variant = registry.get("kdtree.sah", "builder")
    raw = variant.func(mesh, variant.make_options({"max_leaf_size": 1}))
    assert kd.n_refs > raw.n_refs
    narrow = KdTree(raw.nodes, raw.leaf_first, raw.leaf_count, raw.prim_index, kd.lo, kd.hi,
                    raw.n_prims, raw.perfect_splits)  # fmt: skip
    control = Accel(accel.key, mesh, narrow, accel.options, 0.0)
    with pytest.raises(StructureInvariantError, match="float64 triangle"):
        control.validate()
    lost = ~control.trace(_edge_and_vertex_rays(mesh)).hit
    assert lost.sum() > 0


@pytest.mark.parametrize("builder", [*KD_BUILDERS, "grid.uniform", "grid.two_level"])
def test_float64_structures_of_a_soup_validate(builder):
    """A kd-tree's added references need only touch their leaf by the test without the
    plane axis, so ``validate()`` checks its lists for holding every touching triangle, not
    for listing only overlapping ones; a grid's check asks for a triangle only in the cells
    it overlaps by the full test, since the plane axis separates some cells the partial
    test names (the soup has both cases)."""
    soup = procedural.triangle_soup(600, seed=1)
    mesh = rayaccel.TriangleMesh(soup.vertices, soup.faces, precision="float64")
    accel = rayaccel.build(mesh, builder)
    if builder in KD_BUILDERS:
        assert accel.structure.n_refs > rayaccel.build(soup, builder).structure.n_refs
    accel.validate()


@pytest.mark.parametrize("builder", ["kdtree.sah", "grid.uniform"])
def test_float32_loses_what_float64_keeps(builder):
    """The same scene in float32: vertices and ray origins snap to a 1 m grid at 1e7."""
    accel32 = _accel("icosphere", builder, "float32")
    rays = _rays(_scene("icosphere"), seed=1)
    hits = accel32.intersect(rays.origin, rays.direction)
    assert hits.t.dtype == np.float32
    ref_t, ref_prim, _ = _oracle(accel32.mesh, rays)
    hit = np.isfinite(ref_t)
    rel = np.full(rays.n_rays, np.inf)
    rel[hit] = np.abs(hits.t[hit].astype(np.float64) - ref_t[hit]) / ref_t[hit]
    wrong = (hits.prim != ref_prim) | (rel > 1e-3)
    assert wrong.mean() > 0.25, wrong.mean()
    hits64 = _accel("icosphere", builder).intersect(rays.origin, rays.direction)
    _check_against_oracle(_scene("icosphere"), rays, hits64)


def test_irregular_grid_refuses_float64():
    with pytest.raises(InvalidInputError, match=r"grid\.irregular.*float64.*grid\.uniform"):
        rayaccel.build(_scene("icosphere"), "grid.irregular")


def test_float64_kd_and_grid_refit_rebuild():
    """Refitting rebuilds a kd-tree or a grid, which stays conservative."""
    accel = rayaccel.build(_scene("icosphere"), "kdtree.sah")
    moved = accel.mesh.vertices64 + np.array([0.3, -0.2, 0.45])
    report = accel.refit(moved)
    assert report["method"] == "rebuild"
    assert accel.precision == "float64"
    accel.validate()
