"""Build steps: +collapse and +reinsert on every builder; chains; determinism."""

from __future__ import annotations

import numba
import numpy as np
import pytest

import rayaccel
from rayaccel import registry
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.bvh.steps.reinsert import ReinsertOptions
from rayaccel.errors import InvalidInputError

BUILDERS = [pytest.param(k, id=k) for k in registry.keys("builder", "bvh2")]


@pytest.mark.parametrize("builder", BUILDERS)
@pytest.mark.parametrize("scene", ["sphereflake", "teapot-in-stadium"])
def test_reinsert_never_raises_the_sah(builder, scene):
    mesh = rayaccel.scenes.get(scene)
    before = rayaccel.build(mesh, builder).structure
    accel = rayaccel.build(mesh, builder + "+reinsert")
    accel.validate()
    after = accel.structure
    assert after.sah_cost() <= before.sah_cost() + 1e-9
    assert after.n_refs == before.n_refs
    assert after.depth() <= MAX_DEPTH


def test_reinsert_helps_lbvh_most():
    mesh = rayaccel.scenes.get("sphereflake")
    gain = {}
    for key in ("bvh2.lbvh", "bvh2.binned_sah"):
        before = rayaccel.build(mesh, key).structure.sah_cost()
        after = rayaccel.build(mesh, key + "+reinsert").structure.sah_cost()
        gain[key] = 1 - after / before
    assert gain["bvh2.lbvh"] > gain["bvh2.binned_sah"] > 0


def test_collapse_respects_the_leaf_size_and_lowers_the_sah():
    mesh = rayaccel.scenes.get("teapot")
    fine = rayaccel.build(mesh, "bvh2.binned_sah", max_leaf_size=1).structure
    for leaf in (1, 4, 8):
        accel = rayaccel.build(mesh, "bvh2.binned_sah+collapse", max_leaf_size=1,
                               collapse={"max_leaf_size": leaf})
        accel.validate()
        bvh = accel.structure
        assert bvh.node_count.max() <= leaf
        assert bvh.sah_cost() <= fine.sah_cost() + 1e-9
        assert np.array_equal(np.sort(bvh.prim_index), np.arange(mesh.n_triangles))


def test_chains_are_deterministic_across_thread_counts():
    mesh = rayaccel.scenes.get("soup")
    before = numba.get_num_threads()
    try:
        runs = []
        for n in (1, 2):
            numba.set_num_threads(n)
            bvh = rayaccel.build(mesh, "bvh2.lbvh+reinsert+collapse").structure
            runs.append((bvh.node_lo.tobytes(), bvh.node_first.tobytes(),
                         bvh.prim_index.tobytes()))
        assert runs[0] == runs[1]
    finally:
        numba.set_num_threads(before)


def test_configurations_resolve_and_are_listed():
    keys = registry.configurations()
    assert len(keys) == 8
    for key in keys:
        registry.get_chain(key)
    assert set(keys) <= set(registry.build_keys())


def test_bad_reinsert_options_name_the_option():
    for bad, name in (({"batch_fraction": 0}, "batch_fraction"),
                      ({"max_iterations": -1}, "max_iterations"),
                      ({"patience": 0}, "patience")):
        with pytest.raises(InvalidInputError, match=name):
            ReinsertOptions(**bad)
    with pytest.raises(InvalidInputError, match="max_leaf_size"):
        rayaccel.build(rayaccel.scenes.get("cornell-box"), "bvh2.lbvh+collapse",
                       collapse={"max_leaf_size": 0})
