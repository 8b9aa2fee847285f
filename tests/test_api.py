"""The public facade: ``rayaccel.build``, ``Accel`` queries, ``info``, registry lookups."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import config, registry
from rayaccel.counters import COUNTER_NAMES
from rayaccel.errors import InvalidInputError, StructureInvariantError, UnknownVariantError
from rayaccel.queries import QUERY_KINDS, query_constant
from rayaccel.rays.batch import HitBatch, RayBatch


@pytest.fixture(scope="module")
def teapot():
    return rayaccel.build(rayaccel.scenes.get("teapot"), "bvh2.binned_sah")


@pytest.fixture(scope="module")
def rays(teapot):
    lo, hi = teapot.mesh.bounds()
    return reference.rays_outside(lo, hi, 700, seed=3)


def test_public_names():
    for name in ("build", "Accel", "TriangleMesh", "RayBatch", "HitBatch", "scenes",
                 "registry", "load_mesh", "InvalidInputError", "UnknownVariantError",
                 "TraversalOverflowError", "StructureInvariantError", "Counter",
                 "COUNTER_NAMES"):
        assert hasattr(rayaccel, name), name
    assert set(rayaccel.__all__) <= set(dir(rayaccel))


def test_default_build_and_repr(teapot):
    accel = rayaccel.build(teapot.mesh)
    assert accel.key == "bvh2.binned_sah"
    assert accel.structure_name == "bvh2"
    assert "bvh2.binned_sah" in repr(accel)
    assert accel.build_ms >= 0


def test_intersect_result_types(teapot, rays):
    hits = teapot.intersect(rays.origin, rays.direction)
    assert isinstance(hits, HitBatch)
    assert len(hits) == rays.n_rays
    assert hits.t.dtype == np.float32
    assert hits.prim.dtype == np.int32
    assert hits.u.dtype == np.float32
    assert hits.v.dtype == np.float32
    assert hits.stats is None
    assert np.array_equal(hits.hit, hits.prim >= 0)
    assert 0 < hits.hit.sum() < rays.n_rays


def test_barycentrics_and_points(teapot, rays):
    hits = teapot.trace(rays)
    hit = hits.hit
    tri = teapot.mesh.triangles()[hits.prim[hit]].astype(np.float64)
    u, v = hits.u[hit, None], hits.v[hit, None]
    on_tri = (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
    points = hits.points(rays)
    assert np.allclose(points[hit], on_tri, atol=1e-4)
    assert np.isnan(points[~hit]).all()
    assert (hits.u[hit] >= 0).all()
    assert (hits.v[hit] >= 0).all()
    assert (hits.u[hit] + hits.v[hit] <= 1 + 1e-6).all()


def test_occluded_equals_closest_hit_mask(teapot, rays):
    hits = teapot.intersect(rays.origin, rays.direction)
    occluded = teapot.occluded(rays.origin, rays.direction)
    assert occluded.dtype == np.bool_
    assert np.array_equal(occluded, hits.hit)
    # Finite intervals: shadow-ray style queries stop before the closest hit.
    tmax = np.where(hits.hit, hits.t * 0.5, 1.0)
    assert not teapot.occluded(rays.origin, rays.direction, 0.0, tmax)[hits.hit].any()


def test_trace_equals_intersect(teapot, rays):
    a = teapot.trace(rays)
    b = teapot.intersect(rays.origin, rays.direction, rays.tmin, rays.tmax,
                         traversal="bvh2.stack")
    reference.assert_hits_identical(a, b)


def test_stats_dict(teapot, rays):
    hits = teapot.intersect(rays.origin, rays.direction, stats=True)
    assert tuple(hits.stats) == COUNTER_NAMES
    reference.check_counter_invariants(rays, hits)
    # Primary rays are row-major, so a counter reshapes into a heatmap.
    camera = rayaccel.rays.frame_bounds(*teapot.mesh.bounds(), width=32, height=16)
    image = teapot.trace(camera.rays(), stats=True).stats["nodes"].reshape(16, 32)
    assert image.max() > 0


def test_single_triangle_counters():
    mesh = rayaccel.TriangleMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    accel = rayaccel.build(mesh)
    hits = accel.intersect([[0.2, 0.2, 1.0], [5, 5, 1]], (0, 0, -1), stats=True)
    assert list(hits.prim) == [0, -1]
    s = hits.stats
    assert s["nodes"][0] == 1
    assert s["prim_tests"][0] == 1
    assert s["box_tests"][0] == 1
    assert s["nodes"][1] == 0
    assert s["prim_tests"][1] == 0
    assert s["box_tests"][1] == 1


def test_empty_ray_batch(teapot):
    hits = teapot.intersect(np.zeros((0, 3)), np.zeros((0, 3)))
    assert len(hits) == 0
    assert hits.t.dtype == np.float32
    assert teapot.occluded(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_empty_ray_batch_with_stats(teapot):
    hits = teapot.intersect(np.zeros((0, 3)), np.zeros((0, 3)), stats=True)
    assert hits.stats is not None
    assert tuple(hits.stats) == COUNTER_NAMES


def test_per_ray_intervals(teapot, rays):
    hits = teapot.trace(rays)
    t = np.where(hits.hit, hits.t, 1.0)
    tmin = np.where(np.arange(rays.n_rays) % 2 == 0, 0.0, t * 1.001)
    again = teapot.intersect(rays.origin, rays.direction, tmin, np.inf)
    even = np.arange(rays.n_rays) % 2 == 0
    assert np.array_equal(again.t[even], hits.t[even])
    assert (again.t[~even & hits.hit] > hits.t[~even & hits.hit]).all()


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_ray_arrays_are_writable_copies_of_read_only_input(precision):
    """A single broadcast row or a read-only array is copied: read-only is part of a
    kernel's argument types, and both kinds would compile every traversal twice."""
    one = RayBatch([[0.0, 0, -1]], np.array([0.0, 0, 1]), precision=precision)
    frozen = np.zeros((4, 3), dtype=precision)
    frozen.flags.writeable = False
    tmax = np.full(4, 5.0, dtype=precision)
    tmax.flags.writeable = False
    many = RayBatch(frozen, np.ones((4, 3)), 0.0, tmax, precision=precision)
    for batch in (one, many):
        for array in (batch.origin, batch.direction, batch.tmin, batch.tmax):
            assert array.flags.writeable
            assert array.flags.c_contiguous


def test_info(teapot):
    info = teapot.info()
    for key in ("builder", "structure", "build_ms", "n_prims", "n_nodes", "n_leaves",
                "n_refs", "depth", "sah", "mean_leaf_size", "bytes", "options"):
        assert key in info, key
    assert info["n_prims"] == teapot.mesh.n_triangles == info["n_refs"]
    assert info["options"]["max_leaf_size"] == 8
    assert info["sah"] > 0
    assert info["depth"] == teapot.structure.depth()


def test_derived_layout_is_cached_and_counted():
    accel = rayaccel.build(rayaccel.scenes.get("teapot"), "bvh2.sweep_sah")
    before = accel.info()["bytes"]
    assert before == accel.structure.nbytes()
    assert accel.info()["layouts"] == {}
    assert accel.derived("bvh2.packed") is None
    accel.intersect([[0, 0, 10]], (0, 0, -1), traversal="bvh2.stack")
    # bvh2.stack traces the pairs rows, derived from the packed layout (both kept).
    packed = accel.derived("bvh2.packed")
    pairs = accel.derived("bvh2.pairs")
    assert packed is not None
    assert pairs is not None
    assert accel.info()["bytes"] == before + packed.nbytes() + pairs.nbytes()
    accel.intersect([[0, 0, 10]], (0, 0, -1), traversal="bvh2.stack")
    assert accel.derived("bvh2.packed") is packed
    assert accel.derived("bvh2.pairs") is pairs
    # A query naming no traversal uses the fastest, bvh2.wide: its 8-wide layout is built
    # once, and info() reports its bytes and build time.
    accel.intersect([[0, 0, 10]], (0, 0, -1))
    wide = accel.derived("bvh2.wide8")
    assert wide is not None
    layouts = accel.info()["layouts"]
    assert set(layouts) == {"bvh2.packed", "bvh2.pairs", "bvh2.wide8"}
    assert layouts["bvh2.wide8"]["bytes"] == wide.nbytes()
    assert all(entry["build_ms"] > 0 for entry in layouts.values())
    assert accel.info()["bytes"] == before + sum(entry["bytes"] for entry in layouts.values())
    accel.occluded([[0, 0, 10]], (0, 0, -1))
    assert accel.derived("bvh2.wide8") is wide


def test_queries_naming_no_traversal_use_the_fastest(teapot, rays):
    """intersect/occluded/trace without a traversal run registry.query_traversal (bvh2.wide
    for BVHs): the same hits as the reference traversal, bvh2.stack."""
    assert registry.query_traversal("bvh2") == "bvh2.wide"
    assert registry.query_traversal("kdtree") == registry.default_traversal("kdtree")
    assert registry.query_traversal("grid") == registry.default_traversal("grid")
    fastest = teapot.trace(rays, stats=True)
    reference_hits = teapot.trace(rays, traversal="bvh2.stack")
    wide = teapot.trace(rays, traversal="bvh2.wide", stats=True)
    assert np.array_equal(fastest.prim, reference_hits.prim)
    assert np.array_equal(fastest.t, reference_hits.t)
    # The counters are the wide walk's (8-wide nodes), not the binary one's.
    assert fastest.stats.keys() == wide.stats.keys()
    for name, counts in wide.stats.items():
        assert np.array_equal(fastest.stats[name], counts), name


def test_builder_options_round_trip():
    mesh = rayaccel.scenes.get("teapot")
    accel = rayaccel.build(mesh, "bvh2.binned_sah", max_leaf_size=2, n_bins=8)
    assert accel.options.max_leaf_size == 2
    assert accel.options.n_bins == 8
    assert accel.structure.node_count.max() <= 2
    assert accel.info()["options"]["n_bins"] == 8


def test_validate_passes_and_debug_build_validates(monkeypatch, teapot):
    teapot.validate()
    calls = []
    original = rayaccel.Accel.validate
    monkeypatch.setattr(config, "DEBUG", True)
    monkeypatch.setattr(rayaccel.Accel, "validate",
                        lambda self: calls.append(self.key) or original(self))
    rayaccel.build(teapot.mesh, "bvh2.sweep_sah")
    assert calls == ["bvh2.sweep_sah"]


def test_validate_reports_broken_structure(teapot):
    broken = dataclasses.replace(teapot.structure, node_hi=teapot.structure.node_lo - 1)
    accel = rayaccel.Accel("bvh2.binned_sah", teapot.mesh, broken, teapot.options, 0.0)
    with pytest.raises(StructureInvariantError):
        accel.validate()


def test_registry_enumeration():
    builders = registry.keys("builder")
    assert {"bvh2.binned_sah", "bvh2.sweep_sah"} <= set(builders)
    assert "bvh2.stack" in registry.keys("traversal")
    assert builders == sorted(builders)
    for v in registry.variants():
        separator = "+" if v.role == "step" else "."
        assert v.key.startswith(v.structure + separator)
        assert v.role in ("builder", "traversal", "step")
        assert v.backend in ("cpu", "cuda")
        assert v.summary
        assert callable(v.func)
        assert dataclasses.is_dataclass(v.options)
        v.make_options()  # defaults are valid
        assert registry.get(v.key) is v
        assert registry.get(v.key, v.role) is v
    assert registry.keys("builder", "no-such-structure") == []
    assert [v.key for v in registry.variants("traversal", "bvh2")] == \
        registry.keys("traversal", "bvh2")


def test_defaults_come_from_the_registry():
    assert registry.default_traversal("bvh2") == "bvh2.stack"
    assert registry.query_traversal("bvh2") == "bvh2.wide"
    assert registry.default_builder("bvh2") == "bvh2.binned_sah"
    with pytest.raises(InvalidInputError, match="no default traversal"):
        registry.default_traversal("no-such-structure")


def test_every_structure_has_one_default_builder_and_traversal():
    for structure in registry.structures():
        defaults = {
            role: [v.key for v in registry.variants(role, structure) if v.default]
            for role in ("builder", "traversal")
        }
        assert all(len(keys) == 1 for keys in defaults.values()), (structure, defaults)
    assert registry.get(registry.DEFAULT_BUILD_KEY, "builder").default


def test_pausable_traversal_from_the_registry():
    key, start = registry.pausable("bvh2")
    assert registry.get(key, "traversal").structure == "bvh2"
    assert start.__module__ == registry.get(key).func.__module__
    with pytest.raises(InvalidInputError, match="can pause"):
        registry.pausable("no-such-structure")


def test_traversal_of_another_structure_rejected(monkeypatch, teapot):
    from rayaccel._variant import REGISTRY, Variant

    @dataclasses.dataclass(frozen=True)
    class NoOptions:
        pass

    fake = Variant("grid.fake", "traversal", "grid", lambda *a, **k: None, NoOptions, "fake")
    monkeypatch.setitem(REGISTRY, "grid.fake", fake)
    with pytest.raises(InvalidInputError, match="walks 'grid'"):
        teapot.intersect([[0, 0, 10]], (0, 0, -1), traversal="grid.fake")


def test_ray_batch_helpers(rays):
    sub = rays.subset(slice(0, 10))
    assert sub.n_rays == len(sub) == 10
    mask = np.zeros(rays.n_rays, bool)
    mask[[1, 5]] = True
    assert rays.subset(mask).n_rays == 2
    assert rays.valid().all()
    empty = HitBatch.empty(4)
    assert (empty.prim == -1).all()
    assert np.isposinf(empty.t).all()


def test_query_kinds_constant():
    assert QUERY_KINDS == ("closest", "any")
    with pytest.raises(InvalidInputError, match="query"):
        query_constant("nearest")


def test_trace_rejects_batch_subclass_lookalike(teapot):
    class Fake:
        n_rays = 1

    with pytest.raises(InvalidInputError):
        teapot.trace(Fake())
    assert isinstance(RayBatch(np.zeros((1, 3)), np.ones((1, 3))), RayBatch)


# --------------------------------------------------------------------------- build steps


@dataclasses.dataclass(frozen=True)
class _CountOptions:
    scale: int = 1


def _count_step(bvh, mesh, options):
    _STEP_CALLS.append((bvh.n_nodes, mesh.n_triangles, options.scale))
    return bvh


_STEP_CALLS: list = []


@pytest.fixture
def count_step(monkeypatch):
    from rayaccel._variant import REGISTRY, Variant

    _STEP_CALLS.clear()
    monkeypatch.setitem(REGISTRY, "bvh2+count", Variant(
        "bvh2+count", "step", "bvh2", _count_step, _CountOptions, "test step"))
    return _STEP_CALLS


def test_build_chains_steps_with_their_options(count_step):
    mesh = rayaccel.scenes.get("cornell-box")
    accel = rayaccel.build(mesh, "bvh2.binned_sah+count+count", max_leaf_size=2,
                           count={"scale": 3})
    assert [c[2] for c in count_step] == [3, 3]
    assert count_step[0][1] == mesh.n_triangles
    assert accel.options.max_leaf_size == 2
    info = accel.info()
    assert info["builder"] == "bvh2.binned_sah+count+count"
    assert list(info["step_ms"]) == ["bvh2.binned_sah", "bvh2+count"]
    accel.validate()
    assert accel.intersect([[278, 273, -800]], [[0, 0, 1]]).hit[0]


def test_build_chain_errors_name_the_problem(count_step):
    mesh = rayaccel.scenes.get("cornell-box")
    with pytest.raises(UnknownVariantError, match="did you mean count"):
        rayaccel.build(mesh, "bvh2.binned_sah+cuont")
    with pytest.raises(UnknownVariantError, match="unknown option 'scal'"):
        rayaccel.build(mesh, "bvh2.binned_sah+count", count={"scal": 2})
    with pytest.raises(InvalidInputError, match="step options are a dict"):
        rayaccel.build(mesh, "bvh2.binned_sah+count", count=2)
    with pytest.raises(UnknownVariantError):
        rayaccel.build(mesh, "bvh2.binned_sah", count={"scale": 2})
