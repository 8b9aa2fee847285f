import numpy as np
import pytest

from rayaccel.errors import InvalidInputError
from rayaccel.rays import (
    SHADOW_TMAX,
    HitBatch,
    RayBatch,
    ambient_occlusion_rays,
    cosine_hemisphere,
    diffuse_rays,
    offset_origin,
    shadow_rays,
)

# Triangle normals: up, down, tilted, unnormalised, and one degenerate (zero)
NORMALS = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 1], [0, 3, 0], [0, 0, 0]], dtype=np.float32)


def _scene(n=2000, seed=1):
    """Rays from a random spread of origins, hitting at random t on random triangles."""
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-5, 5, (n, 3))
    direction = rng.normal(size=(n, 3))
    t = rng.uniform(0.5, 3.0, n)
    prim = rng.integers(-1, len(NORMALS), n)
    rays = RayBatch(origin, direction)
    hits = HitBatch(
        t=np.where(prim >= 0, t, np.inf).astype(np.float32),
        prim=prim.astype(np.int32),
        u=np.zeros(n, np.float32),
        v=np.zeros(n, np.float32),
    )
    return rays, hits


def _facing_normals(rays, hits, source):
    normal = NORMALS[hits.prim[source]].astype(np.float64)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    incoming = rays.direction[source].astype(np.float64)
    flip = np.einsum("ij,ij->i", normal, incoming) > 0
    normal[flip] *= -1
    return normal


def _points(rays, hits, source):
    return rays.origin[source].astype(np.float64) + (
        hits.t[source].astype(np.float64)[:, None] * rays.direction[source]
    )


def test_diffuse_skips_misses_and_degenerate_triangles():
    rays, hits = _scene()
    new, source = diffuse_rays(rays, hits, NORMALS)
    expected = np.flatnonzero((hits.prim >= 0) & (hits.prim != 4))
    np.testing.assert_array_equal(source, expected)
    assert source.dtype == np.int32
    assert new.n_rays == len(expected)
    assert new.origin.dtype == np.float32
    assert new.direction.dtype == np.float32
    assert (new.tmin == 0).all()
    assert np.isposinf(new.tmax).all()


def test_diffuse_directions_in_hemisphere_of_flipped_normal():
    rays, hits = _scene()
    new, source = diffuse_rays(rays, hits, NORMALS, seed=3)
    normal = _facing_normals(rays, hits, source)
    np.testing.assert_allclose(np.linalg.norm(new.direction, axis=1), 1.0, atol=1e-6)
    cosine = np.einsum("ij,ij->i", normal, new.direction)
    assert (cosine >= -1e-6).all()
    # The flip happened: the bounce goes back against the incoming ray's side
    incoming = rays.direction[source].astype(np.float64)
    assert (np.einsum("ij,ij->i", normal, incoming) <= 0).all()


def test_diffuse_origin_is_offset_along_the_normal():
    rays, hits = _scene()
    epsilon = 1e-3
    new, source = diffuse_rays(rays, hits, NORMALS, epsilon=epsilon)
    points = _points(rays, hits, source)
    normal = _facing_normals(rays, hits, source)
    scale = np.maximum.reduce(
        [
            np.ones(len(source)),
            np.abs(points).max(axis=1),
            np.abs(rays.origin[source]).max(axis=1),
            hits.t[source] * np.abs(rays.direction[source]).max(axis=1),
        ]
    )
    np.testing.assert_allclose(new.origin, points + epsilon * scale[:, None] * normal, atol=1e-5)
    height = np.einsum("ij,ij->i", new.origin - points, normal)
    assert (height > 0).all()


def test_offset_clears_the_surface_far_from_the_origin():
    # Grazing rays from far away onto the plane z = 0, with float32 hit distances
    rng = np.random.default_rng(7)
    n = 5000
    origin = np.column_stack([rng.uniform(-1e3, 1e3, (n, 2)), rng.uniform(1, 1e4, n)])
    target = np.column_stack([rng.uniform(-1e3, 1e3, (n, 2)), np.zeros(n)])
    direction = target - origin
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    rays = RayBatch(origin, direction)
    o32, d32 = rays.origin.astype(np.float64), rays.direction.astype(np.float64)
    t = (-o32[:, 2] / d32[:, 2]).astype(np.float32)
    hits = HitBatch(t, np.zeros(n, np.int32), np.zeros(n, np.float32), np.zeros(n, np.float32))
    plane = np.array([[0, 0, 1]], np.float32)
    for new, _ in (
        diffuse_rays(rays, hits, plane),
        ambient_occlusion_rays(rays, hits, plane, radius=1.0),
        shadow_rays(rays, hits, plane, (0.0, 0.0, 50.0)),
    ):
        assert (new.origin[:, 2] > 0).all()
        assert (new.direction[:, 2] >= 0).all()


def test_cosine_hemisphere_distribution():
    rng = np.random.default_rng(0)
    n = 400_000
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    u = rng.random((n, 2))
    direction = cosine_hemisphere(normal, u[:, 0], u[:, 1])
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0, atol=1e-12)
    cosine = np.einsum("ij,ij->i", normal, direction)
    assert (cosine >= 0).all()
    # pdf cos(θ)/π: E[cos θ] = 2/3, E[cos² θ] = 1/2 and P(cos θ <= c) = c²
    assert abs(cosine.mean() - 2 / 3) < 2e-3
    assert abs((cosine**2).mean() - 1 / 2) < 2e-3
    for c in (0.25, 0.5, 0.75, 0.9):
        assert abs((cosine <= c).mean() - c * c) < 3e-3


def test_cosine_hemisphere_at_special_normals():
    u1, u2 = np.meshgrid(np.linspace(0, 0.999, 50), np.linspace(0, 0.999, 50))
    u1, u2 = u1.ravel(), u2.ravel()
    for n in ([0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [0.6, 0.8, -0.0]):
        normal = np.tile(np.array(n, float), (len(u1), 1))
        direction = cosine_hemisphere(normal, u1, u2)
        assert np.isfinite(direction).all()
        np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0, atol=1e-12)
        assert (direction @ np.array(n, float) >= -1e-12).all()
    centre = cosine_hemisphere(np.array([[0.0, 1.0, 0.0]]), np.array([0.5]), np.array([0.5]))
    np.testing.assert_allclose(centre, [[0.0, 1.0, 0.0]])


def test_diffuse_mean_cosine_is_two_thirds():
    n = 200_000
    rays = RayBatch(np.zeros((n, 3)), np.tile([0.0, 0.0, -1.0], (n, 1)))
    hits = HitBatch(
        np.ones(n, np.float32),
        np.zeros(n, np.int32),
        np.zeros(n, np.float32),
        np.zeros(n, np.float32),
    )
    new, _ = diffuse_rays(rays, hits, np.array([[0.0, 0.0, 1.0]]), seed=11)
    assert abs(new.direction[:, 2].mean() - 2 / 3) < 3e-3
    assert abs(new.direction[:, 0].mean()) < 3e-3
    assert abs(new.direction[:, 1].mean()) < 3e-3


@pytest.mark.parametrize(
    "generate",
    [
        lambda r, h, seed: diffuse_rays(r, h, NORMALS, seed=seed),
        lambda r, h, seed: ambient_occlusion_rays(r, h, NORMALS, n_per_hit=3, seed=seed),
        lambda r, h, seed: shadow_rays(
            r,
            h,
            NORMALS,
            [[[0, 9, 0], [1, 9, 0], [0, 9, 1]], [[0, 9, 0], [4, 9, 4], [0, 9, 5]]],
            seed=seed,
        ),
    ],
)
def test_deterministic_by_seed(generate):
    rays, hits = _scene()
    first, source_a = generate(rays, hits, 5)
    second, source_b = generate(rays, hits, 5)
    other, _ = generate(rays, hits, 6)
    np.testing.assert_array_equal(source_a, source_b)
    for name in ("origin", "direction", "tmin", "tmax"):
        assert getattr(first, name).tobytes() == getattr(second, name).tobytes()
    assert first.direction.tobytes() != other.direction.tobytes()


def test_shadow_rays_to_point_light_reach_it_at_t_one():
    rays, hits = _scene()
    light = np.array([2.0, 30.0, -4.0])
    new, source = shadow_rays(rays, hits, NORMALS, light)
    np.testing.assert_array_equal(source, np.flatnonzero((hits.prim >= 0) & (hits.prim != 4)))
    end = new.origin.astype(np.float64) + new.direction
    np.testing.assert_allclose(end, np.tile(light, (len(source), 1)), atol=1e-5)
    assert (new.tmin == 0).all()
    np.testing.assert_array_equal(new.tmax, np.float32(SHADOW_TMAX))
    assert (new.tmax < 1).all()
    # The origin sits on the light's side of the surface, just off the hit point
    points = _points(rays, hits, source)
    normal = _facing_normals(rays, hits, source)
    side = np.sign(np.einsum("ij,ij->i", normal, light - points))
    height = np.einsum("ij,ij->i", new.origin - points, normal)
    assert (np.sign(height) == side).all()
    assert (np.abs(height) < 1e-2).all()


def test_shadow_rays_sample_area_lights_by_area():
    n = 40_000
    rays = RayBatch(np.zeros((n, 3)), np.tile([0.0, 0.0, -1.0], (n, 1)))
    hits = HitBatch(
        np.ones(n, np.float32),
        np.zeros(n, np.int32),
        np.zeros(n, np.float32),
        np.zeros(n, np.float32),
    )
    # Two disjoint triangles in the plane y = 10 with areas 1 and 3, plus a degenerate one
    light = np.array(
        [
            [[0, 10, 0], [2, 10, 0], [0, 10, 1]],
            [[5, 10, 5], [5, 10, 5], [9, 10, 9]],
            [[10, 10, 0], [13, 10, 0], [10, 10, 2]],
        ],
        dtype=np.float32,
    )
    new, _ = shadow_rays(rays, hits, np.array([[0.0, 0.0, 1.0]]), light, seed=2)
    end = new.origin.astype(np.float64) + new.direction
    np.testing.assert_allclose(end[:, 1], 10.0, atol=1e-5)
    in_first = end[:, 0] < 4
    assert abs(in_first.mean() - 0.25) < 0.01
    # Inside each triangle: x/2 + z <= 1 and (x - 10)/3 + z/2 <= 1
    first, second = end[in_first], end[~in_first]
    assert (first[:, 0] >= -1e-5).all()
    assert (first[:, 2] >= -1e-5).all()
    assert (first[:, 0] / 2 + first[:, 2] <= 1 + 1e-5).all()
    assert (second[:, 0] >= 10 - 1e-5).all()
    assert (second[:, 2] >= -1e-5).all()
    assert ((second[:, 0] - 10) / 3 + second[:, 2] / 2 <= 1 + 1e-5).all()
    # Uniform inside: mean of a uniform triangle sample is its centroid
    np.testing.assert_allclose(first.mean(axis=0), [2 / 3, 10, 1 / 3], atol=0.02)
    np.testing.assert_allclose(second.mean(axis=0), [11, 10, 2 / 3], atol=0.02)


def test_ambient_occlusion_rays():
    rays, hits = _scene()
    new, source = ambient_occlusion_rays(rays, hits, NORMALS, n_per_hit=4, radius=0.5, seed=9)
    hit = np.flatnonzero((hits.prim >= 0) & (hits.prim != 4))
    np.testing.assert_array_equal(source, np.repeat(hit, 4))
    assert source.dtype == np.int32
    assert new.n_rays == 4 * len(hit)
    assert (new.tmin == 0).all()
    np.testing.assert_array_equal(new.tmax, np.float32(0.5))
    np.testing.assert_allclose(np.linalg.norm(new.direction, axis=1), 1.0, atol=1e-6)
    normal = _facing_normals(rays, hits, source)
    assert (np.einsum("ij,ij->i", normal, new.direction) >= -1e-6).all()
    # The four rays of one hit share an origin but not a direction
    origins = new.origin.reshape(-1, 4, 3)
    assert (origins == origins[:, :1]).all()
    assert len(np.unique(new.direction[:4], axis=0)) == 4


def test_ambient_occlusion_default_radius():
    rays, hits = _scene()
    new, source = ambient_occlusion_rays(rays, hits, NORMALS)
    points = _points(rays, hits, source)
    expected = 0.1 * np.linalg.norm(points.max(axis=0) - points.min(axis=0))
    np.testing.assert_allclose(new.tmax, expected, rtol=1e-5)


def test_no_hits_gives_empty_batches():
    rays, _ = _scene(n=10)
    hits = HitBatch.empty(10)
    for new, source in (
        diffuse_rays(rays, hits, NORMALS),
        shadow_rays(rays, hits, NORMALS, (0, 0, 0)),
        shadow_rays(rays, hits, NORMALS, [[[0, 0, 0], [1, 0, 0], [0, 1, 0]]]),
        ambient_occlusion_rays(rays, hits, NORMALS, n_per_hit=2),
    ):
        assert new.n_rays == 0
        assert new.origin.shape == (0, 3)
        assert source.shape == (0,)
        assert source.dtype == np.int32


def test_offset_origin_helper():
    points = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    normals = np.array([[0.0, 0.0, 2.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    moved = offset_origin(points, normals, epsilon=1e-3)
    assert moved.dtype == np.float32
    np.testing.assert_allclose(moved, [[0, 0, 1e-3], [100, 0.1, 0], [1, 1, 1]], rtol=1e-6)
    directions = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    flipped = offset_origin(points, normals, directions, epsilon=1e-3, scale=2.0)
    np.testing.assert_allclose(flipped, [[0, 0, -2e-3], [100, 2e-3, 0], [1, 1, 1]], rtol=1e-6)
    with pytest.raises(InvalidInputError):
        offset_origin(points, normals[:2])
    with pytest.raises(InvalidInputError):
        offset_origin(points[:, :2], normals[:, :2])
    with pytest.raises(InvalidInputError):
        offset_origin(points, normals, directions[:1])
    with pytest.raises(InvalidInputError):
        offset_origin(points, normals, epsilon=-1.0)


def _bad_calls():
    rays, hits = _scene(n=20)
    short = HitBatch.empty(19)
    out_of_range = HitBatch(hits.t, np.full(20, 7, np.int32), hits.u, hits.v)
    return [
        lambda: diffuse_rays(rays, short, NORMALS),
        lambda: diffuse_rays(rays, out_of_range, NORMALS),
        lambda: diffuse_rays(rays, hits, NORMALS[:, :2]),
        lambda: diffuse_rays(rays, hits, "normals"),
        lambda: diffuse_rays(rays.origin, hits, NORMALS),
        lambda: diffuse_rays(rays, hits.t, NORMALS),
        lambda: diffuse_rays(rays, hits, NORMALS, epsilon=np.nan),
        lambda: diffuse_rays(rays, hits, NORMALS, seed=-1),
        lambda: shadow_rays(rays, hits, NORMALS, (0, 0)),
        lambda: shadow_rays(rays, hits, NORMALS, np.zeros((2, 3))),
        lambda: shadow_rays(rays, hits, NORMALS, np.zeros((0, 3, 3))),
        lambda: shadow_rays(rays, hits, NORMALS, np.zeros((2, 3, 3))),
        lambda: shadow_rays(rays, hits, NORMALS, (0, np.inf, 0)),
        lambda: ambient_occlusion_rays(rays, hits, NORMALS, n_per_hit=0),
        lambda: ambient_occlusion_rays(rays, hits, NORMALS, n_per_hit=2.0),
        lambda: ambient_occlusion_rays(rays, hits, NORMALS, radius=0.0),
        lambda: ambient_occlusion_rays(rays, hits, NORMALS, radius="far"),
    ]


@pytest.mark.parametrize("index", range(len(_bad_calls())))
def test_rejects_bad_input(index):
    with pytest.raises(InvalidInputError):
        _bad_calls()[index]()
