"""Accel.refit: a deforming mesh keeps giving the oracle's hits, for every family.

A BVH is refitted (its boxes checked against a plain recomputation from the triangles,
its hits against a fresh build and the brute-force oracle for every traversal); kd-trees
and grids are rebuilt; the SAH degradation is reported and ``rebuild_if_worse``
rebuilds exactly what a fresh build would make.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.bvh.builders import refit_vertices
from rayaccel.bvh.builders.refit_vertices import refit_bvh2, sah_of
from rayaccel.errors import InvalidInputError

#: One builder per family, plus the BVH builders whose leaves hold split references.
BUILDERS = ("bvh2.binned_sah", "bvh2.sbvh", "bvh2.lbvh+presplit", "kdtree.sah", "grid.uniform")


@pytest.fixture(scope="module")
def sphere() -> rayaccel.TriangleMesh:
    return reference.icosphere(3)


def wave(mesh: rayaccel.TriangleMesh, frame: int) -> np.ndarray:
    """The mesh's vertices displaced radially by a smooth travelling wave, and drifting."""
    v = mesh.vertices.astype(np.float64)
    phase = 0.7 * frame
    bulge = 1.0 + 0.3 * np.sin(3.0 * v[:, 0] + phase) * np.cos(2.0 * v[:, 1] - phase)
    return v * bulge[:, None] + np.array([0.2 * frame, 0.0, -0.1 * frame])


def recomputed_boxes(bvh, mesh):
    """Every node's box from scratch: leaves from their triangles' corners, inner by union."""
    tri = mesh.triangles()
    lo = np.empty_like(bvh.node_lo)
    hi = np.empty_like(bvh.node_hi)
    for node in range(bvh.n_nodes - 1, -1, -1):  # children follow their parent
        first, count = bvh.node_first[node], bvh.node_count[node]
        if count:
            corners = tri[bvh.prim_index[first : first + count]].reshape(-1, 3)
            lo[node], hi[node] = corners.min(axis=0), corners.max(axis=0)
        else:
            lo[node] = np.minimum(lo[first], lo[first + 1])
            hi[node] = np.maximum(hi[first], hi[first + 1])
    return lo, hi


def structure_arrays_equal(a, b) -> bool:
    return all(
        np.array_equal(getattr(a, name), getattr(b, name))
        for name in a.__dataclass_fields__
        if isinstance(getattr(a, name), np.ndarray)
    )


@pytest.mark.parametrize("builder", BUILDERS)
def test_deforming_mesh_matches_fresh_build_and_oracle(sphere, builder):
    accel = rayaccel.build(sphere, builder)
    is_bvh = accel.structure_name == "bvh2"
    build_sah = accel.info().get("sah")
    traversals = registry.keys("traversal", accel.structure_name)
    default = registry.default_traversal(accel.structure_name)
    for frame in range(1, 4):
        verts = wave(sphere, frame)
        report = accel.refit(verts)
        # The accel holds a new mesh with the new vertices and the old faces.
        assert np.array_equal(accel.mesh.vertices, verts.astype(np.float32))
        assert accel.mesh.faces is sphere.faces or np.array_equal(accel.mesh.faces, sphere.faces)
        assert accel.info()["refit"] == report
        accel.validate()
        if is_bvh:
            assert report["method"] == "refit", report
            lo, hi = recomputed_boxes(accel.structure, accel.mesh)
            assert np.array_equal(accel.structure.node_lo, lo)
            assert np.array_equal(accel.structure.node_hi, hi)
            assert report["sah_refit"] == pytest.approx(accel.structure.sah_cost(), rel=1e-6)
            assert report["sah_build"] == pytest.approx(build_sah, rel=1e-6)
            assert report["ratio"] == report["sah_refit"] / report["sah_build"]
        else:
            assert report["method"] == "rebuild"
            assert "cannot be refitted" in report["reason"]
        fresh = rayaccel.build(accel.mesh, builder)
        if not is_bvh:
            assert structure_arrays_equal(accel.structure, fresh.structure)
        rays = reference.mixed_rays(accel.mesh, 300, seed=frame)
        ref = reference.oracle(accel.mesh, rays)
        tri = reference.tri9(accel.mesh)
        for traversal in traversals:
            label = f"{builder}/{traversal}/frame {frame}"
            hits = accel.trace(rays, traversal=traversal)
            reference.assert_closest_matches(tri, rays, hits, ref, label)
            again = fresh.trace(rays, traversal=traversal)
            assert np.array_equal(hits.t.view(np.int32), again.t.view(np.int32)), label
        any_ref = reference.oracle(accel.mesh, rays, "any")
        reference.assert_any_matches(tri, rays, accel.trace(rays, query="any"), any_ref, default)


def test_refit_reports_degradation_and_rebuilds_when_worse(sphere):
    accel = rayaccel.build(sphere, "bvh2.binned_sah", max_leaf_size=2)
    build_sah = sah_of(accel.structure)
    # The same vertices: nothing degrades.
    same = accel.refit(sphere.vertices)
    assert same["method"] == "refit"
    assert same["ratio"] == 1.0
    # Scrambled vertices: the topology no longer fits the geometry.
    rng = np.random.default_rng(1)
    scrambled = sphere.vertices[rng.permutation(sphere.n_vertices)]
    kept = accel.refit(scrambled, rebuild_if_worse=np.inf)
    assert kept["method"] == "refit"
    assert kept["ratio"] > 2.0, kept
    assert kept["sah_build"] == build_sah
    rebuilt = accel.refit(scrambled * 1.01, rebuild_if_worse=1.5)
    assert rebuilt["method"] == "rebuild"
    assert "rebuild_if_worse" in rebuilt["reason"]
    assert rebuilt["sah_refit"] > 1.5 * build_sah
    fresh = rayaccel.build(accel.mesh, "bvh2.binned_sah", max_leaf_size=2)
    assert structure_arrays_equal(accel.structure, fresh.structure)
    assert rebuilt["sah_after"] == pytest.approx(fresh.info()["sah"], rel=1e-6)
    assert rebuilt["sah_after"] < rebuilt["sah_refit"]
    # The rebuilt tree is the new reference: refitting it to the same vertices is ratio 1.
    assert accel.refit(accel.mesh.vertices)["ratio"] == 1.0
    accel.validate()


def test_refit_reuses_the_known_sah_of_the_tree_it_refits(sphere, monkeypatch):
    """After a refit or rebuild the tree's SAH is known (its ``sah_after``): the next refit
    reports it as ``sah_before`` without another pass, and it equals a fresh pass."""
    accel = rayaccel.build(sphere, "bvh2.binned_sah", max_leaf_size=2)
    passes = []
    original = rayaccel.refit.sah_cost
    monkeypatch.setattr(rayaccel.refit, "sah_cost",
                        lambda structure: passes.append(1) or original(structure))  # fmt: skip
    last = accel.refit(wave(sphere, 1))
    assert len(passes) == 1  # the built tree's cost: not known before the first refit
    for frame, ratio in ((2, None), (3, 1.0001), (4, None)):
        before = sah_of(accel.structure)
        report = accel.refit(wave(sphere, frame), rebuild_if_worse=ratio)
        assert report["sah_before"] == before == last["sah_after"]
        assert report["method"] == ("rebuild" if frame == 3 else "refit")
        last = report
    # One more pass, for the tree the rebuild made (frame 3): never for a known tree.
    assert len(passes) == 2


def test_refit_topology_is_found_once_per_tree_and_dropped_on_rebuild(sphere, monkeypatch):
    """The parent links and leaf-order corners are found on the first refit of a tree and
    kept (the topology and faces never move); a rebuild makes a new tree, so they are found
    again. Kept or found afresh, the boxes are the same."""
    accel = rayaccel.build(sphere, "bvh2.binned_sah", max_leaf_size=2)
    found = []
    original = rayaccel.refit.refit_topology
    monkeypatch.setattr(rayaccel.refit, "refit_topology",
                        lambda bvh, faces: found.append(1) or original(bvh, faces))  # fmt: skip
    for frame, ratio in ((1, None), (2, None), (3, 1.0001), (4, None)):
        report = accel.refit(wave(sphere, frame), rebuild_if_worse=ratio)
        fresh = refit_bvh2(accel.structure, accel.mesh.vertices, accel.mesh.faces)
        if report["method"] == "refit":
            assert np.array_equal(accel.structure.node_lo, fresh.node_lo)
            assert np.array_equal(accel.structure.node_hi, fresh.node_hi)
    assert report["method"] == "refit"
    # Frames 1 and 2 share one; frame 3 refits with it, then rebuilds; frame 4 finds anew.
    assert len(found) == 2
    topology = refit_vertices.refit_topology(accel.structure, accel.mesh.faces)
    info = accel.info()
    assert info["refit_bytes"] == topology.nbytes() > 0
    assert info["bytes"] == accel.structure.nbytes() + info["refit_bytes"] + sum(
        entry["bytes"] for entry in info["layouts"].values())  # fmt: skip
    assert "refit_bytes" not in rayaccel.build(sphere, "bvh2.binned_sah").info()
    assert np.array_equal(topology.corners, sphere.faces[accel.structure.prim_index])
    inner = np.flatnonzero(accel.structure.node_count == 0)
    assert topology.parent[0] == -1
    assert np.array_equal(topology.parent[accel.structure.node_first[inner]], inner)
    assert np.array_equal(topology.parent[accel.structure.node_first[inner] + 1], inner)


def test_with_vertices_shares_the_faces_and_checks_the_positions(sphere):
    moved = sphere.with_vertices(wave(sphere, 1))
    assert moved.faces is sphere.faces
    assert moved.name == sphere.name
    assert moved.vertices.dtype == np.float32
    assert not moved.vertices.flags.writeable
    assert np.array_equal(moved.vertices, wave(sphere, 1).astype(np.float32))
    with pytest.raises(InvalidInputError, match="642 vertices"):
        sphere.with_vertices(np.zeros((5, 3)))
    bad = wave(sphere, 1)
    bad[7, 1] = np.nan
    with pytest.raises(InvalidInputError, match="vertex 7"):
        sphere.with_vertices(bad)


def test_rebuild_keeps_builder_steps_and_options(sphere):
    options = {"max_leaf_size": 2, "reinsert": {"max_iterations": 2}}
    accel = rayaccel.build(sphere, "bvh2.lbvh+reinsert", **options)
    scrambled = sphere.vertices[::-1].copy()
    report = accel.refit(scrambled, rebuild_if_worse=1.0)
    assert report["method"] == "rebuild"
    fresh = rayaccel.build(accel.mesh, "bvh2.lbvh+reinsert", **options)
    assert structure_arrays_equal(accel.structure, fresh.structure)
    assert accel.step_options["reinsert"].max_iterations == 2
    assert accel.options.max_leaf_size == 2


def test_refit_drops_derived_layouts(sphere):
    accel = rayaccel.build(sphere, "bvh2.binned_sah")
    rays = reference.mixed_rays(sphere, 100)
    accel.trace(rays, traversal="bvh2.stack")
    accel.trace(rays, traversal="bvh2.wide")
    derived = [name for name in ("bvh2.packed",) if accel.derived(name) is not None]
    assert derived
    report = accel.refit(wave(sphere, 1))
    assert set(derived) <= set(report["dropped"])
    assert all(accel.derived(name) is None for name in report["dropped"])
    tri = reference.tri9(accel.mesh)
    hits = accel.trace(rays, traversal="bvh2.wide")
    reference.assert_closest_matches(tri, rays, hits, reference.oracle(accel.mesh, rays))


@pytest.mark.parametrize("parallel", [False, True])
def test_refit_is_independent_of_thread_count(sphere, monkeypatch, parallel):
    if parallel:  # the sphere's tree is small: force the parallel kernels
        monkeypatch.setattr(refit_vertices, "PARALLEL_MIN_NODES", 0)
    accel = rayaccel.build(sphere, "bvh2.sbvh")
    verts = wave(sphere, 2).astype(np.float32)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = refit_bvh2(accel.structure, verts, sphere.faces)
        one_sah = sah_of(one)
    finally:
        numba.set_num_threads(before)
    many = refit_bvh2(accel.structure, verts, sphere.faces)
    assert np.array_equal(one.node_lo, many.node_lo)
    assert np.array_equal(one.node_hi, many.node_hi)
    assert sah_of(many) == one_sah
    # Split references get their triangles' whole boxes: conservative, still valid.
    mesh = rayaccel.TriangleMesh(verts, sphere.faces)
    many.validate(mesh.triangles())
    lo, hi = recomputed_boxes(many, mesh)
    assert np.array_equal(many.node_lo, lo)
    assert np.array_equal(many.node_hi, hi)
    # Writable and read-only inputs share one compiled signature per kernel.
    refit_bvh2(accel.structure, mesh.vertices, mesh.faces.copy())
    assert len(refit_vertices._refit_kernel(parallel).signatures) == 1
    assert len(refit_vertices._sah_kernel(parallel).signatures) == 1


def test_refit_deep_chain_tree():
    bvh, mesh = reference.chain_tree(40)
    verts = mesh.vertices + np.arange(mesh.n_vertices, dtype=np.float32)[:, None] * 0.01
    refitted = refit_bvh2(bvh, verts, mesh.faces)
    moved = rayaccel.TriangleMesh(verts, mesh.faces)
    lo, hi = recomputed_boxes(refitted, moved)
    assert np.array_equal(refitted.node_lo, lo)
    assert np.array_equal(refitted.node_hi, hi)
    refitted.validate(moved.triangles())
    assert sah_of(refitted) == pytest.approx(refitted.sah_cost(), rel=1e-6)


@pytest.mark.parametrize(
    ("new_vertices", "match"),
    [
        (np.zeros((5, 3)), "vertex count"),
        (np.zeros((642, 2)), "shape"),
        ("vertices", "shape"),
        (None, "shape"),
    ],
)
def test_refit_rejects_another_shape(sphere, new_vertices, match):
    accel = rayaccel.build(sphere, "bvh2.binned_sah")
    mesh = accel.mesh
    with pytest.raises(InvalidInputError, match=f"new_vertices.*{match}"):
        accel.refit(new_vertices)
    assert accel.mesh is mesh


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e39])
def test_refit_rejects_non_finite_vertices(sphere, bad):
    accel = rayaccel.build(sphere, "kdtree.sah")
    verts = sphere.vertices.astype(np.float64)
    verts[7, 1] = bad
    with pytest.raises(InvalidInputError, match="new_vertices: vertex 7"):
        accel.refit(verts)
    assert accel.mesh is sphere
    assert accel.last_refit is None


@pytest.mark.parametrize("ratio", [0, -1.0, np.nan, "2", True, [2.0]])
def test_refit_rejects_bad_rebuild_ratio(sphere, ratio):
    accel = rayaccel.build(sphere, "bvh2.binned_sah")
    with pytest.raises(InvalidInputError, match="rebuild_if_worse"):
        accel.refit(sphere.vertices, rebuild_if_worse=ratio)
