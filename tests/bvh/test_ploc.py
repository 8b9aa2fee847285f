"""PLOC: radius option, quality close to binned SAH, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
from rayaccel.bvh.builders.ploc import PlocOptions
from rayaccel.errors import InvalidInputError


def test_quality_between_lbvh_and_binned_sah():
    mesh = rayaccel.scenes.get("sphereflake")
    sah = {k: rayaccel.build(mesh, k).structure.sah_cost()
           for k in ("bvh2.lbvh", "bvh2.ploc", "bvh2.binned_sah")}
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
    mesh = rayaccel.TriangleMesh(np.eye(3).tolist() + (np.eye(3) + 5).tolist(),
                                 [[0, 1, 2], [3, 4, 5]])
    bvh = rayaccel.build(mesh, "bvh2.ploc", max_leaf_size=1).structure
    bvh.validate(mesh.triangles())
    assert bvh.n_nodes == 3
