"""The pairs layout of ``bvh2.stack``: rows reproduce the packed binary rows they come from.

Its traversal is checked by the registry-driven conformance suite (against the
brute-force oracle) and by the stackless tests (which must match it hit for hit).
"""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
from rayaccel.bvh.layouts.pairs import COUNT_COLUMN, REF_COLUMN, pairs_layout
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.rays.batch import RayBatch


@pytest.mark.parametrize("scene", ["teapot", "teapot-in-stadium"])
def test_pairs_rows_reproduce_the_packed_rows(scene):
    accel = rayaccel.build(rayaccel.scenes.get(scene))
    packed = packed_layout(accel.structure, accel.mesh, None)
    pairs = pairs_layout(packed)
    assert pairs.rows.ctypes.data % 64 == 0
    prefs, refs = packed.rows.view(np.int32), pairs.rows.view(np.int32)
    for c in range(2):
        for k in range(6):
            assert np.array_equal(pairs.rows[:, 2 * k + c], packed.rows[:, 6 * c + k])
        ref, count = prefs[:, 12 + c], refs[:, COUNT_COLUMN + c]
        inner = ref >= 0
        assert np.array_equal(refs[inner, REF_COLUMN + c], ref[inner])
        assert (count[inner] == 0).all()
        leaf = ~ref[~inner]
        assert np.array_equal(~refs[~inner, REF_COLUMN + c], packed.leaf_first[leaf])
        assert np.array_equal(count[~inner], packed.leaf_count[leaf])
    assert list(pairs.root_ref) == [0, 0]


def test_a_leaf_root_is_inlined_and_traced():
    """A tree that is one leaf: the root reference carries the triangle range itself."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    mesh = rayaccel.TriangleMesh(vertices, np.array([[0, 1, 2], [0, 1, 3]], np.int32))
    accel = rayaccel.build(mesh, max_leaf_size=4, traversal_cost=100.0)
    packed = packed_layout(accel.structure, mesh, None)
    assert packed.root_ref[0] < 0
    pairs = pairs_layout(packed)
    assert list(pairs.root_ref) == [-1, 2]
    rays = RayBatch([[0.2, 0.2, 1.0], [0.2, -1.0, 0.2], [5, 5, 5]],
                    [[0, 0, -1], [0, 1, 0], [0, 0, 1]])  # fmt: skip
    hits = accel.trace(rays, traversal="bvh2.stack")
    assert list(hits.prim) == [0, 1, -1]
    assert np.allclose(hits.t[:2], [1.0, 1.0])
