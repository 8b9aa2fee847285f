"""Stackless traversals: exactly the hits of ``bvh2.stack``, options, counters, pause/resume.

The registry-driven conformance suite already checks every traversal against the
brute-force oracle on every scene; here each stackless traversal is compared with
``bvh2.stack`` itself, bit for bit, on small procedural inputs chosen for the edge
cases of stackless traversal (shrinking intervals, zero direction components,
origins inside boxes, deep degenerate trees), with every option.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import rayaccel
import reference
from rayaccel import registry
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.bvh.layouts.perfect_hash import build_perfect_hash
from rayaccel.errors import InvalidInputError, UnknownVariantError
from rayaccel.rays.batch import RayBatch

#: Ordered stackless traversals (and option sets): bit-identical to bvh2.stack.
ORDERED = [
    ("bvh2.restart_trail", {}),
    ("bvh2.restart_trail", {"short_stack": 1}),
    ("bvh2.restart_trail", {"short_stack": 3}),
    ("bvh2.restart_trail", {"short_stack": 64}),
    ("bvh2.parent_link", {}),
    ("bvh2.bitstack", {}),
    ("bvh2.perfect_hash", {}),
    ("bvh2.perfect_hash", {"hash": False}),
    ("bvh2.perfect_hash", {"uncle_refs": False}),
    ("bvh2.perfect_hash", {"register": False}),
    ("bvh2.perfect_hash", {"level_mask": False}),
    (
        "bvh2.perfect_hash",
        {"hash": False, "uncle_refs": False, "register": False, "level_mask": False},
    ),
]
ORDERED_PARAMS = [
    pytest.param(key, opts, id=key + "".join(f"-{k}={v}" for k, v in opts.items()))
    for key, opts in ORDERED
]
#: Traversals that enter exactly the nodes bvh2.stack enters.
SAME_NODES = [
    ("bvh2.parent_link", {}),
    ("bvh2.bitstack", {}),
    ("bvh2.perfect_hash", {}),
    ("bvh2.restart_trail", {"short_stack": 64}),
]
BUILDERS = registry.keys("builder", "bvh2")
SCENES = ("teapot", "soup", "cornell-box")


@pytest.fixture(scope="module")
def cases():
    """(accel, rays, closest, any) per builder × scene, with bvh2.stack's results."""
    out = {}
    for builder in BUILDERS:
        for scene in SCENES:
            mesh = rayaccel.scenes.get(scene)
            accel = rayaccel.build(mesh, builder)
            rays = reference.mixed_rays(mesh)
            closest = accel.trace(rays, traversal="bvh2.stack", stats=True)
            any_hit = accel.trace(rays, query="any", traversal="bvh2.stack", stats=True)
            out[builder, scene] = (accel, rays, closest, any_hit)
    return out


@pytest.mark.parametrize(("traversal", "options"), ORDERED_PARAMS)
def test_ordered_identical_to_stack(cases, traversal, options):
    for (builder, scene), (accel, rays, closest, any_hit) in cases.items():
        label = f"{builder}/{scene}/{traversal}{options}"
        hits = accel.trace(rays, traversal=traversal, stats=True, **options)
        reference.assert_hits_identical(closest, hits, label)
        hits_any = accel.trace(rays, query="any", traversal=traversal, stats=True, **options)
        reference.assert_hits_identical(any_hit, hits_any, label + "/any")
        if (traversal, options) in SAME_NODES:
            for h, ref in ((hits, closest), (hits_any, any_hit)):
                assert np.array_equal(h.stats["nodes"], ref.stats["nodes"]), label
                assert np.array_equal(h.stats["prim_tests"], ref.stats["prim_tests"]), label
        else:
            assert (hits.stats["nodes"] >= closest.stats["nodes"]).all(), label


def test_skip_same_t_same_prim_except_exact_ties(cases):
    for (builder, scene), (accel, rays, closest, any_hit) in cases.items():
        label = f"{builder}/{scene}"
        hits = accel.trace(rays, traversal="bvh2.skip", stats=True)
        assert hits.t.tobytes() == closest.t.tobytes(), label
        ties = np.flatnonzero(hits.prim != closest.prim)
        again = reference.eval_prims(reference.tri9(accel.mesh), rays.subset(ties), hits.prim[ties])
        assert again.t.tobytes() == closest.t[ties].tobytes(), label
        assert (hits.stats["nodes"] >= 1).sum() >= (closest.stats["nodes"] >= 1).sum()
        assert hits.stats["nodes"].sum() >= closest.stats["nodes"].sum(), label
        occluded = accel.occluded(
            rays.origin, rays.direction, rays.tmin, rays.tmax, traversal="bvh2.skip"
        )
        assert np.array_equal(occluded, any_hit.prim >= 0), label


def test_counters(cases):
    accel, rays, closest, _ = cases[BUILDERS[0], "soup"]
    stack_nodes = closest.stats["nodes"].sum()
    pure = accel.trace(rays, traversal="bvh2.restart_trail", stats=True).stats
    short = accel.trace(rays, traversal="bvh2.restart_trail", stats=True, short_stack=3).stats
    deep = accel.trace(rays, traversal="bvh2.restart_trail", stats=True, short_stack=64).stats
    assert pure["restarts"].sum() > short["restarts"].sum() > 0
    assert deep["restarts"].sum() == 0
    assert pure["nodes"].sum() > short["nodes"].sum() > stack_nodes
    assert (pure["stack_peak"] == 0).all()
    assert (short["stack_peak"] <= 3).all()
    ph = accel.trace(rays, traversal="bvh2.perfect_hash", stats=True).stats
    hist = sum(ph[f"backtrack_{k}"] for k in ("sibling", "uncle", "grand_uncle", "further"))
    assert np.array_equal(hist, ph["backtracks"])
    assert (ph["hash_lookups"] <= ph["backtrack_further"]).all()
    no_reg = accel.trace(rays, traversal="bvh2.perfect_hash", stats=True, register=False).stats
    no_unc = accel.trace(rays, traversal="bvh2.perfect_hash", stats=True, uncle_refs=False).stats
    assert no_reg["hash_lookups"].sum() >= ph["hash_lookups"].sum()
    assert no_unc["hash_lookups"].sum() > ph["hash_lookups"].sum()
    no_hash = accel.trace(rays, traversal="bvh2.perfect_hash", stats=True, hash=False).stats
    assert no_hash["hash_lookups"].sum() == 0
    for name in ("restarts", "backtracks", "hash_lookups", "backtrack_sibling"):
        assert (closest.stats[name] == 0).all(), name


def test_derived_layouts_counted_in_info_bytes():
    accel = rayaccel.build(rayaccel.scenes.get("teapot"))
    o = np.zeros((1, 3))
    d = np.array([[0.0, 0.0, 1.0]])
    accel.intersect(o, d)
    tree = accel.structure  # with its boxes (released after the default query)
    before = accel.info()["bytes"]
    packed = accel.derived("bvh2.packed")
    assert not packed.has_rows  # the default queries do not make the packed rows
    tables = 4 * (tree.n_nodes + 2 * tree.n_leaves)  # node numbers, leaf firsts and counts
    for key, name in (
        ("bvh2.skip", "bvh2.skip"),
        ("bvh2.parent_link", "bvh2.links"),
        ("bvh2.perfect_hash", "bvh2.keyed"),
    ):
        had_rows = packed.has_rows
        packed_before = packed.nbytes()
        accel.intersect(o, d, traversal=key)
        layout = accel.derived(name)
        assert layout is not None
        assert layout.nbytes() > 0
        # The first traversal over the packed rows makes them, the first that needs the
        # leaf tables makes those, and each counts once.
        made = packed.nbytes() - packed_before
        rows_made = packed.rows.nbytes if packed.has_rows and not had_rows else 0
        assert made in (rows_made, rows_made + tables), key
        after = accel.info()["bytes"]
        assert after == before + layout.nbytes() + made, key
        before = after
    assert packed.has_rows
    # The triangle ids are the tree's own prim_index, counted with the tree.
    assert np.shares_memory(packed.tri_prim, tree.prim_index)
    assert packed.nbytes() == packed.tri.nbytes + packed.rows.nbytes + tables


def _check_all_against_stack(accel_or_bvh, mesh, rays, label):
    """Run every ordered traversal (all options) and skip; compare with bvh2.stack."""

    def trace(key, query, opts):
        variant = registry.get(key)
        return variant.func(
            accel_or_bvh, mesh, rays, query=query, options=variant.make_options(opts), cache=cache
        )

    cache: dict = {}
    ref = trace("bvh2.stack", "closest", {})
    ref_any = trace("bvh2.stack", "any", {})
    for key, opts in ORDERED:
        reference.assert_hits_identical(ref, trace(key, "closest", opts), f"{label}/{key}{opts}")
        reference.assert_hits_identical(ref_any, trace(key, "any", opts), f"{label}/{key}{opts}")
    assert trace("bvh2.skip", "closest", {}).t.tobytes() == ref.t.tobytes()
    return ref


def test_deep_degenerate_tree_identical_triangles():
    """20k identical triangles: every hit is an exact tie; the builder splits by index."""
    n = 20_000
    tri = np.tile([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], (n, 1))
    mesh = rayaccel.TriangleMesh(tri, np.arange(3 * n).reshape(n, 3))
    accel = rayaccel.build(mesh, "bvh2.binned_sah", max_leaf_size=1)
    rng = np.random.default_rng(3)
    o = np.column_stack([rng.random(300) * 0.5, rng.random(300) * 0.5, np.full(300, -1.0)])
    d = np.column_stack([rng.normal(size=300) * 0.05, rng.normal(size=300) * 0.05, np.ones(300)])
    ref = _check_all_against_stack(accel.structure, mesh, RayBatch(o, d), "identical")
    assert ref.hit.sum() > 200


def test_deep_chain_at_max_depth():
    """A MAX_DEPTH-deep caterpillar: the trails, keys and levels use every bit they have."""
    bvh, mesh = reference.chain_tree(MAX_DEPTH)
    bvh.validate(mesh.triangles())
    assert bvh.depth() == MAX_DEPTH
    rng = np.random.default_rng(4)
    o = np.column_stack([rng.random(200) * 0.6, rng.random(200) * 0.6, np.full(200, -1.0)])
    d = np.column_stack([rng.normal(size=200) * 0.02, rng.normal(size=200) * 0.02, np.ones(200)])
    ref = _check_all_against_stack(bvh, mesh, RayBatch(o, d), "chain")
    assert ref.hit.sum() > 100


@pytest.mark.parametrize("traversal", list(registry.keys("traversal", "bvh2")))
def test_degenerate_rays_miss_and_terminate(traversal):
    accel = rayaccel.build(rayaccel.scenes.get("cornell-box"))
    o = np.array([[0.5, 0.5, 0.5]] * 5, np.float32)
    d = np.array([[0, 0, 0], [np.nan, 1, 0], [np.inf, 0, 0], [0, -0.0, 1], [1, 0, 0]], np.float32)
    o[4] = np.nan
    hits = accel.intersect(o, d, traversal=traversal, stats=True)
    ref = accel.intersect(o, d, traversal="bvh2.stack", stats=True)
    reference.assert_hits_identical(ref, hits, traversal)
    assert not hits.hit[[0, 1, 2, 4]].any()
    assert all((hits.stats[k][[0, 1, 2, 4]] == 0).all() for k in hits.stats)


def test_single_leaf_tree():
    mesh = rayaccel.TriangleMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    accel = rayaccel.build(mesh)
    o = np.array([[0.2, 0.2, -1.0], [2.0, 2.0, -1.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    ref = accel.intersect(o, d)
    for key in registry.keys("traversal", "bvh2"):
        reference.assert_hits_identical(ref, accel.intersect(o, d, traversal=key), key)
    state = accel.traversal_state(o, d)
    ray, t, prim, _, _ = state.all_hits()
    assert ray.tolist() == [0]
    assert prim.tolist() == [0]
    assert t[0] == ref.t[0]


def test_options_are_validated():
    accel = rayaccel.build(rayaccel.scenes.get("cornell-box"))
    o, d = np.zeros((1, 3)), np.ones((1, 3))
    with pytest.raises(InvalidInputError, match="short_stack"):
        accel.intersect(o, d, traversal="bvh2.restart_trail", short_stack=-1)
    with pytest.raises(InvalidInputError, match="short_stack"):
        accel.intersect(o, d, traversal="bvh2.restart_trail", short_stack=1.5)
    with pytest.raises(InvalidInputError, match="short_stack"):
        accel.intersect(o, d, traversal="bvh2.restart_trail", short_stack=65)
    with pytest.raises(InvalidInputError, match="level_mask"):
        accel.intersect(o, d, traversal="bvh2.perfect_hash", level_mask="no")
    with pytest.raises(UnknownVariantError, match="short_stack"):
        accel.intersect(o, d, traversal="bvh2.restart_trail", shortstack=3)


def test_perfect_hash_talk_vector():
    keys = np.array([1, 2, 3, 4, 5, 8, 9, 18, 19, 38, 39])
    h = build_perfect_hash(keys, keys, n_table=11, n_disp=8, scatter=False)
    assert h.disp.tolist() == [2, 0, 0, 0, 0, 0, 1, 5]
    assert h.table.tolist() == [39, 1, 2, 3, 4, 5, 38, 18, 19, 9, 8]
    assert np.array_equal(h.lookup(keys), keys)
    scattered = build_perfect_hash(keys, keys, n_table=11, n_disp=8)
    assert np.array_equal(scattered.lookup(keys), keys)
    assert sorted(scattered.table.tolist()) == sorted(keys.tolist())  # still minimal


def _tree_keys(n_leaves, seed):
    """Inner-node keys (root 1, children 2k and 2k + 1) of a random tree split at 30-70%."""
    rng = np.random.default_rng(seed)
    keys, todo = [], [(1, n_leaves)]
    while todo:
        key, n = todo.pop()
        if n < 2:
            continue
        keys.append(key)
        left = min(max(int(rng.integers(int(0.3 * n), int(0.7 * n) + 1)), 1), n - 1)
        todo += [(2 * key, left), (2 * key + 1, n - left)]
    return np.array(keys, dtype=np.int64)


def test_perfect_hash_of_tree_keys_scattered_search():
    """Node keys are structured: searched from 0 their buckets crowd, scattered they fit.

    On this tree the search from 0 needs a table 21% above minimal (and on a 120k-leaf
    one, 60x the time); the scattered search stays within 10%.
    """
    keys = _tree_keys(20_000, 1)
    values = np.arange(keys.size)
    scattered = build_perfect_hash(keys, values)
    from_zero = build_perfect_hash(keys, values, scatter=False)
    for h in (scattered, from_zero):
        assert np.array_equal(h.lookup(keys), values)
    assert scattered.table.size <= 1.1 * keys.size < from_zero.table.size


@given(
    keys=st.sets(st.integers(0, 2**62), min_size=1, max_size=300)
    | st.builds(lambda n, step, start: {start + step * i for i in range(n)},
                st.integers(1, 300), st.integers(1, 2**20), st.integers(0, 2**40)),
    scatter=st.booleans(),
)  # fmt: skip
def test_perfect_hash_answers_every_key(keys, scatter):
    """Any distinct keys (random or evenly spaced), either search: every lookup is right."""
    keys = np.array(sorted(keys), dtype=np.int64)
    h = build_perfect_hash(keys, np.arange(keys.size), scatter=scatter)
    assert np.array_equal(h.lookup(keys), np.arange(keys.size))
    assert (h.table >= 0).sum() == keys.size


def test_perfect_hash_random_keys_and_errors():
    rng = np.random.default_rng(1)
    keys = np.unique(rng.integers(1, 2**56, 5000))
    h = build_perfect_hash(keys, np.arange(keys.size))
    assert np.array_equal(h.lookup(keys), np.arange(keys.size))
    assert h.table.size >= keys.size
    assert (h.table >= 0).sum() == keys.size
    with pytest.raises(InvalidInputError):
        build_perfect_hash(np.array([1, 1]), np.array([0, 1]))


def _all_hits_oracle(mesh, rays):
    tri = reference.tri9(mesh)
    rr = np.repeat(np.arange(rays.n_rays), mesh.n_triangles)
    ff = np.tile(np.arange(mesh.n_triangles), rays.n_rays)
    ev = reference.eval_prims(tri, rays.subset(rr), ff)
    ok = ev.prim >= 0
    ray, t, prim = rr[ok], ev.t[ok], ev.prim[ok]
    order = np.lexsort((prim, t, ray))
    return ray[order], t[order], prim[order]


@pytest.mark.parametrize("scene", ["icosphere", "cornell-box"])
def test_pause_resume_collects_all_hits_in_order(scene):
    mesh = reference.icosphere(2) if scene == "icosphere" else rayaccel.scenes.get(scene)
    accel = rayaccel.build(mesh)
    lo, hi = mesh.bounds()
    rays = reference.concat(
        reference.rays_outside(lo, hi, 120, 1),
        reference.rays_inside(lo, hi, 60, 2),
        reference.rays_intervals(lo, hi, 40, 3),
    )
    state = accel.traversal_state(rays.origin, rays.direction, rays.tmin, rays.tmax)
    first = state.next_hits()
    # The first pause is the any-hit answer of the same traversal order.
    any_hit = accel.trace(rays, query="any", traversal="bvh2.perfect_hash")
    reference.assert_hits_identical(any_hit, first, scene)
    ray, t, prim, _, _ = state.all_hits()
    assert state.done.all()
    ray = np.concatenate([np.flatnonzero(first.hit), ray])
    t = np.concatenate([first.t[first.hit], t])
    prim = np.concatenate([first.prim[first.hit], prim])
    order = np.lexsort((prim, t, ray))
    ref_ray, ref_t, ref_prim = _all_hits_oracle(mesh, rays)
    assert np.array_equal(ray[order], ref_ray)
    assert t[order].tobytes() == ref_t.tobytes()
    assert np.array_equal(prim[order], ref_prim)
    # Finished rays stay finished.
    assert not state.next_hits().hit.any()


def test_traversal_state_closest_is_min_of_all_hits():
    mesh = rayaccel.scenes.get("teapot")
    accel = rayaccel.build(mesh)
    rays = reference.mixed_rays(mesh, 200, seed=9)
    closest = accel.trace(rays)
    ray, t, _, _, _ = accel.traversal_state(
        rays.origin, rays.direction, rays.tmin, rays.tmax
    ).all_hits()
    first = np.full(rays.n_rays, np.inf, np.float32)
    np.minimum.at(first, ray, t)
    assert first.tobytes() == closest.t.tobytes()
