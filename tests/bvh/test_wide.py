"""The 4-wide traversal ``bvh2.wide``: the vector box test, the collapsed rows, edge cases.

The registry-driven conformance suite checks ``bvh2.wide`` against the brute-force
oracle on every scene; here the 4-lane slab test is compared with the scalar one
lane by lane, the collapsed rows are checked against the binary tree they come from,
and the degenerate trees of the stackless tests are traced.
"""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel._jit import cpu_kernel
from rayaccel.bvh.layout import MAX_DEPTH
from rayaccel.bvh.traverse_stack import packed_layout
from rayaccel.bvh.wide import COUNT_COLUMN, REF_COLUMN, WIDTH, wide_layout
from rayaccel.kernels.aabb import ray_box_entry
from rayaccel.kernels.aabb_wide import slab_test4
from rayaccel.rays.batch import RayBatch


@cpu_kernel()
def _both_tests(rows, origin, inv, t_lo, t_hi, wide_t, wide_mask, scalar_t):
    """Every ray against every row: 4-lane test and the scalar test of each lane."""
    lane_t = np.empty(WIDTH, dtype=np.float32)
    for r in range(origin.shape[0]):
        ox, oy, oz = origin[r, 0], origin[r, 1], origin[r, 2]
        ix, iy, iz = inv[r, 0], inv[r, 1], inv[r, 2]
        nx = 0 if ix >= 0 else 4
        ny = 8 if iy >= 0 else 12
        nz = 16 if iz >= 0 else 20
        for w in range(rows.shape[0]):
            wide_mask[r, w] = slab_test4(
                rows, w, nx, 4 - nx, ny, 20 - ny, nz, 36 - nz,
                ox, oy, oz, ix, iy, iz, t_lo[r], t_hi[r], lane_t,
            )  # fmt: skip
            for j in range(WIDTH):
                wide_t[r, w, j] = lane_t[j]
                scalar_t[r, w, j] = ray_box_entry(
                    ox, oy, oz, ix, iy, iz,
                    rows[w, nx + j], rows[w, ny + j], rows[w, nz + j],
                    rows[w, 4 - nx + j], rows[w, 20 - ny + j], rows[w, 36 - nz + j],
                    t_lo[r], t_hi[r],
                )  # fmt: skip


def test_vector_slab_test_matches_the_scalar_one_lane_by_lane():
    rng = np.random.default_rng(0)
    n_rows, n_rays = 64, 400
    lo = rng.uniform(-2, 1, (n_rows, WIDTH, 3)).astype(np.float32)
    hi = (lo + rng.uniform(0, 2, lo.shape)).astype(np.float32)
    hi[::5, 1, 0] = lo[::5, 1, 0]  # flat boxes
    rows = np.zeros((n_rows, 32), np.float32)
    for a in range(3):
        rows[:, 8 * a : 8 * a + 4] = lo[:, :, a]
        rows[:, 8 * a + 4 : 8 * a + 8] = hi[:, :, a]
    rows[::3, [3, 11, 19]] = np.inf  # empty lane, as the collapse writes it
    rows[::3, [7, 15, 23]] = -np.inf
    origin = rng.uniform(-3, 3, (n_rays, 3)).astype(np.float32)
    direction = rng.normal(size=(n_rays, 3)).astype(np.float32)
    direction[::4, rng.integers(0, 3)] = 0.0  # zero components: inv = ±inf
    direction[1::8, 1] = -0.0
    origin[::9, 0] = lo[0, 0, 0]  # origins in a slab plane (0 * inf = NaN)
    with np.errstate(divide="ignore"):
        inv = (np.float32(1.0) / direction).astype(np.float32)
    t_lo = rng.uniform(0, 0.5, n_rays).astype(np.float32)
    t_hi = np.where(rng.random(n_rays) < 0.5, np.inf, rng.uniform(0.5, 5, n_rays)).astype(
        np.float32
    )
    wide_t = np.empty((n_rays, n_rows, WIDTH), np.float32)
    scalar_t = np.empty_like(wide_t)
    mask = np.empty((n_rays, n_rows), np.int32)
    _both_tests(rows, origin, inv, t_lo, t_hi, wide_t, mask, scalar_t)
    assert np.array_equal(wide_t, scalar_t)
    bits = (mask[:, :, None] >> np.arange(WIDTH)) & 1
    assert np.array_equal(bits == 1, wide_t < np.inf)
    assert not (wide_t[:, ::3, 3] < np.inf).any()
    assert 500 < (wide_t < np.inf).sum() < wide_t.size // 2


@pytest.mark.parametrize("scene", ["teapot", "teapot-in-stadium"])
def test_collapsed_rows_reproduce_the_binary_tree(scene):
    accel = rayaccel.build(rayaccel.scenes.get(scene))
    packed = packed_layout(accel.structure, accel.mesh, None)
    wide = wide_layout(packed)
    rows, refs = wide.rows, wide.rows.view(np.int32)
    count = refs[:, COUNT_COLUMN]
    assert ((count >= 2) & (count <= WIDTH)).all()
    assert wide.n_rows <= packed.rows.shape[0]
    # Every binary leaf hangs under exactly one wide lane, with its own box.
    binary_box = {}
    for row in range(packed.rows.shape[0]):
        for c in range(2):
            binary_box[int(packed.rows.view(np.int32)[row, 12 + c])] = packed.rows[
                row, 6 * c : 6 * c + 6
            ]
    leaves, inner = [], []
    for w in range(wide.n_rows):
        for j in range(count[w]):
            ref = int(refs[w, REF_COLUMN + j])
            (inner if ref >= 0 else leaves).append(ref)
            if ref < 0:
                box = [rows[w, 8 * a + 4 * s + j] for a in range(3) for s in range(2)]
                assert np.array_equal(box, binary_box[ref])
        # A row with an inner child at rank < 4 was filled to four children.
        if any(refs[w, REF_COLUMN + j] >= 0 for j in range(count[w])):
            assert count[w] == WIDTH
    assert sorted(leaves) == sorted(range(-packed.leaf_first.shape[0], 0))
    assert sorted(inner) == list(range(1, wide.n_rows))


def test_same_closest_t_and_occlusion_as_the_stack_traversal():
    for scene in ("soup", "cornell-box", "teapot-in-stadium"):
        accel = rayaccel.build(rayaccel.scenes.get(scene), "bvh2.lbvh")
        rays = reference.mixed_rays(accel.mesh, n=900)
        ref = accel.trace(rays, stats=True)
        hits = accel.trace(rays, traversal="bvh2.wide", stats=True)
        assert hits.t.tobytes() == ref.t.tobytes(), scene
        ties = np.flatnonzero(hits.prim != ref.prim)
        again = reference.eval_prims(reference.tri9(accel.mesh), rays.subset(ties), hits.prim[ties])
        assert again.t.tobytes() == ref.t[ties].tobytes(), scene
        occluded = accel.occluded(
            rays.origin, rays.direction, rays.tmin, rays.tmax, traversal="bvh2.wide"
        )
        assert np.array_equal(
            occluded, accel.occluded(rays.origin, rays.direction, rays.tmin, rays.tmax)
        ), scene
        # Half the steps of the binary traversal or fewer, more box tests per step.
        visited = ref.stats["nodes"] > 0
        assert hits.stats["nodes"][visited].sum() < 0.75 * ref.stats["nodes"][visited].sum()
        assert (hits.stats["stack_peak"] <= 3 * MAX_DEPTH).all()


def test_counters_and_bytes():
    accel = rayaccel.build(rayaccel.scenes.get("teapot"))
    rays = reference.mixed_rays(accel.mesh, n=400)
    hits = accel.trace(rays, traversal="bvh2.wide", stats=True)
    s = hits.stats
    assert (s["steps"] == s["nodes"]).all()
    assert (s["box_tests"] >= s["nodes"]).all()
    assert (s["box_tests"][s["nodes"] > 1] > 2 * s["nodes"][s["nodes"] > 1] - 2).all()
    wide = accel.derived("bvh2.wide")
    assert wide is not None
    assert wide.nbytes() == wide.rows.nbytes
    info = accel.info()
    assert info["bytes"] >= accel.structure.nbytes() + wide.nbytes()


def test_deep_chain_and_identical_triangles():
    bvh, mesh = reference.chain_tree(MAX_DEPTH)
    rng = np.random.default_rng(4)
    o = np.column_stack([rng.random(200) * 0.6, rng.random(200) * 0.6, np.full(200, -1.0)])
    d = np.column_stack([rng.normal(size=200) * 0.02, rng.normal(size=200) * 0.02, np.ones(200)])
    rays = RayBatch(o, d)
    cache: dict = {}
    stack = rayaccel.registry.get("bvh2.stack").func
    wide = rayaccel.registry.get("bvh2.wide").func
    ref = stack(bvh, mesh, rays, cache=cache)
    hits = wide(bvh, mesh, rays, cache=cache)
    assert ref.hit.sum() > 100
    assert hits.t.tobytes() == ref.t.tobytes()
    n = 20_000
    tri = np.tile([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], (n, 1))
    accel = rayaccel.build(
        rayaccel.TriangleMesh(tri, np.arange(3 * n).reshape(n, 3)), max_leaf_size=1
    )
    ref = accel.intersect(o, d)
    hits = accel.intersect(o, d, traversal="bvh2.wide")
    assert hits.t.tobytes() == ref.t.tobytes()
    assert np.array_equal(hits.hit, ref.hit)
