"""The canonical BVH's boxes, released after the default queries and restored on demand.

An accel whose cache holds only the default queries' layouts drops its tree's boxes when
a refit would give them back bit for bit (:mod:`rayaccel.bvh.layouts.released_bounds`);
every use that reads them gets them back, the same bits, and the hits never change.
"""

from __future__ import annotations

import pickle
import threading

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.bvh.layouts.released_bounds import boxes_are_unions
from rayaccel.rays.batch import RayBatch


@pytest.fixture(scope="module")
def mesh() -> rayaccel.TriangleMesh:
    return rayaccel.scenes.get("teapot")


@pytest.fixture(scope="module")
def rays(mesh: rayaccel.TriangleMesh) -> RayBatch:
    lo, hi = mesh.bounds()
    return reference.concat(
        reference.rays_outside(lo, hi, 300, seed=11), reference.rays_inside(lo, hi, 300, seed=12)
    )


@pytest.fixture(scope="module")
def oracle(mesh: rayaccel.TriangleMesh, rays: RayBatch) -> rayaccel.HitBatch:
    return reference.oracle(mesh, rays)


def _released(mesh: rayaccel.TriangleMesh, rays: RayBatch, key: str = "bvh2.binned_sah"):
    """Return ``(accel after its default queries, its tree's boxes, default hits)``.

    The boxes come from a second build (builds are deterministic): reading the accel's
    own tree before its default queries would keep its boxes.
    """
    twin = rayaccel.build(mesh, key).structure
    boxes = (twin.node_lo, twin.node_hi)
    accel = rayaccel.build(mesh, key)
    # Named with its default options, a default query's traversal reads no boxes either:
    # this query already releases them.
    accel.trace(rays, query="any", traversal="bvh2.wide")
    closest = accel.trace(rays)
    return accel, boxes, closest


@pytest.mark.parametrize("key", ["bvh2.binned_sah", "bvh2.lbvh", "bvh2.ploc+reinsert"])
def test_default_queries_release_the_boxes_and_every_later_use_gets_the_same_ones(
    mesh, rays, oracle, key
):
    accel, (lo, hi), closest = _released(mesh, rays, key)
    info = accel.info()
    assert info["boxes_released"]
    n_nodes = info["n_nodes"]
    layouts = sum(entry["bytes"] for entry in info["layouts"].values())
    assert info["bytes"] == layouts + 8 * n_nodes + 4 * info["n_refs"]
    # info() reports the tree's figures without keeping the boxes it recomputes for them.
    assert accel.info()["boxes_released"]
    # Default queries keep answering from the derived layouts alone.
    reference.assert_hits_identical(accel.trace(rays), closest, key)
    reference.assert_closest_matches(reference.tri9(mesh), rays, closest, oracle, key)
    # Another traversal reads the boxes: restored, bit for bit, and kept from then on.
    stack = accel.trace(rays, traversal="bvh2.stack")
    assert not accel.info()["boxes_released"]
    assert np.array_equal(accel.structure.node_lo, lo)
    assert np.array_equal(accel.structure.node_hi, hi)
    reference.assert_closest_matches(reference.tri9(mesh), rays, stack, oracle, key)
    accel.structure.validate(mesh.triangles())
    accel.trace(rays)
    assert not accel.info()["boxes_released"]


def test_each_use_that_reads_the_boxes_restores_them(mesh, rays, oracle, tmp_path):
    lo = rayaccel.build(mesh).structure.node_lo
    uses = {
        "count_intersections": lambda a: a.count_intersections(rays.origin, rays.direction),
        "closest points": lambda a: a.compute_closest_points(mesh.vertices[:20] * 1.1),
        "save": lambda a: a.save(tmp_path / "teapot.npz"),
        "refit": lambda a: a.refit(mesh.vertices),
        "validate": lambda a: a.validate(),
        "structure": lambda a: a.structure,
        "named traversal": lambda a: a.trace(rays, traversal="bvh2.wide", width=4),
    }
    for name, use in uses.items():
        accel, _, closest = _released(mesh, rays)
        assert accel.info()["boxes_released"], name
        use(accel)
        assert not accel.info()["boxes_released"], name
        assert np.array_equal(accel.structure.node_lo, lo), name
        reference.assert_hits_identical(accel.trace(rays), closest, name)
    loaded = rayaccel.load_accel(tmp_path / "teapot.npz")
    assert np.array_equal(loaded.structure.node_lo, lo)


def test_a_pickled_released_accel_carries_its_boxes(mesh, rays):
    accel, (lo, hi), closest = _released(mesh, rays)
    clone = pickle.loads(pickle.dumps(accel))
    assert not accel.info()["boxes_released"]  # pickling reads them
    reference.assert_hits_identical(clone.trace(rays), closest, "clone")
    assert clone.info()["boxes_released"]  # the copy's own default queries release them
    assert np.array_equal(clone.structure.node_lo, lo)
    assert np.array_equal(clone.structure.node_hi, hi)


def test_boxes_tighter_or_wider_than_their_triangles_are_kept(mesh, rays, oracle):
    """SBVH's clipped boxes and a float64 mesh's widened ones would not come back as they
    were; the check also catches a single changed box."""
    for key in ("bvh2.sbvh", "bvh2.binned_sah+presplit"):
        accel, (lo, _), closest = _released(mesh, rays, key)
        assert accel.info()["n_refs"] > mesh.n_triangles, key  # split references
        assert not accel.info()["boxes_released"], key
        assert np.array_equal(accel.structure.node_lo, lo)
        reference.assert_closest_matches(reference.tri9(mesh), rays, closest, oracle, key)
    mesh64 = rayaccel.TriangleMesh(mesh.vertices, mesh.faces, precision="float64")
    accel64 = rayaccel.build(mesh64)
    accel64.trace(rays)
    assert not accel64.info()["boxes_released"]

    tree = rayaccel.build(mesh).structure
    assert boxes_are_unions(tree, mesh.vertices, mesh.faces)
    leaf = int(np.flatnonzero(tree.node_count)[3])
    inner = int(np.flatnonzero(tree.node_count == 0)[-1])
    for node, array in ((leaf, tree.node_hi), (inner, tree.node_lo), (0, tree.node_hi)):
        saved = array[node].copy()
        array[node, 1] = np.nextafter(array[node, 1], np.float32(-np.inf if array is tree.node_lo
                                                                 else np.inf))  # fmt: skip
        assert not boxes_are_unions(tree, mesh.vertices, mesh.faces), node
        array[node] = saved
    assert boxes_are_unions(tree, mesh.vertices, mesh.faces)


def test_an_accel_whose_tree_was_read_keeps_its_boxes(mesh, rays):
    """Whoever read ``accel.structure`` may still derive layouts from its boxes."""
    for read in (
        lambda a: a.trace(rays, traversal="bvh2.stack"),
        lambda a: a.structure,
        lambda a: a.count_intersections(rays.origin[:4], rays.direction[:4]),
    ):
        accel = rayaccel.build(mesh)
        read(accel)
        accel.trace(rays)
        assert not accel.info()["boxes_released"]


def test_threads_mixing_default_and_other_queries_agree(mesh, rays, oracle):
    """Releases and restores under concurrent queries never hand a traversal a tree
    without boxes it needs."""
    expected = {}
    for traversal in (None, "bvh2.stack", "bvh2.bitstack"):
        expected[traversal] = rayaccel.build(mesh).trace(rays, traversal=traversal)
    for _ in range(3):
        accel = rayaccel.build(mesh)
        errors: list[str] = []

        def run(traversal: str | None, accel=accel, errors=errors) -> None:
            for _ in range(4):
                hits = accel.trace(rays, traversal=traversal)
                if hits.t.tobytes() != expected[traversal].t.tobytes():
                    errors.append(str(traversal))

        workers = [threading.Thread(target=run, args=(t,)) for t in (None, None, "bvh2.stack",
                                                                      "bvh2.bitstack")]  # fmt: skip
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        assert not errors


def test_a_default_traversal_named_without_options_releases_the_boxes(mesh, rays):
    accel = rayaccel.build(mesh)
    accel.trace(rays, query="any", traversal="bvh2.packet")
    accel.trace(rays, traversal="bvh2.wide")
    assert accel.info()["boxes_released"]
    # With an option it is another traversal: a reader of the tree.
    other = rayaccel.build(mesh)
    other.trace(rays, traversal="bvh2.wide", width=4)
    other.trace(rays)
    assert not other.info()["boxes_released"]
