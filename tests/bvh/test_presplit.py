"""Pre-splitting (+presplit): every builder taking refs, both methods, against the oracle."""

from __future__ import annotations

import dataclasses

import numba
import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.bvh.builders.refs import BuildRefs, remove_leaf_duplicates, triangle_refs
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.steps.presplit import PresplitOptions, presplit
from rayaccel.errors import InvalidInputError

REF_BUILDERS = [v.key for v in registry.variants("builder", "bvh2") if v.takes_refs]
METHODS = ("median", "evh")


def _long_triangles(n=300, seed=0):
    """Long thin diagonal triangles (boxes much larger than the triangles)."""
    rng = np.random.default_rng(seed)
    a = rng.random((n, 3)) * 10
    b = a + rng.normal(size=(n, 3)) * 4
    c = a + rng.normal(size=(n, 3)) * 0.05
    tri = np.stack([a, b, c], axis=1)
    return rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3))


_MESHES: dict = {}


def _mesh(name):
    if name not in _MESHES:
        _MESHES[name] = _long_triangles() if name == "long" else rayaccel.scenes.get(name)
    return _MESHES[name]


def _rays(mesh, seed):
    lo, hi = mesh.bounds()
    return reference.concat(
        reference.rays_inside(lo, hi, 600, seed),
        reference.rays_outside(lo, hi, 600, seed + 1),
        reference.rays_intervals(lo, hi, 200, seed + 2),
    )


def test_every_bvh2_builder_takes_refs():
    # bvh2.insertion is wired by the lead; the others must take refs.
    expected = {"bvh2.lbvh", "bvh2.ploc", "bvh2.binned_sah", "bvh2.sweep_sah", "bvh2.sbvh"}
    assert expected <= set(REF_BUILDERS)
    assert registry.get("bvh2+presplit").stage == "before"
    assert registry.get("bvh2+collapse").stage == "after"


@pytest.mark.parametrize("scene", ["long", "teapot-in-stadium"])
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("builder", REF_BUILDERS)
def test_presplit_builds_validate_and_match_the_oracle(builder, method, scene):
    mesh = _mesh(scene)
    accel = rayaccel.build(mesh, builder + "+presplit", presplit={"method": method})
    accel.validate()
    bvh = accel.structure
    assert list(accel.step_ms) == ["bvh2+presplit", builder]
    if scene == "long":
        assert bvh.n_refs > mesh.n_triangles  # something was split and kept
    rays = _rays(mesh, seed=len(builder) + len(method))
    ref = reference.oracle(mesh, rays)
    tri = reference.tri9(mesh)
    label = f"{builder}+presplit/{method}/{scene}"
    reference.assert_closest_matches(tri, rays, accel.trace(rays), ref, label)
    reference.assert_any_matches(tri, rays, accel.trace(rays, query="any"), ref, label)


def test_refs_cover_their_triangles_and_stay_inside_their_boxes():
    mesh = _mesh("long")
    whole = triangle_refs(mesh)
    tri = mesh.triangles().astype(np.float64)
    rng = np.random.default_rng(4)
    uv = rng.random((48, 2))
    uv[uv.sum(axis=1) > 1] = 1 - uv[uv.sum(axis=1) > 1]
    for method in METHODS:
        refs = presplit(mesh, PresplitOptions(method=method))
        assert np.all(np.diff(refs.prim) >= 0)  # pieces contiguous, in triangle order
        assert np.array_equal(np.unique(refs.prim), np.arange(mesh.n_triangles))
        assert (refs.lo >= whole.lo[refs.prim]).all()
        assert (refs.hi <= whole.hi[refs.prim]).all()
        for t in range(0, mesh.n_triangles, 7):
            e1, e2 = tri[t, 1] - tri[t, 0], tri[t, 2] - tri[t, 0]
            points = np.concatenate([tri[t, 0] + uv[:, :1] * e1 + uv[:, 1:] * e2, tri[t]])
            sel = refs.prim == t
            lo, hi = refs.lo[sel], refs.hi[sel]
            inside = ((points[:, None] >= lo[None]) & (points[:, None] <= hi[None])).all(axis=2)
            assert inside.any(axis=1).all(), f"{method}: part of triangle {t} is in no piece"


@pytest.mark.parametrize("budget", [0.0, 0.1, 0.5])
def test_median_budget_bounds_the_reference_count(budget):
    mesh = _mesh("long")
    n = mesh.n_triangles
    refs = presplit(mesh, PresplitOptions(method="median", budget=budget))
    assert refs.n_refs <= n + int(budget * n)
    if budget == 0.0:
        assert np.array_equal(refs.prim, np.arange(n))
    else:
        assert refs.n_refs >= n + int(0.8 * budget * n)  # most of the budget is used
    bvh = rayaccel.build(
        mesh, "bvh2.binned_sah+presplit", presplit={"method": "median", "budget": budget}
    ).structure
    assert bvh.n_refs <= refs.n_refs


def test_evh_threshold_and_depth_control_the_splits():
    mesh = _mesh("long")
    counts = [
        presplit(mesh, PresplitOptions(method="evh", threshold_exponent=t)).n_refs
        for t in (4, 14, 20)
    ]
    assert mesh.n_triangles <= counts[0] < counts[1] < counts[2]
    assert presplit(mesh, PresplitOptions(method="evh", max_depth=0)).n_refs == mesh.n_triangles
    shallow = presplit(mesh, PresplitOptions(method="evh", threshold_exponent=30, max_depth=2))
    assert np.bincount(shallow.prim).max() <= 4
    # Axis-aligned geometry has zero edge volumes: the stadium and its teapot stay whole.
    stadium = _mesh("teapot-in-stadium")
    assert presplit(stadium, PresplitOptions(method="evh")).n_refs == stadium.n_triangles


@pytest.mark.parametrize("builder", ["bvh2.lbvh", "bvh2.binned_sah"])
def test_presplit_lowers_the_sah_on_long_diagonal_triangles(builder):
    mesh = _mesh("long")
    plain = rayaccel.build(mesh, builder).structure
    for method in METHODS:
        split = rayaccel.build(mesh, builder + "+presplit", presplit={"method": method})
        assert split.structure.sah_cost() < 0.95 * plain.sah_cost(), method


def test_deterministic_across_thread_counts():
    # More triangles than one work chunk (2048), so several threads share the kernels.
    meshes = {"median": _mesh("teapot-in-stadium"), "evh": _long_triangles(2500, seed=5)}
    before = numba.get_num_threads()
    try:
        runs = {}
        for n in (1, 2):
            numba.set_num_threads(n)
            for method, mesh in meshes.items():
                refs = presplit(mesh, PresplitOptions(method=method))
                bvh = rayaccel.build(
                    mesh, "bvh2.binned_sah+presplit", presplit={"method": method}
                ).structure
                runs[n, method] = (
                    refs.lo.tobytes(),
                    refs.hi.tobytes(),
                    refs.prim.tobytes(),
                    bvh.node_lo.tobytes(),
                    bvh.prim_index.tobytes(),
                )
        for method in meshes:
            assert runs[1, method] == runs[2, method], method
    finally:
        numba.set_num_threads(before)


def test_leaves_hold_each_triangle_once_and_all_hits_reports_it_once():
    mesh = _mesh("long")
    # Big leaves gather many pieces of one triangle; the collapse step merges more.
    accel = rayaccel.build(
        mesh,
        "bvh2.lbvh+presplit+collapse",
        max_leaf_size=16,
        presplit={"method": "evh"},
        collapse={"max_leaf_size": 32},
    )
    accel.validate()
    bvh = accel.structure
    assert bvh.n_refs > mesh.n_triangles
    assert list(accel.step_ms) == ["bvh2+presplit", "bvh2.lbvh", "bvh2+collapse"]
    rays = _rays(mesh, seed=11)
    ray, t, prim, _, _ = accel.traversal_state(
        rays.origin, rays.direction, rays.tmin, rays.tmax
    ).all_hits()
    tri = reference.tri9(mesh)
    rr = np.repeat(np.arange(rays.n_rays), mesh.n_triangles)
    ff = np.tile(np.arange(mesh.n_triangles), rays.n_rays)
    ev = reference.eval_prims(tri, rays.subset(rr), ff)
    ok = ev.prim >= 0
    order = np.lexsort((ev.prim[ok], ev.t[ok], rr[ok]))
    assert np.array_equal(ray, rr[ok][order])
    assert np.array_equal(prim, ev.prim[ok][order])
    assert t.tobytes() == ev.t[ok][order].tobytes()


def test_remove_leaf_duplicates():
    # Root with two leaves: [0, 2, 0] and [1, 2]; triangle 0 repeats in the first.
    bvh = Bvh2(
        node_lo=np.zeros((3, 3), np.float32),
        node_hi=np.ones((3, 3), np.float32),
        node_first=np.array([1, 0, 3], np.int32),
        node_count=np.array([0, 3, 2], np.int32),
        prim_index=np.array([0, 2, 0, 1, 2], np.int32),
        n_prims=3,
    )
    out = remove_leaf_duplicates(bvh)
    assert out.prim_index.tolist() == [0, 2, 1, 2]
    assert out.node_first.tolist() == [1, 0, 2]
    assert out.node_count.tolist() == [0, 2, 2]
    out.validate()
    with pytest.raises(rayaccel.StructureInvariantError, match="twice"):
        bvh.validate()
    assert remove_leaf_duplicates(out) is out


def test_bad_options_name_the_option():
    for bad, name in (
        ({"method": "sah"}, "method"),
        ({"threshold_exponent": -1}, "threshold_exponent"),
        ({"max_depth": 17}, "max_depth"),
        ({"max_depth": 1.5}, "max_depth"),
        ({"budget": -0.1}, "budget"),
        ({"budget": 5}, "budget"),
        ({"priority_base": 0.5}, "priority_base"),
        ({"priority_exponent": 0}, "priority_exponent"),
    ):
        with pytest.raises(InvalidInputError, match=name):
            PresplitOptions(**bad)
    with pytest.raises(InvalidInputError, match="budget"):
        rayaccel.build(_mesh("long"), "bvh2.lbvh+presplit", presplit={"budget": 9})


def test_a_builder_without_refs_and_bad_refs_are_refused(monkeypatch):
    from rayaccel._variant import REGISTRY

    mesh = _mesh("cornell-box")
    plain = REGISTRY["bvh2.sweep_sah"]
    fake = dataclasses.replace(
        plain, key="bvh2.norefs", func=lambda mesh, options: plain.func(mesh, options)
    )
    monkeypatch.setitem(REGISTRY, "bvh2.norefs", fake)
    assert not fake.takes_refs
    with pytest.raises(InvalidInputError, match=r"bvh2\.norefs .*bvh2\+presplit"):
        rayaccel.build(mesh, "bvh2.norefs+presplit")
    rayaccel.build(mesh, "bvh2.norefs").validate()
    with pytest.raises(InvalidInputError, match="one pre-build step"):
        rayaccel.build(mesh, "bvh2.lbvh+presplit+presplit")
    refs = triangle_refs(mesh)
    for bad in (
        refs._replace(prim=refs.prim[:-1], lo=refs.lo[:-1], hi=refs.hi[:-1]),
        refs._replace(prim=np.full_like(refs.prim, 0)),
        refs._replace(lo=refs.hi + 1),
    ):
        for builder in REF_BUILDERS:
            with pytest.raises(InvalidInputError, match=builder.replace(".", r"\.")):
                registry.get(builder).func(mesh, None, refs=bad)
    assert isinstance(refs, BuildRefs)
