"""The shared top-down scheduler (``bvh/builders/topdown.py``): serial and frontier phases."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
from rayaccel.bvh.builders.topdown import SPLIT_KINDS, frontier_kernel, subtree_kernel


def _arrays(bvh):
    return (bvh.node_lo, bvh.node_hi, bvh.node_first, bvh.node_count, bvh.prim_index)


@pytest.mark.parametrize("key", ["bvh2.sbvh", "bvh2.sbvh+presplit"])
def test_frontier_gives_the_serial_tree(key):
    """SBVH's tree does not depend on where the serial phase hands over to the frontier."""
    mesh = rayaccel.scenes.get("teapot")
    serial = rayaccel.build(mesh, key, parallel_threshold=10**6).structure
    for threshold in (2, 37, 500):
        split = rayaccel.build(mesh, key, parallel_threshold=threshold).structure
        split.validate(mesh.triangles())
        for a, b in zip(_arrays(serial), _arrays(split), strict=True):
            assert np.array_equal(a, b)


def test_binned_frontier_of_many_subtrees_is_valid():
    mesh = rayaccel.scenes.get("soup")
    bvh = rayaccel.build(mesh, "bvh2.binned_sah", parallel_threshold=64).structure
    bvh.validate(mesh.triangles())
    assert bvh.n_nodes == 2 * np.count_nonzero(bvh.node_count) - 1


def test_one_signature_per_split_kind():
    mesh = rayaccel.scenes.get("cornell-box")
    for key in ("bvh2.binned_sah", "bvh2.sweep_sah", "bvh2.sbvh"):
        rayaccel.build(mesh, key, parallel_threshold=2) if key != "bvh2.sweep_sah" else (
            rayaccel.build(mesh, key)
        )
    for kind in SPLIT_KINDS:
        assert len(subtree_kernel(kind).signatures) <= 1
        assert len(frontier_kernel(kind).signatures) <= 1
