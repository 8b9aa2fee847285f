"""Registry-driven conformance: every builder × traversal × query × scene against the oracle.

Test ids read ``<builder>-<traversal>-<query>-<scene>``. A new registered variant is
picked up with no edit here. Rays per scene (see ``conftest._make_ray_set``): camera
rays, random rays from inside and outside the bounds, random finite intervals
(some empty), diffuse bounces and shadow rays; big file scenes are subsampled so
the brute-force oracle stays within budget.
"""

from __future__ import annotations

import numpy as np
import pytest

import reference
from conftest import FILE_SCENES, scene_params
from rayaccel import registry
from rayaccel.rays.batch import RayBatch


def _traversal_params() -> list:
    params = []
    for key in registry.build_keys():
        structure = registry.get_chain(key)[0].structure
        for traversal in registry.keys("traversal", structure):
            params.append(pytest.param(key, traversal, id=f"{key}-{traversal}"))
    return params


# Every builder and every composed configuration (builder+steps) of the registry.
BUILDERS = [pytest.param(key, id=key) for key in registry.build_keys()]
TRAVERSALS = _traversal_params()
QUERIES = [pytest.param(q, id=q) for q in ("closest", "any")]
SCENES = scene_params(marks_slow_files=False)

def _pair_scene_params(cross_on_procedural: bool) -> list:
    """``(builder, traversal, scene)`` cases: the core pairs everywhere, the other pairs
    marked ``cross`` (run with ``--full``) except, when asked, on procedural scenes.

    Traversal correctness depends on the tree only through its shape, which the
    procedural scenes already vary over every builder; the file scenes add size.
    """
    params = []
    for scene in SCENES:
        name = scene.values[0]
        for pair in TRAVERSALS:
            builder, traversal = pair.values
            core = reference.is_core_pair(builder, traversal)
            marks = list(scene.marks) + reference.file_scene_marks(builder, name, traversal)
            if not core and (name in FILE_SCENES or not cross_on_procedural):
                marks.append(pytest.mark.cross)
            params.append(
                pytest.param(builder, traversal, name, id=f"{pair.id}-{name}", marks=marks)
            )
    return params


#: The whole cross product on procedural scenes (closest and any hit against the oracle).
PAIR_SCENES_CROSS = _pair_scene_params(cross_on_procedural=True)
PAIR_SCENES = _pair_scene_params(cross_on_procedural=False)
#: Every pair, the non-core ones marked ``cross`` (for the big file scenes).
PAIRS_CORE_FIRST = [
    p if reference.is_core_pair(*p.values)
    else pytest.param(*p.values, id=p.id, marks=[pytest.mark.cross])
    for p in TRAVERSALS
]


def test_registry_is_not_empty():
    assert registry.keys("builder"), "no builder registered"
    for builder in registry.variants("builder"):
        assert registry.keys("traversal", builder.structure), (
            f"builder {builder.key} has no traversal for structure {builder.structure}"
        )


BUILDER_SCENES = [
    pytest.param(b.values[0], sc.values[0], id=f"{b.id}-{sc.id}",
                 marks=[*sc.marks,
                        *reference.file_scene_marks(b.values[0], sc.values[0])])
    for sc in SCENES
    for b in BUILDERS
]


@pytest.mark.parametrize(("builder", "scene"), BUILDER_SCENES)
def test_builder_validates(scenes_cache, builder, scene):
    accel = scenes_cache.accel(builder, scene)
    accel.validate()
    info = accel.info()
    assert info["n_prims"] == scenes_cache.mesh(scene).n_triangles
    assert info["builder"] == builder


@pytest.mark.parametrize("query", QUERIES)
@pytest.mark.parametrize(("builder", "traversal", "scene"), PAIR_SCENES_CROSS)
def test_matches_oracle(scenes_cache, builder, traversal, query, scene):
    accel = scenes_cache.accel(builder, scene)
    rays = scenes_cache.ray_set(scene)
    ref = scenes_cache.oracle(scene)
    tri = reference.tri9(accel.mesh)
    hits = accel.trace(rays, query=query, traversal=traversal)
    label = f"{builder}/{traversal}/{query}/{scene}"
    if query == "closest":
        reference.assert_closest_matches(tri, rays, hits, ref, label)
    else:
        reference.assert_any_matches(tri, rays, hits, ref, label)
        occluded = accel.occluded(rays.origin, rays.direction, rays.tmin, rays.tmax,
                                  traversal=traversal)
        assert np.array_equal(occluded, ref.prim >= 0)


@pytest.mark.parametrize(("builder", "traversal", "scene"), PAIR_SCENES)
def test_stats_variant_identical(scenes_cache, builder, traversal, scene):
    accel = scenes_cache.accel(builder, scene)
    rays = scenes_cache.ray_set(scene)
    results = {}
    for query in ("closest", "any"):
        plain = accel.trace(rays, query=query, traversal=traversal)
        assert plain.stats is None
        counted = accel.trace(rays, query=query, traversal=traversal, stats=True)
        reference.assert_hits_identical(plain, counted, f"{builder}/{traversal}/{query}")
        reference.check_counter_invariants(rays, counted)
        results[query] = counted
    if traversal == "bvh2.stack":
        reference.check_stack_counters(accel.structure, rays, results["closest"],
                                       results["any"])


def _hit_rows(scenes_cache, builder, scene):
    accel = scenes_cache.accel(builder, scene)
    rays = scenes_cache.ray_set(scene)
    ref = scenes_cache.oracle(scene)
    rows = np.flatnonzero(ref.prim >= 0)[:300]
    return accel, rays.subset(rows), ref.t[rows]


@pytest.mark.parametrize(("builder", "traversal", "scene"), PAIR_SCENES)
def test_interval_excludes_hits_just_outside(scenes_cache, builder, traversal, scene):
    """With ``tmax`` one ulp below the closest hit, that hit is not reported."""
    accel, rays, t = _hit_rows(scenes_cache, builder, scene)
    below = np.nextafter(t, np.float32(-np.inf))
    short = RayBatch(rays.origin, rays.direction, rays.tmin, below)
    ref = reference.oracle(accel.mesh, short)
    hits = accel.trace(short, traversal=traversal)
    reference.assert_closest_matches(reference.tri9(accel.mesh), short, hits, ref)
    assert np.all(hits.t[hits.hit] <= below[hits.hit])


@pytest.mark.parametrize(("builder", "traversal", "scene"), PAIR_SCENES)
def test_interval_tmin_inclusive(scenes_cache, builder, traversal, scene):
    """A hit at exactly ``tmin`` is accepted."""
    accel, rays, t = _hit_rows(scenes_cache, builder, scene)
    at_tmin = accel.intersect(rays.origin, rays.direction, t, np.inf, traversal=traversal)
    missed = np.flatnonzero(at_tmin.t != t)
    assert missed.size == 0, f"{missed.size}/{t.size} hits lost with tmin = t"


@pytest.mark.parametrize(("builder", "traversal", "scene"), PAIR_SCENES)
def test_interval_tmax_inclusive(scenes_cache, builder, traversal, scene):
    """A hit at exactly ``tmax`` is accepted, by closest-hit and any-hit queries."""
    accel, rays, t = _hit_rows(scenes_cache, builder, scene)
    o, d = rays.origin, rays.direction
    at_tmax = accel.intersect(o, d, rays.tmin, t, traversal=traversal)
    missed = np.flatnonzero(~at_tmax.hit)
    assert missed.size == 0, f"{missed.size}/{t.size} hits lost with tmax = t"
    assert np.array_equal(at_tmax.t, t)
    assert accel.occluded(o, d, t, t, traversal=traversal).all()


@pytest.mark.parametrize("traversal", registry.keys("traversal"))
def test_tmax_inclusive_single_triangle(traversal):
    """Minimal repro: half of the Cornell box's back wall (flat box), tmax = t."""
    import rayaccel

    mesh = rayaccel.TriangleMesh([[549.6, 0, 559.2], [0, 0, 559.2], [0, 548.8, 559.2]],
                                 [[0, 1, 2]])
    o = np.array([[278.0, 273.0, 20.0]], np.float32)
    d = np.array([[-0.05180857703089714, -0.4221184253692627, 0.9050590395927429]],
                 np.float32)
    ref = reference.oracle(mesh, RayBatch(o, d))
    assert ref.prim[0] == 0
    for builder in registry.keys("builder", registry.get(traversal).structure):
        accel = rayaccel.build(mesh, builder)
        assert accel.intersect(o, d, traversal=traversal).t[0] == ref.t[0]
        hits = accel.intersect(o, d, 0.0, ref.t, traversal=traversal)
        assert hits.prim[0] == 0, f"{builder}: the hit at t == tmax = {ref.t[0]} is lost"


@pytest.mark.slow
@pytest.mark.scenes
@pytest.mark.parametrize(
    ("builder", "traversal", "scene"),
    [
        pytest.param(*p.values, scene, id=f"{p.id}-{scene}",
                     marks=[*p.marks, *reference.file_scene_marks(p.values[0], scene, p.values[1])])
        for scene in ("stanford-bunny", "sponza_dabrovic", "kitchen")
        for p in PAIRS_CORE_FIRST
    ],
)
def test_matches_oracle_more_rays(scenes_cache, full, builder, traversal, scene):
    """More camera and diffuse rays on the large scenes (x10 with ``--full``)."""
    from rayaccel.rays.bounce import diffuse_rays
    from rayaccel.rays.camera import frame_bounds

    accel = scenes_cache.accel(builder, scene)
    mesh = accel.mesh
    lo, hi = mesh.bounds()
    n = (4000 if full else 400) * 200_000 // max(mesh.n_triangles, 200_000)
    camera = frame_bounds(lo, hi, width=64, height=64, direction=(0.3, -0.4, -1.0))
    primary = reference.subsample(camera.rays(), n // 2, seed=7)
    hits = accel.trace(primary, traversal=traversal)
    diffuse, _ = diffuse_rays(primary, hits, mesh.normals(), seed=8)
    rays = reference.concat(primary, diffuse)
    ref = reference.oracle(mesh, rays)
    tri = reference.tri9(mesh)
    reference.assert_closest_matches(tri, rays, accel.trace(rays, traversal=traversal), ref)
    reference.assert_any_matches(tri, rays, accel.trace(rays, query="any",
                                                        traversal=traversal), ref)
