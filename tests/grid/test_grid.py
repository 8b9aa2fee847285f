"""Grid family: resolution, caps, skip data, and the DDA's edge cases against the oracle.

Registry conformance (tests/test_conformance.py) already runs every grid build key with
``grid.dda`` and every traversal on ``grid.uniform``; here the skipping builders are
also traced with ``grid.skip`` (their own traversal), on the edge cases of issue 17:
rays along cell boundaries and grid faces, origins inside, on and outside the grid,
axis-parallel rays with ±0.0 components, a flat scene, a single triangle, 100k copies
of one triangle, and the teapot in a stadium. The irregular grid's merge and expansion
are checked against their invariants.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.errors import InvalidInputError, StructureInvariantError
from rayaccel.grid.builders import two_level
from rayaccel.grid.builders.skip import chessboard_distance, macro_regions, mip_bits
from rayaccel.grid.builders.uniform import UniformGridOptions, grid_resolution
from rayaccel.grid.layouts.uniform import (
    SKIP_DISTANCE,
    SKIP_MACRO,
    SKIP_MIPMAP,
    UniformGrid,
    mip_levels_needed,
)
from rayaccel.rays.batch import RayBatch

#: (builder, traversal): each skipping builder with the traversal that reads its data.
#: ``grid.two_level+distance`` is ``grid.two_level`` with ``skip="distance"``.
PAIRS = [
    pytest.param("grid.uniform", "grid.dda", id="uniform-dda"),
    pytest.param("grid.distance", "grid.skip", id="distance-skip"),
    pytest.param("grid.macro_regions", "grid.skip", id="macro-skip"),
    pytest.param("grid.mipmap", "grid.skip", id="mipmap-skip"),
    pytest.param("grid.two_level", "grid.dda", id="two_level-dda"),
    pytest.param("grid.two_level+distance", "grid.skip", id="two_level_distance-skip"),
    pytest.param("grid.irregular", "grid.dda", id="irregular-dda"),
]
_ACCELS: dict = {}


def _build(mesh, builder):
    if builder == "grid.two_level+distance":
        return rayaccel.build(mesh, "grid.two_level", skip="distance")
    return rayaccel.build(mesh, builder)


def _accel(scenes_cache, builder, scene):
    if builder != "grid.two_level+distance":
        return scenes_cache.accel(builder, scene)
    key = (builder, scene)
    if key not in _ACCELS:
        _ACCELS[key] = _build(scenes_cache.mesh(scene), builder)
    return _ACCELS[key]


def _check(accel, rays: RayBatch, traversal: str, label: str = "") -> None:
    tri = reference.tri9(accel.mesh)
    ref = reference.oracle(accel.mesh, rays)
    hits = accel.trace(rays, traversal=traversal)
    reference.assert_closest_matches(tri, rays, hits, ref, label)
    any_hits = accel.trace(rays, traversal=traversal, query="any")
    reference.assert_any_matches(tri, rays, any_hits, ref, label)


def _boundary_rays(accel, n: int, seed: int) -> RayBatch:
    """Rays in cell-boundary planes and grid faces, axis-parallel with ±0.0 components,
    with origins on cell (or voxel) corners, on the grid box and outside it."""
    grid = getattr(accel.structure, "top", accel.structure)
    rng = np.random.default_rng(seed)
    lo = grid.lo.astype(np.float32)
    res = getattr(grid, "fine_res", None)  # the irregular grid's voxels
    res = grid.res if res is None else res
    size = ((grid.hi - grid.lo) / res).astype(np.float32)
    origins = []
    dirs = []
    for _ in range(n):
        cell = rng.integers(0, res + 1)
        o = lo + cell.astype(np.float32) * size  # a cell corner (float32, as the DDA)
        d = rng.normal(size=3)
        zero = rng.integers(0, 3)
        d[zero] = 0.0 if rng.random() < 0.5 else -0.0
        if rng.random() < 0.3:
            d[(zero + 1) % 3] = -0.0
        if rng.random() < 0.3:  # start outside, along the same line
            o = o - 3.0 * d * float(np.max(grid.hi - grid.lo))
        origins.append(o)
        dirs.append(d)
    return RayBatch(np.array(origins, np.float32), np.array(dirs, np.float32))


def test_resolution_formula():
    assert tuple(grid_resolution(np.array([1.0, 1.0, 1.0]), 1000)) == (10, 10, 10)
    assert tuple(grid_resolution(np.array([2.0, 1.0, 1.0]), 2000)) == (20, 10, 10)
    # A flat box: one cell across, the 2D formula on the other axes.
    assert tuple(grid_resolution(np.array([1.0, 1.0, 1e-9]), 400)) == (20, 20, 1)
    assert tuple(grid_resolution(np.array([1.0, 1e-9, 1e-9]), 50)) == (50, 1, 1)


def test_sub_grid_resolutions_follow_the_formula():
    """Each top cell's sub-grid is Slusallek's resolution of its box for λ2 · references."""
    rng = np.random.default_rng(7)
    for size in ([1.0, 1.0, 1.0], [2.0, 0.5, 1e-6], [3.0, 1e-9, 1e-9]):
        counts = np.concatenate([[0, 1, 2], rng.integers(0, 20000, 200)])
        got = two_level.sub_resolutions(np.array(size), counts, 1.2)
        assert got.dtype == np.int32
        assert got.shape == (counts.size, 3)
        for c, n in enumerate(counts):
            want = (1, 1, 1) if n == 0 else tuple(grid_resolution(np.array(size), 1.2 * n))
            assert tuple(got[c]) == want, (size, n)


def test_density_cap_raises():
    mesh = reference.cube()
    with pytest.raises(InvalidInputError, match="max_cells"):
        rayaccel.build(mesh, "grid.uniform", density=1000.0, max_cells=1000)
    with pytest.raises(InvalidInputError, match="density"):
        UniformGridOptions(density=0.0)
    with pytest.raises(InvalidInputError, match="max_refs_per_prim"):
        UniformGridOptions(max_refs_per_prim=0.5)


def test_info_and_validate(scenes_cache):
    accel = scenes_cache.accel("grid.uniform", "teapot")
    info = accel.info()
    for key in ("resolution", "n_cells", "empty_fraction", "refs_per_prim", "bytes"):
        assert key in info
    assert set(info["build_phase_ms"]) >= {"count", "fill", "sort", "ranges"}
    grid = accel.structure
    grid.validate(accel.mesh.triangles())
    broken = UniformGrid(grid.lo, grid.hi, grid.res, grid.cell_start,
                         grid.prim_index[::-1].copy(), grid.skip_kind, grid.skip, grid.n_prims)
    with pytest.raises(StructureInvariantError):
        broken.validate()


@pytest.mark.parametrize("seed", range(4))
def test_skip_data_matches_definition(seed):
    """Distance field, macro regions and mip levels against their definitions on random grids."""
    rng = np.random.default_rng(seed)
    res = rng.integers(1, 12, size=3).astype(np.int32)
    n_cells = int(np.prod(res))
    occupied = rng.random(n_cells) < rng.choice([0.02, 0.1, 0.4])
    occupied[rng.integers(0, n_cells)] = True
    counts = occupied.astype(np.int32)
    cell_start = np.zeros(n_cells + 1, np.int32)
    np.cumsum(counts, out=cell_start[1:])
    n = int(cell_start[-1])
    prim_index = np.arange(n, dtype=np.int32)
    lo = np.zeros(3, np.float32)
    hi = np.ones(3, np.float32)
    rx, ry, rz = (int(r) for r in res)
    top = mip_levels_needed(res)
    bits = mip_bits(cell_start, rx, ry, rz, top)
    for kind, skip in ((SKIP_DISTANCE, chessboard_distance(cell_start, rx, ry, rz)),
                       (SKIP_MACRO, macro_regions(cell_start, rx, ry, rz)),
                       (SKIP_MIPMAP, bits)):
        UniformGrid(lo, hi, res, cell_start, prim_index, kind, skip, n).validate()
    # The pyramid by brute force: bit m set iff the aligned 2^m block holds an occupied cell.
    grid = occupied.reshape(rz, ry, rx)
    for c in range(n_cells):
        x, y, z = c % rx, (c // rx) % ry, c // (rx * ry)
        expect = sum(
            int(grid[(z >> m) << m:((z >> m) + 1) << m, (y >> m) << m:((y >> m) + 1) << m,
                     (x >> m) << m:((x >> m) + 1) << m].any()) << m
            for m in range(top + 1)
        )  # fmt: skip
        assert int(bits[c, 0]) & 0xFFFF == expect
    assert (1 << top) >= max(rx, ry, rz)
    assert top == 0 or (1 << (top - 1)) < max(rx, ry, rz)
    flipped = bits.copy()
    flipped[int(rng.integers(0, n_cells)), 0] ^= 1 << int(rng.integers(0, top + 1))
    with pytest.raises(StructureInvariantError, match="mip-map bits"):
        UniformGrid(lo, hi, res, cell_start, prim_index, SKIP_MIPMAP, flipped, n).validate()


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
@pytest.mark.parametrize("scene", ["cornell-box", "teapot", "teapot-in-stadium"])
def test_procedural_scenes(scenes_cache, builder, traversal, scene):
    accel = _accel(scenes_cache, builder, scene)
    accel.validate()
    _check(accel, scenes_cache.ray_set(scene), traversal, f"{builder}/{scene}")
    _check(accel, reference.mixed_rays(accel.mesh, 400, seed=3), traversal, "mixed")


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
@pytest.mark.parametrize("scene", ["cornell-box", "teapot"])
def test_cell_boundary_rays(scenes_cache, builder, traversal, scene):
    accel = _accel(scenes_cache, builder, scene)
    _check(accel, _boundary_rays(accel, 600, seed=7), traversal, "boundary")


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_flat_scene(builder, traversal):
    """A single plane (flat along z): grazing, crossing and in-plane rays."""
    mesh = reference.grid_plane(8, z=0.5)
    accel = _build(mesh, builder)
    accel.validate()
    grid = getattr(accel.structure, "top", accel.structure)
    assert getattr(grid, "top_res", getattr(grid, "res", None))[2] == 1
    lo, hi = mesh.bounds()
    rng = np.random.default_rng(1)
    n = 300
    o = lo + rng.random((n, 3)) * (hi - lo)
    o[:, 2] = 0.5  # in the plane
    d = rng.normal(size=(n, 3))
    d[: n // 2, 2] = 0.0
    d[n // 4 : n // 2, 2] = -0.0
    in_plane = RayBatch(o, d)
    _check(accel, in_plane, traversal, "in-plane")
    _check(accel, reference.mixed_rays(mesh, 400, seed=4), traversal, "mixed")
    _check(accel, _boundary_rays(accel, 300, seed=5), traversal, "boundary")


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_single_triangle(builder, traversal):
    mesh = rayaccel.TriangleMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0.3]], [[0, 1, 2]])
    accel = _build(mesh, builder)
    accel.validate()
    _check(accel, reference.mixed_rays(mesh, 400, seed=6), traversal, "single")
    _check(accel, _boundary_rays(accel, 200, seed=8), traversal, "boundary")


def test_copies_of_one_triangle():
    """100k copies of one triangle: the reference budget lowers the resolution."""
    faces = np.zeros((100_000, 3), np.int64)
    faces[:, 1] = 1
    faces[:, 2] = 2
    mesh = rayaccel.TriangleMesh([[0, 0, 0], [1, 0.2, 0], [0.3, 1, 0.7]], faces)
    accel = rayaccel.build(mesh, "grid.uniform")
    accel.validate()
    info = accel.info()
    assert info["n_refs"] <= 16 * 100_000
    rays = reference.subsample(reference.mixed_rays(mesh, 120, seed=9), 60)
    _check(accel, rays, "grid.dda", "copies")


@pytest.mark.parametrize("rounds", [1, 2])
def test_two_level_stops_coarsening_after_its_rounds(monkeypatch, rounds):
    """Identical triangles need the sub-grids halved; cut short, the grid is still right."""
    tri = np.broadcast_to(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64), (5000, 3, 3))
    mesh = rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(15000).reshape(-1, 3))
    full = rayaccel.build(mesh, "grid.two_level", max_refs_per_prim=2.0)
    monkeypatch.setattr(two_level, "MAX_SHRINK_ROUNDS", rounds)
    accel = rayaccel.build(mesh, "grid.two_level", max_refs_per_prim=2.0)
    accel.validate()
    # Fewer halvings leave more leaves per crowded top cell, so more references.
    assert accel.structure.prim_index.shape[0] > full.structure.prim_index.shape[0]
    rays = reference.subsample(reference.mixed_rays(mesh, 120, seed=4), 60)
    _check(accel, rays, "grid.dda", f"{rounds} rounds")


def test_two_level_leaves_and_cap():
    mesh = reference.icosphere(3)
    accel = rayaccel.build(mesh, "grid.two_level")
    accel.validate()
    info = accel.info()
    assert info["n_leaf_cells"] >= info["n_cells"]
    with pytest.raises(InvalidInputError, match="max_cells"):
        rayaccel.build(mesh, "grid.two_level", leaf_density=1000.0, max_cells=2000)


@pytest.mark.parametrize("builder", ["grid.distance", "grid.macro_regions", "grid.mipmap"])
def test_skipping_visits_fewer_cells(scenes_cache, builder):
    """On the teapot in a stadium every skipping grid enters fewer cells than the plain DDA."""
    rays = reference.mixed_rays(scenes_cache.mesh("teapot-in-stadium"), 300, seed=12)
    plain = scenes_cache.accel("grid.uniform", "teapot-in-stadium")
    skipping = scenes_cache.accel(builder, "teapot-in-stadium")
    walked = plain.trace(rays, traversal="grid.dda", stats=True).stats
    jumped = skipping.trace(rays, traversal="grid.skip", stats=True).stats
    assert jumped["cells"].sum() < 0.8 * walked["cells"].sum()
    assert walked["vertical_steps"].sum() == 0
    climbed = jumped["vertical_steps"]
    assert (climbed.sum() > 0) == (builder == "grid.mipmap")
    assert (climbed <= 15 * jumped["empty_cells"]).all()


def test_irregular_merges_expands_and_validates():
    """Merging lowers the cell count, expansion moves faces, and broken grids are rejected."""
    mesh = reference.icosphere(3)
    accel = rayaccel.build(mesh, "grid.irregular")
    grid = accel.structure
    grid.validate(accel.mesh.triangles())
    stats = accel.info()["build_stats"]
    assert grid.n_cells < stats["leaves"]
    assert stats["cells_per_round"][0] == stats["leaves"]
    assert stats["faces_moved"] > 0
    assert (grid.cell_exit[:, :3] <= grid.cell_box[:, :3]).all()
    assert (grid.cell_exit != grid.cell_box).any()
    plain = rayaccel.build(mesh, "grid.irregular", merge_threshold=0.0, expansion_passes=0)
    assert plain.structure.n_cells == stats["leaves"]
    assert np.array_equal(plain.structure.cell_exit, plain.structure.cell_box)
    rays = reference.mixed_rays(mesh, 500, seed=21)
    for variant in (accel, plain):
        _check(variant, rays, "grid.dda", "irregular")
    # An expanded box over a cell whose triangles its cell does not list.
    counts = np.diff(grid.cell_start)
    c = int(np.argmin(counts))
    whole = grid.cell_exit.copy()
    whole[c, :3] = 0
    whole[c, 3:] = grid.fine_res
    broken = dataclasses.replace(grid, cell_exit=whole)
    with pytest.raises(StructureInvariantError, match="expanded box covers"):
        broken.validate(accel.mesh.triangles())
    moved = grid.cell_of_leaf.copy()
    moved[0] = (moved[0] + 1) % grid.n_cells
    with pytest.raises(StructureInvariantError, match="leaf"):
        dataclasses.replace(grid, cell_of_leaf=moved).validate()
    with pytest.raises(InvalidInputError, match="merge_threshold"):
        rayaccel.build(mesh, "grid.irregular", merge_threshold=1.5)
