"""PLOC: radius option, quality close to binned SAH, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.bvh.builders.ploc import PlocOptions
from rayaccel.errors import InvalidInputError


def test_quality_between_lbvh_and_binned_sah():
    mesh = rayaccel.scenes.get("sphereflake")
    sah = {
        k: rayaccel.build(mesh, k).structure.sah_cost()
        for k in ("bvh2.lbvh", "bvh2.ploc", "bvh2.binned_sah")
    }
    assert sah["bvh2.ploc"] < sah["bvh2.lbvh"]
    assert sah["bvh2.ploc"] < 1.2 * sah["bvh2.binned_sah"]


def test_larger_radius_is_not_worse_on_average():
    mesh = rayaccel.scenes.get("teapot")
    small = rayaccel.build(mesh, "bvh2.ploc", radius=1).structure.sah_cost()
    large = rayaccel.build(mesh, "bvh2.ploc", radius=25).structure.sah_cost()
    assert large <= small * 1.02


@pytest.mark.parametrize("radius", [1, 2, 25, 256])
def test_every_radius_builds_a_valid_tree(radius):
    mesh = rayaccel.scenes.get("cornell-box")
    accel = rayaccel.build(mesh, "bvh2.ploc", radius=radius)
    accel.validate()


def test_bad_radius():
    for radius in (0, 257):
        with pytest.raises(InvalidInputError, match="radius"):
            PlocOptions(radius=radius)
    with pytest.raises(InvalidInputError, match="morton_bits"):
        PlocOptions(morton_bits=10)


def test_two_triangles():
    mesh = rayaccel.TriangleMesh(
        np.eye(3).tolist() + (np.eye(3) + 5).tolist(), [[0, 1, 2], [3, 4, 5]]
    )
    bvh = rayaccel.build(mesh, "bvh2.ploc", max_leaf_size=1).structure
    bvh.validate(mesh.triangles())
    assert bvh.n_nodes == 3


def _fan(n: int) -> rayaccel.TriangleMesh:
    """``n`` coplanar triangles around one shared vertex (a disc)."""
    angle = np.linspace(0.0, 2.0 * np.pi, n + 1)
    vertices = np.zeros((n + 2, 3))
    vertices[1:, 0] = np.cos(angle)
    vertices[1:, 1] = np.sin(angle)
    ring = np.arange(1, n + 1)
    faces = np.stack([np.zeros(n, dtype=np.int64), ring, ring + 1], axis=1)
    return rayaccel.TriangleMesh(vertices, faces)


def test_a_fan_of_coplanar_triangles_clusters_in_logarithmic_depth():
    """A fan made PLOC merge one pair per iteration: a chain n deep, O(n²·r) time (issue 20)."""
    mesh = _fan(6000)
    accel = rayaccel.build(mesh, "bvh2.ploc", max_leaf_size=1)
    accel.validate()
    assert accel.info()["depth"] <= 64  # was 6000 - 1 before the Morton pairing fallback
    rng = np.random.default_rng(3)
    origins = np.column_stack([rng.uniform(-1.2, 1.2, (500, 2)), np.full(500, 1.0)])
    rays = rayaccel.RayBatch(origins, np.tile([0.0, 0.0, -1.0], (500, 1)))
    reference.assert_closest_matches(
        reference.tri9(mesh), rays, accel.trace(rays), reference.oracle(mesh, rays), "ploc fan"
    )
