"""``bvh2.packet``: the packet box test lane by lane, mixed packets, and the default's choice."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel._jit import cpu_kernel
from rayaccel.bench.raysets import standard_raysets
from rayaccel.kernels import aabb_packet
from rayaccel.kernels.aabb import ray_box_entry
from rayaccel.kernels.ray_packet import packet_setup
from rayaccel.kernels.triangle import ray_triangle, ray_triangle_setup
from rayaccel.kernels.triangle_packet import (
    ROWS,
    SHEAR,
    SHEARED_ORIGIN,
    T_HIT,
    T_LO,
    U,
    V,
    packet_triangle,
)
from rayaccel.rays.batch import RayBatch
from rayaccel.rays.coherence import packet_coherence
from rayaccel.trace.ray_setup import ray_prologue

PACKET = aabb_packet.PACKET
_OUT = 8


@cpu_kernel()
def _both_tests(rows, origin, inv, t_lo, t_hi, lanes, packet_t, packet_mask, scalar_t):
    """Each packet of rays (one octant) against every box: the packet test and the scalar one."""
    for p in range(origin.shape[0] // PACKET):
        first = p * PACKET
        for lane in range(PACKET):
            r = first + lane
            for a in range(3):
                lanes[a, lane] = origin[r, a]
                lanes[3 + a, lane] = inv[r, a]
            lanes[aabb_packet.LO_ROW, lane] = t_lo[r]
            lanes[aabb_packet.HI_ROW, lane] = t_hi[r]
        nx = 0 if inv[first, 0] >= 0 else 1
        ny = 2 if inv[first, 1] >= 0 else 3
        nz = 4 if inv[first, 2] >= 0 else 5
        fx, fy, fz = 1 - nx, 5 - ny, 9 - nz
        for w in range(rows.shape[0]):
            packet_mask[p, w] = aabb_packet.packet_slab_test(
                rows, w, nx, fx, ny, fy, nz, fz, lanes, _OUT
            )
            for lane in range(PACKET):
                r = first + lane
                packet_t[r, w] = lanes[_OUT, lane]
                scalar_t[r, w] = ray_box_entry(
                    origin[r, 0], origin[r, 1], origin[r, 2], inv[r, 0], inv[r, 1], inv[r, 2],
                    rows[w, nx], rows[w, ny], rows[w, nz], rows[w, fx], rows[w, fy], rows[w, fz],
                    t_lo[r], t_hi[r],
                )  # fmt: skip


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_packet_slab_test_matches_the_scalar_one_lane_by_lane(dtype):
    rng = np.random.default_rng(1)
    n_rows, n_packets = 64, 40
    lo = rng.uniform(-2, 1, (n_rows, 3)).astype(np.float32)
    hi = (lo + rng.uniform(0, 2, lo.shape)).astype(np.float32)
    hi[::5, 0] = lo[::5, 0]  # flat boxes
    rows = np.zeros((n_rows, 6), np.float32)
    rows[:, 0::2] = lo
    rows[:, 1::2] = hi
    n = n_packets * PACKET
    origin = rng.uniform(-3, 3, (n, 3)).astype(dtype)
    # Each packet's rays share their direction signs (an octant), as the traversal's do.
    signs = np.repeat(rng.choice([-1.0, 1.0], (n_packets, 3)), PACKET, axis=0)
    direction = (np.abs(rng.normal(size=(n, 3))) * signs).astype(dtype)
    direction[::4, 0] = 0.0  # +0: inv = +inf, the packet's sign
    direction[1::8, 1] = np.where(signs[1::8, 1] < 0, -0.0, 0.0)
    origin[::9, 0] = lo[0, 0]  # origins in a slab plane (0 * inf = NaN)
    with np.errstate(divide="ignore"):
        inv = (dtype(1.0) / direction).astype(dtype)
    t_lo = rng.uniform(0, 0.5, n).astype(dtype)
    t_hi = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0.5, 5, n)).astype(dtype)
    t_hi[::7] = -np.inf  # retired lanes never hit
    lanes = np.zeros((_OUT + 1, PACKET), dtype)
    packet_t = np.empty((n, n_rows), dtype)
    scalar_t = np.empty_like(packet_t)
    mask = np.empty((n_packets, n_rows), np.int32)
    _both_tests(rows, origin, inv, t_lo, t_hi, lanes, packet_t, mask, scalar_t)
    assert np.array_equal(packet_t, scalar_t)
    bits = (mask[:, None, :] >> np.arange(PACKET)[None, :, None]) & 1
    assert np.array_equal(bits.reshape(n, n_rows) == 1, packet_t < np.inf)
    assert not (packet_t[::7] < np.inf).any()
    assert 200 < (packet_t < np.inf).sum() < packet_t.size // 2


@cpu_kernel()
def _row_ops(lanes, row, bound_row, source, target):
    aabb_packet.copy_lane_row(lanes, source, target)
    return aabb_packet.lanes_at_most(lanes, row, bound_row)


def test_lane_row_compare_and_copy():
    lanes = np.zeros((4, PACKET), np.float32)
    lanes[0] = np.arange(PACKET)
    lanes[1] = 7.0
    lanes[1, 3] = np.nan  # unordered: not "at most"
    mask = _row_ops(lanes, 0, 1, 0, 2)
    assert mask == 0b11110111
    assert np.array_equal(lanes[2], lanes[0])
    # A missed box (inf) is not "at most" a ray with no hit yet (inf bound).
    lanes[0, 1] = np.inf
    lanes[1, 1] = np.inf
    lanes[1, 9] = np.inf
    assert _row_ops(lanes, 0, 1, 0, 2) == 0b1000000000 | 0b11110101


def _mixed_packets(mesh: rayaccel.TriangleMesh, n: int, seed: int) -> RayBatch:
    """Rays from inside the scene box; every packet mixes octants, lengths and a degenerate ray."""
    rng = np.random.default_rng(seed)
    lo, hi = mesh.bounds()
    origin = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    direction = rng.normal(size=(n, 3)).astype(np.float32)
    direction[5::PACKET] = 0.0  # a degenerate ray in every packet
    tmax = np.where(rng.random(n) < 0.3, rng.uniform(0.01, 1.0, n), np.inf).astype(np.float32)
    return RayBatch(origin, direction, 0.0, tmax)


@pytest.mark.parametrize("width", [8, 2])
@pytest.mark.parametrize("scene", ["cornell-box", "teapot"])
def test_mixed_octant_packets_match_the_oracle(scene, width):
    """Packets whose rays go every way traverse octant by octant and lose nothing."""
    mesh = rayaccel.scenes.get(scene)
    accel = rayaccel.build(mesh)
    rays = _mixed_packets(mesh, 50 * PACKET + 5, seed=3)  # a partial last packet
    oracle = reference.oracle(mesh, rays)
    tri = reference.tri9(mesh)
    closest = accel.trace(rays, traversal="bvh2.packet", width=width)
    reference.assert_closest_matches(tri, rays, closest, oracle, "bvh2.packet")
    occluded = accel.trace(rays, traversal="bvh2.packet", query="any", width=width)
    reference.assert_any_matches(tri, rays, occluded, oracle, "bvh2.packet")


def test_packet_rows_of_either_width_give_the_same_closest_hits():
    """Camera rays through the 8-wide and the binary rows: the same ``t`` as ``bvh2.stack``."""
    mesh = rayaccel.scenes.get("teapot")
    accel = rayaccel.build(mesh)
    primary = standard_raysets(mesh, "teapot", kinds=["primary"], width=64, height=64)
    rays = primary["primary"].rays
    stack = accel.trace(rays, traversal="bvh2.stack")
    for width in (8, 2):
        packet = accel.trace(rays, traversal="bvh2.packet", width=width, stats=True)
        assert np.array_equal(packet.t, stack.t)
        assert packet.hit.sum() > rays.n_rays // 8
        assert packet.stats["box_tests"].sum() > 0
    # The 8-wide rows take a third of the binary rows' steps.
    steps = {w: accel.trace(rays, traversal="bvh2.packet", width=w, stats=True).stats["steps"]
             for w in (8, 2)}  # fmt: skip
    assert steps[8].mean() < 0.6 * steps[2].mean()
    with pytest.raises(rayaccel.InvalidInputError, match="width"):
        accel.trace(rays, traversal="bvh2.packet", width=4)


def test_default_query_takes_packets_for_coherent_batches_only():
    mesh = rayaccel.scenes.get("cornell-box")
    accel = rayaccel.build(mesh)
    sets = standard_raysets(mesh, "cornell-box", width=256, height=256, accel=accel)
    primary, diffuse = sets["primary"].rays, sets["diffuse"].rays
    assert accel.query_traversal(primary) == "bvh2.packet"
    assert accel.query_traversal(diffuse) == "bvh2.wide"
    assert accel.query_traversal(primary.subset(np.arange(10))) == "bvh2.wide"  # < 1 packet
    for rays in (primary, diffuse):
        default = accel.trace(rays)
        chosen = accel.trace(rays, traversal=accel.query_traversal(rays))
        reference.assert_hits_identical(default, chosen, "default")
    # Options belong to the single-ray traversal: with them, no choice is made.
    assert registry.query_traversal("bvh2") == "bvh2.wide"
    narrow = accel.trace(primary, width=4)
    reference.assert_hits_identical(narrow, accel.trace(primary, traversal="bvh2.wide", width=4))


def test_coherence_of_batches():
    mesh = rayaccel.scenes.get("teapot")
    accel = rayaccel.build(mesh)
    sets = standard_raysets(mesh, "teapot", width=128, height=128, accel=accel)
    lo, hi = mesh.bounds()
    diagonal = float(np.linalg.norm(hi - lo))
    primary = sets["primary"].rays
    assert packet_coherence(primary, diagonal) > 0.9
    assert packet_coherence(sets["diffuse"].rays, diagonal) < 0.1
    shuffled = primary.subset(np.random.default_rng(0).permutation(primary.n_rays))
    assert packet_coherence(shuffled, diagonal) < 0.1
    nan = RayBatch(primary.origin, np.full_like(primary.direction, np.nan), 0.0, np.inf)
    assert packet_coherence(nan, diagonal) == 0.0
    assert packet_coherence(primary.subset(np.arange(PACKET - 1)), diagonal) == 0.0


@cpu_kernel()
def _triangle_tests(tri, origin, direction, t_lo, t_hit, lanes, packet_out, scalar_out):
    """Every triangle against each packet: the packet test and the scalar one, lane by lane."""
    for p in range(origin.shape[0] // PACKET):
        first = p * PACKET
        kx, ky, kz, _, _, _ = ray_triangle_setup(
            direction[first, 0], direction[first, 1], direction[first, 2]
        )
        for row in range(tri.shape[0]):
            for lane in range(PACKET):
                r = first + lane
                _, _, _, Sx, Sy, Sz = ray_triangle_setup(
                    direction[r, 0], direction[r, 1], direction[r, 2]
                )
                lanes[T_LO, lane] = t_lo[r]
                lanes[T_HIT, lane] = t_hit[r]
                lanes[SHEAR, lane] = Sx
                lanes[SHEAR + 1, lane] = Sy
                lanes[SHEAR + 2, lane] = Sz
                lanes[SHEARED_ORIGIN, lane] = origin[r, kx]
                lanes[SHEARED_ORIGIN + 1, lane] = origin[r, ky]
                lanes[SHEARED_ORIGIN + 2, lane] = origin[r, kz]
                lanes[U, lane] = -1.0
                lanes[V, lane] = -1.0
                t, u, v = ray_triangle(
                    tri, row, origin[r, kx], origin[r, ky], origin[r, kz], kx, ky, kz,
                    Sx, Sy, Sz, t_lo[r], t_hit[r],
                )  # fmt: skip
                scalar_out[r, row, 0] = t if t < t_hit[r] else t_hit[r]
                scalar_out[r, row, 1] = u if t < t_hit[r] else -1.0
                scalar_out[r, row, 2] = v if t < t_hit[r] else -1.0
            mask = packet_triangle(tri, row, kx, ky, kz, lanes, 0, 0xAAAA | 0x5555)
            for lane in range(PACKET):
                r = first + lane
                packet_out[r, row, 0] = lanes[T_HIT, lane]
                packet_out[r, row, 1] = lanes[U, lane]
                packet_out[r, row, 2] = lanes[V, lane]
                packet_out[r, row, 3] = (mask >> lane) & 1


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_packet_triangle_test_matches_the_scalar_one_lane_by_lane(dtype):
    """Same ``t, u, v`` bit for bit, including edges shared by two triangles and misses."""
    rng = np.random.default_rng(2)
    n_packets = 24
    grid = rng.integers(-4, 5, (40, 3, 3)).astype(np.float32) / 4  # coarse: exact edge cases
    tri = np.concatenate([grid, rng.normal(size=(40, 3, 3)).astype(np.float32)])
    tri[5, 2] = tri[5, 0]  # degenerate
    rows = tri.reshape(-1, 9).astype(dtype)
    n = n_packets * PACKET
    # Rays of a packet share their shear axes: a common dominant axis and its sign.
    dominant = np.repeat(rng.integers(0, 3, n_packets), PACKET)
    direction = rng.uniform(-0.5, 0.5, (n, 3))
    direction[np.arange(n), dominant] = np.repeat(rng.choice([-1.0, 1.0], n_packets), PACKET)
    direction = direction.astype(dtype)
    origin = (rng.integers(-8, 9, (n, 3)) / 4 - 3 * direction).astype(dtype)
    t_lo = np.where(rng.random(n) < 0.2, 2.5, 0.0).astype(dtype)
    t_hit = np.where(rng.random(n) < 0.3, 3.5, np.inf).astype(dtype)
    lanes = np.zeros((ROWS, PACKET), dtype)
    packet_out = np.empty((n, rows.shape[0], 4), dtype)
    scalar_out = np.empty((n, rows.shape[0], 3), dtype)
    _triangle_tests(rows, origin, direction, t_lo, t_hit, lanes, packet_out, scalar_out)
    assert np.array_equal(packet_out[..., :3], scalar_out)
    hit = packet_out[..., 3] == 1
    assert np.array_equal(hit, scalar_out[..., 1] >= 0)
    assert 300 < hit.sum() < hit.size // 2


@cpu_kernel()
def _setups(origin, direction, tmin, tmax, root_box, lanes, axes, packet_out, scalar_out):
    """Each packet's constants from the vector set-up and from the scalar prologue."""
    n = origin.shape[0]
    for p in range((n + PACKET - 1) // PACKET):
        first = p * PACKET
        valid_bits = packet_setup(
            origin, direction, tmin, tmax, first, n, root_box, lanes, 8, 9, axes
        )
        for lane in range(min(PACKET, n - first)):
            r = first + lane
            (
                valid, ox, oy, oz, ix, iy, iz, nx, ny, nz, _fx, _fy, _fz,
                kx, ky, kz, Sx, Sy, Sz, okx, oky, okz, t_lo, t_hit, pad,
            ) = ray_prologue(origin, direction, tmin, tmax, r, root_box)  # fmt: skip
            scalar = (ox, oy, oz, ix, iy, iz, pad, t_lo, t_hit, Sx, Sy, Sz, okx, oky, okz)
            vector = (
                lanes[0, lane], lanes[1, lane], lanes[2, lane], lanes[3, lane],
                lanes[4, lane], lanes[5, lane], lanes[8, lane], lanes[9 + T_LO, lane],
                lanes[9 + T_HIT, lane], lanes[9 + SHEAR, lane], lanes[9 + SHEAR + 1, lane],
                lanes[9 + SHEAR + 2, lane], lanes[9 + SHEARED_ORIGIN, lane],
                lanes[9 + SHEARED_ORIGIN + 1, lane], lanes[9 + SHEARED_ORIGIN + 2, lane],
            )  # fmt: skip
            for k in range(15):
                scalar_out[r, k] = scalar[k]
                packet_out[r, k] = vector[k]
            octant = nx + (ny - 2) * 2 + (nz - 4) * 4
            scalar_out[r, 15] = kx + 4 * ky + 16 * kz + 64 * octant + 512 * valid
            packet_out[r, 15] = (
                axes[0, lane] + 4 * axes[1, lane] + 16 * axes[2, lane] + 64 * axes[3, lane]
                + 512 * ((valid_bits >> lane) & 1)
            )  # fmt: skip


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_packet_setup_matches_the_scalar_prologue_lane_by_lane(dtype):
    """Reciprocals, shear, pad, interval and validity bit for bit, degenerate rays included."""
    rng = np.random.default_rng(4)
    n = 20 * PACKET + 7  # a partial last packet
    origin = rng.uniform(-3, 3, (n, 3)).astype(dtype)
    direction = rng.normal(size=(n, 3)).astype(dtype)
    direction[::5, 0] = 0.0
    direction[1::7, 2] = -0.0
    direction[2::11] = 0.0  # zero direction: invalid
    direction[3::13, 1] = np.nan
    origin[4::17, 2] = np.inf
    direction[6::9, 1] = direction[6::9, 0]  # |dx| == |dy|: ties in the dominant axis
    tmin = rng.uniform(0, 1, n).astype(dtype)
    tmax = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(0, 5, n)).astype(dtype)
    tmax[5::19] = 0.0
    root_box = np.array([-2, 2, -1, 3, -4, 1], np.float32)
    lanes = np.zeros((9 + ROWS, PACKET), dtype)
    axes = np.zeros((4, PACKET), np.int64)
    packet_out = np.zeros((n, 16), dtype)
    scalar_out = np.zeros((n, 16), dtype)
    with np.errstate(all="ignore"):
        _setups(origin, direction, tmin, tmax, root_box, lanes, axes, packet_out, scalar_out)
    valid = scalar_out[:, 15] >= 512
    assert 0.5 * n < valid.sum() < n
    assert np.array_equal(packet_out[:, 15], scalar_out[:, 15])
    # The constants of valid rays, bit for bit (invalid rays' are never read).
    bits = packet_out[valid, :15].view(np.uint8), scalar_out[valid, :15].view(np.uint8)
    assert np.array_equal(*bits)
