"""The wide traversal ``bvh2.wide``: the vector box tests, the collapsed rows, edge cases.

The registry-driven conformance suite checks ``bvh2.wide`` (width 8) against the
brute-force oracle on every scene; here the 2-, 4- and 8-lane slab tests are compared with
the scalar one lane by lane, the collapsed rows are checked against the binary tree they come from,
and the degenerate trees of the stackless tests are traced.
"""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel._jit import cpu_kernel
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.bvh.layouts.wide import (
    C_NODE,
    C_PRIM,
    MAX_LEAF,
    WIDTHS,
    count_column,
    ref_column,
    wide_layout,
)
from rayaccel.bvh.traverse.stack import packed_layout
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.aabb import ray_box_entry
from rayaccel.kernels.aabb_wide import slab_test2, slab_test4, slab_test8
from rayaccel.kernels.sah import box_half_area_py
from rayaccel.rays.batch import RayBatch


@cpu_kernel()
def _both_tests(rows, width, origin, inv, t_lo, t_hi, wide_t, wide_mask, scalar_t):
    """Every ray against every row: the vector test and the scalar test of each lane."""
    lane_t = np.empty(width, dtype=np.float32)
    for r in range(origin.shape[0]):
        ox, oy, oz = origin[r, 0], origin[r, 1], origin[r, 2]
        ix, iy, iz = inv[r, 0], inv[r, 1], inv[r, 2]
        nx = 0 if ix >= 0 else width
        ny = 2 * width if iy >= 0 else 3 * width
        nz = 4 * width if iz >= 0 else 5 * width
        fx, fy, fz = width - nx, 5 * width - ny, 9 * width - nz
        for w in range(rows.shape[0]):
            if width == 8:
                wide_mask[r, w] = slab_test8(
                    rows, w, nx, fx, ny, fy, nz, fz, ox, oy, oz, ix, iy, iz, t_lo[r], t_hi[r],
                    lane_t,
                )  # fmt: skip
            elif width == 4:
                wide_mask[r, w] = slab_test4(
                    rows, w, nx, fx, ny, fy, nz, fz, ox, oy, oz, ix, iy, iz, t_lo[r], t_hi[r],
                    lane_t,
                )  # fmt: skip
            else:
                wide_mask[r, w] = slab_test2(
                    rows, w, nx, fx, ny, fy, nz, fz, ox, oy, oz, ix, iy, iz, t_lo[r], t_hi[r],
                    lane_t,
                )  # fmt: skip
            for j in range(width):
                wide_t[r, w, j] = lane_t[j]
                scalar_t[r, w, j] = ray_box_entry(
                    ox, oy, oz, ix, iy, iz,
                    rows[w, nx + j], rows[w, ny + j], rows[w, nz + j],
                    rows[w, fx + j], rows[w, fy + j], rows[w, fz + j],
                    t_lo[r], t_hi[r],
                )  # fmt: skip


@pytest.mark.parametrize("width", [2, *WIDTHS])
def test_vector_slab_test_matches_the_scalar_one_lane_by_lane(width):
    """Width 2 is the pairs row of ``bvh2.stack`` (same structure-of-arrays planes)."""
    rng = np.random.default_rng(0)
    n_rows, n_rays = 64, 400
    lo = rng.uniform(-2, 1, (n_rows, width, 3)).astype(np.float32)
    hi = (lo + rng.uniform(0, 2, lo.shape)).astype(np.float32)
    hi[::5, 1, 0] = lo[::5, 1, 0]  # flat boxes
    rows = np.zeros((n_rows, 8 * width), np.float32)
    for a in range(3):
        rows[:, 2 * a * width : (2 * a + 1) * width] = lo[:, :, a]
        rows[:, (2 * a + 1) * width : (2 * a + 2) * width] = hi[:, :, a]
    last = [(k + 1) * width - 1 for k in range(6)]
    rows[::3, last[0::2]] = np.inf  # empty last lane, as the collapse writes it
    rows[::3, last[1::2]] = -np.inf
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
    wide_t = np.empty((n_rays, n_rows, width), np.float32)
    scalar_t = np.empty_like(wide_t)
    mask = np.empty((n_rays, n_rows), np.int32)
    _both_tests(rows, width, origin, inv, t_lo, t_hi, wide_t, mask, scalar_t)
    assert np.array_equal(wide_t, scalar_t)
    bits = (mask[:, :, None] >> np.arange(width)) & 1
    assert np.array_equal(bits == 1, wide_t < np.inf)
    assert not (wide_t[:, ::3, width - 1] < np.inf).any()
    assert 500 < (wide_t < np.inf).sum() < wide_t.size // 2


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("scene", ["teapot", "teapot-in-stadium"])
def test_greedy_rows_reproduce_the_binary_tree(scene, width):
    accel = rayaccel.build(rayaccel.scenes.get(scene))
    packed = packed_layout(accel.structure, accel.mesh, None)
    wide = wide_layout(packed, width, "greedy")
    rows, refs = wide.rows, wide.rows.view(np.int32)
    count = refs[:, count_column(width)]
    assert ((count >= 2) & (count <= width)).all()
    tree = accel.structure
    assert wide.n_rows <= tree.n_nodes - tree.n_leaves
    # Every binary leaf hangs under exactly one wide lane (as ~node), with its own box.
    binary_box = {
        ~i: [b[i, a] for a in range(3) for b in (tree.node_lo, tree.node_hi)]
        for i in np.flatnonzero(tree.node_count)
    }
    leaves, inner = [], []
    for w in range(wide.n_rows):
        for j in range(count[w]):
            ref = int(refs[w, ref_column(width) + j])
            (inner if ref >= 0 else leaves).append(ref)
            if ref < 0:
                box = [rows[w, (2 * a + s) * width + j] for a in range(3) for s in range(2)]
                assert np.array_equal(box, binary_box[ref])
        # A row with an inner child was filled to ``width`` children.
        if any(refs[w, ref_column(width) + j] >= 0 for j in range(count[w])):
            assert count[w] == width
    assert sorted(leaves) == sorted(binary_box)
    assert not packed.has_rows
    assert sorted(inner) == list(range(1, wide.n_rows))


def _lanes(wide, w):
    """Yield ``(reference, lo, hi)`` of every child of row ``w``."""
    width = wide.width
    refs = wide.rows.view(np.int32)
    for j in range(refs[w, count_column(width)]):
        lo = [wide.rows[w, 2 * a * width + j] for a in range(3)]
        hi = [wide.rows[w, (2 * a + 1) * width + j] for a in range(3)]
        yield int(refs[w, ref_column(width) + j]), lo, hi


def _wide_sah(wide, root_lo, root_hi):
    """The SAH cost the collapse minimises: C_NODE per row's box, C_PRIM per leaf triangle."""
    cost = C_NODE * box_half_area_py(*root_lo, *root_hi)
    for w in range(wide.n_rows):
        for ref, lo, hi in _lanes(wide, w):
            if ref >= 0:
                cost += C_NODE * box_half_area_py(*lo, *hi)
            else:
                cost += C_PRIM * box_half_area_py(*lo, *hi) * int(wide.leaf_count[~ref])
    return cost


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("scene", ["teapot", "teapot-in-stadium", "cornell-box"])
def test_sah_collapse_covers_every_triangle_once_and_costs_no_more_than_greedy(scene, width):
    accel = rayaccel.build(rayaccel.scenes.get(scene))
    tree = accel.structure
    packed = packed_layout(tree, accel.mesh, None)
    wide, greedy = wide_layout(packed, width), wide_layout(packed, width, "greedy")
    count = wide.rows.view(np.int32)[:, count_column(width)]
    assert ((count >= 2) & (count <= width)).all()
    corners = accel.mesh.vertices[accel.mesh.faces[tree.prim_index]]  # in triangle-row order
    inner, leaves = [], []
    for w in range(wide.n_rows):
        for ref, lo, hi in _lanes(wide, w):
            if ref >= 0:
                inner.append(ref)
                for _, child_lo, child_hi in _lanes(wide, ref):  # children inside the box
                    assert (np.array(child_lo) >= lo).all()
                    assert (np.array(child_hi) <= hi).all()
            else:
                leaves.append(~ref)
                first, n = int(wide.leaf_first[~ref]), int(wide.leaf_count[~ref])
                rows = corners[first : first + n].reshape(-1, 3)
                assert (rows.min(axis=0) >= lo).all()
                assert (rows.max(axis=0) <= hi).all()
    assert sorted(inner) == list(range(1, wide.n_rows))
    assert sorted(leaves) == list(range(wide.leaf_first.shape[0]))
    # The leaves' runs of triangle rows tile the rows exactly, each within the leaf limit
    # unless it is a binary leaf (which cannot be split).
    order = np.argsort(wide.leaf_first)
    starts, sizes = wide.leaf_first[order], wide.leaf_count[order]
    assert starts[0] == 0
    assert np.array_equal(starts[1:], (starts + sizes)[:-1])
    assert starts[-1] + sizes[-1] == tree.n_refs
    is_leaf = tree.node_count > 0
    binary = set(zip(tree.node_first[is_leaf], tree.node_count[is_leaf], strict=True))
    big = sizes > MAX_LEAF
    assert all((int(f), int(n)) in binary for f, n in zip(starts[big], sizes[big], strict=True))
    # The greedy collapse is one of the collapses the SAH one chose among.
    root_lo, root_hi = tree.node_lo[0], tree.node_hi[0]
    assert _wide_sah(wide, root_lo, root_hi) <= _wide_sah(greedy, root_lo, root_hi) * (1 + 1e-9)
    assert wide.n_rows < greedy.n_rows
    assert wide.nbytes() == wide.rows.nbytes + wide.leaf_first.nbytes + wide.leaf_count.nbytes
    assert greedy.nbytes() == greedy.rows.nbytes


def test_a_few_triangles_cheapest_as_one_leaf_make_no_rows():
    mesh = reference.grid_plane(1)  # two triangles, split into two leaves below
    accel = rayaccel.build(mesh, "bvh2.binned_sah", max_leaf_size=1)
    assert accel.structure.n_leaves == 2
    wide = wide_layout(packed_layout(accel.structure, mesh, None), 8)
    assert wide.root_ref[0] < 0
    assert wide.n_rows == 0
    assert (int(wide.leaf_first[0]), int(wide.leaf_count[0])) == (0, 2)
    rays = reference.mixed_rays(mesh, n=300)
    oracle = reference.oracle(mesh, rays)
    assert accel.trace(rays, traversal="bvh2.wide").t.tobytes() == oracle.t.tobytes()
    occluded = accel.occluded(rays.origin, rays.direction, rays.tmin, rays.tmax)
    assert np.array_equal(occluded, oracle.prim >= 0)


@pytest.mark.parametrize("width", WIDTHS)
def test_same_closest_t_and_occlusion_as_the_stack_traversal(width):
    for scene in ("soup", "cornell-box", "teapot-in-stadium"):
        accel = rayaccel.build(rayaccel.scenes.get(scene), "bvh2.lbvh")
        rays = reference.mixed_rays(accel.mesh, n=900)
        ref = accel.trace(rays, traversal="bvh2.stack", stats=True)
        hits = accel.trace(rays, traversal="bvh2.wide", stats=True, width=width)
        assert hits.t.tobytes() == ref.t.tobytes(), scene
        ties = np.flatnonzero(hits.prim != ref.prim)
        again = reference.eval_prims(reference.tri9(accel.mesh), rays.subset(ties), hits.prim[ties])
        assert again.t.tobytes() == ref.t[ties].tobytes(), scene
        occluded = accel.occluded(
            rays.origin, rays.direction, rays.tmin, rays.tmax, traversal="bvh2.wide", width=width
        )
        lanes = accel.occluded(
            rays.origin, rays.direction, rays.tmin, rays.tmax, traversal="bvh2.wide",
            width=width, any_order="lanes",
        )  # fmt: skip
        assert np.array_equal(lanes, occluded), scene
        assert np.array_equal(
            occluded,
            accel.occluded(rays.origin, rays.direction, rays.tmin, rays.tmax,
                           traversal="bvh2.stack"),
        ), scene
        # Half the steps of the binary traversal or fewer, more box tests per step.
        visited = ref.stats["nodes"] > 0
        assert hits.stats["nodes"][visited].sum() < 0.75 * ref.stats["nodes"][visited].sum()
        assert (hits.stats["stack_peak"] <= (width - 1) * MAX_DEPTH).all()


def test_counters_bytes_and_options():
    accel = rayaccel.build(rayaccel.scenes.get("teapot"))
    rays = reference.mixed_rays(accel.mesh, n=400)
    hits = accel.trace(rays, traversal="bvh2.wide", stats=True, width=4)
    eight = accel.trace(rays, traversal="bvh2.wide", stats=True).stats
    s = hits.stats
    assert eight["nodes"].sum() < s["nodes"].sum()
    assert eight["bytes"].sum() > 0
    with pytest.raises(InvalidInputError, match="width"):
        accel.intersect(rays.origin, rays.direction, traversal="bvh2.wide", width=6)
    with pytest.raises(InvalidInputError, match="any_order"):
        accel.occluded(rays.origin, rays.direction, traversal="bvh2.wide", any_order="far")
    with pytest.raises(InvalidInputError, match="collapse"):
        accel.intersect(rays.origin, rays.direction, traversal="bvh2.wide", collapse="best")
    # The greedy rows find the same closest hits, with more steps.
    greedy = accel.trace(rays, traversal="bvh2.wide", stats=True, collapse="greedy")
    assert greedy.t.tobytes() == accel.trace(rays, traversal="bvh2.wide").t.tobytes()
    assert greedy.stats["nodes"].sum() > eight["nodes"].sum()
    assert accel.derived("bvh2.wide8.greedy") is not None
    # The lane order changes only any-hit queries: closest hits keep the nearest-first walk.
    lanes = accel.trace(rays, traversal="bvh2.wide", stats=True, any_order="lanes").stats
    assert all(np.array_equal(lanes[k], eight[k]) for k in eight)
    assert (s["steps"] == s["nodes"]).all()
    assert (s["box_tests"] >= s["nodes"]).all()
    assert (s["box_tests"][s["nodes"] > 1] > 2 * s["nodes"][s["nodes"] > 1] - 2).all()
    wide4, wide8 = accel.derived("bvh2.wide4"), accel.derived("bvh2.wide8")
    assert wide4 is not None
    assert wide8 is not None
    assert wide4.nbytes() == wide4.rows.nbytes + 2 * wide4.leaf_first.nbytes
    info = accel.info()
    assert info["bytes"] >= accel.structure.nbytes() + wide4.nbytes() + wide8.nbytes()


def test_deep_chain_and_identical_triangles():
    bvh, mesh = reference.chain_tree(MAX_DEPTH)
    rng = np.random.default_rng(4)
    o = np.column_stack([rng.random(200) * 0.6, rng.random(200) * 0.6, np.full(200, -1.0)])
    d = np.column_stack([rng.normal(size=200) * 0.02, rng.normal(size=200) * 0.02, np.ones(200)])
    rays = RayBatch(o, d)
    cache: dict = {}
    stack = rayaccel.registry.get("bvh2.stack").func
    wide = rayaccel.registry.get("bvh2.wide")
    ref = stack(bvh, mesh, rays, cache=cache)
    assert ref.hit.sum() > 100
    for width in WIDTHS:
        options = wide.make_options({"width": width})
        hits = wide.func(bvh, mesh, rays, options=options, cache=cache)
        assert hits.t.tobytes() == ref.t.tobytes()
    n = 20_000
    tri = np.tile([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], (n, 1))
    accel = rayaccel.build(
        rayaccel.TriangleMesh(tri, np.arange(3 * n).reshape(n, 3)), max_leaf_size=1
    )
    ref = accel.intersect(o, d, traversal="bvh2.stack")
    for width in WIDTHS:
        hits = accel.intersect(o, d, traversal="bvh2.wide", width=width)
        assert hits.t.tobytes() == ref.t.tobytes()
        assert np.array_equal(hits.hit, ref.hit)
