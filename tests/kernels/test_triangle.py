"""The watertight ray/triangle test (Woop, Benthin, Wald 2013): ``kernels/triangle.py``.

Most cases call the pure-Python ``ray_triangle_py`` on float32 scalars (the readable
form); the jitted form is exercised through the brute-force oracle kernel, which
inlines it exactly as the traversals do.
"""

from __future__ import annotations

import numpy as np
import pytest

import reference
from rayaccel.kernels.brute_force import brute_force_trace
from rayaccel.kernels.triangle import ray_triangle_py, ray_triangle_setup_py
from rayaccel.rays.batch import RayBatch
from rayaccel.scene.mesh import TriangleMesh

f32 = np.float32
INF = f32(np.inf)


def hit_py(tri, o, d, tmin=0.0, tmax=np.inf, row=0):
    """``ray_triangle_py`` on one ray; ``tmax`` is exclusive as in the kernel."""
    tri = np.asarray(tri, dtype=np.float32).reshape(-1, 9)
    o = [f32(x) for x in o]
    kx, ky, kz, Sx, Sy, Sz = ray_triangle_setup_py(*(f32(x) for x in d))
    return ray_triangle_py(tri, row, o[kx], o[ky], o[kz], kx, ky, kz, Sx, Sy, Sz,
                           f32(tmin), f32(tmax))


def hit_jit(tri, o, d, tmin=0.0, tmax=np.inf):
    """The jitted test, through the oracle kernel (inclusive ``tmax``)."""
    tri = np.ascontiguousarray(np.asarray(tri, dtype=np.float32).reshape(-1, 9))
    rays = RayBatch(np.atleast_2d(o), np.atleast_2d(d), tmin, tmax)
    t, prim, u, v = brute_force_trace(tri, rays.origin, rays.direction, rays.tmin, rays.tmax)
    return t[0], prim[0], u[0], v[0]


TRI = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]


def test_setup_picks_dominant_axis_and_keeps_winding():
    for d, kz in (((1, 0.5, 0.2), 0), ((0.1, -3, 2), 1), ((0.1, 0.2, -5), 2)):
        kx, ky, k, Sx, Sy, Sz = ray_triangle_setup_py(*(f32(x) for x in d))
        assert k == kz
        assert {kx, ky, kz} == {0, 1, 2}
        assert Sz == f32(1) / f32(d[kz])
        assert Sx == f32(d[kx]) / f32(d[kz])
        assert Sy == f32(d[ky]) / f32(d[kz])
        if d[kz] < 0:  # swapped to preserve the winding
            assert (kx, ky) == ((kz + 2) % 3, (kz + 1) % 3)
        else:
            assert (kx, ky) == ((kz + 1) % 3, (kz + 2) % 3)
    # Ties between |components| resolve deterministically.
    assert ray_triangle_setup_py(f32(1), f32(1), f32(1))[2] == 0
    assert ray_triangle_setup_py(f32(0), f32(1), f32(1))[2] == 1


def test_centre_hit_distance_and_barycentrics():
    t, u, v = hit_py(TRI, (0.25, 0.25, 2.0), (0, 0, -1))
    assert t == f32(2.0)
    assert np.isclose(u, 0.25)
    assert np.isclose(v, 0.25)
    # Hit point (1-u-v) A + u B + v C.
    p = (1 - u - v) * np.array(TRI[0]) + u * np.array(TRI[1]) + v * np.array(TRI[2])
    assert np.allclose(p, (0.25, 0.25, 0.0))


@pytest.mark.parametrize("scale", [1.0, 0.5, 4.0])
def test_unnormalised_direction_scales_t(scale):
    t, _, _ = hit_py(TRI, (0.2, 0.3, 3.0), (0, 0, -scale))
    assert np.isclose(t, 3.0 / scale, rtol=1e-6)


def test_back_face_is_hit_no_culling():
    front = hit_py(TRI, (0.2, 0.2, 1.0), (0, 0, -1))
    back = hit_py(TRI, (0.2, 0.2, -1.0), (0, 0, 1))
    assert front[0] == back[0] == f32(1.0)
    assert np.isclose(front[1], back[1])
    assert np.isclose(front[2], back[2])


def test_negative_dominant_axis_gives_same_barycentrics():
    a = hit_py(TRI, (0.1, 0.6, 1.0), (0.05, -0.1, -1))
    b = hit_py(TRI, (0.1, 0.6, -1.0), (0.05, -0.1, 1))
    assert np.isfinite(a[0])
    assert np.isfinite(b[0])
    assert np.isclose(a[1], b[1], atol=1e-6)
    assert np.isclose(a[2], b[2], atol=1e-6)


@pytest.mark.parametrize("o", [(1.2, 0.2, 1.0), (-0.01, 0.5, 1.0), (0.6, 0.6, 1.0)])
def test_outside_misses(o):
    assert hit_py(TRI, o, (0, 0, -1))[0] == INF


@pytest.mark.parametrize(
    "o",
    [(0.0, 0.0, 1.0), (1.0, 0.0, 1.0), (0.0, 1.0, 1.0),  # vertices
     (0.5, 0.0, 1.0), (0.0, 0.5, 1.0), (0.5, 0.5, 1.0)],  # edges
)
def test_vertices_and_edges_are_inside(o):
    assert hit_py(TRI, o, (0, 0, -1))[0] == f32(1.0)
    assert hit_jit(TRI, o, (0, 0, -1))[0] == f32(1.0)


@pytest.mark.parametrize(
    "tri",
    [
        pytest.param([[0, 0, 0], [0, 0, 0], [0, 0, 0]], id="point"),
        [[0, 0, 0], [1, 1, 0], [2, 2, 0]],  # collinear
        [[0, 0, 0], [1, 1, 0], [1, 1, 0]],  # repeated vertex
        [[-1, -1, 0], [1, 1, 0], [0, 0, 0]],  # collinear through the ray
    ],
)
def test_zero_area_never_hit(tri):
    for o, d in (((0, 0, 1), (0, 0, -1)), ((0.5, 0.5, 1), (0, 0, -1)),
                 ((0.3, 0.2, 1), (-0.1, 0.2, -1)), ((-1, -1, 0), (1, 1, 0))):
        assert hit_py(tri, o, d)[0] == INF
        assert hit_jit(tri, o, d)[1] == -1


def test_ray_in_the_triangle_plane_misses():
    assert hit_py(TRI, (-1, 0.2, 0), (1, 0, 0))[0] == INF
    assert hit_jit(TRI, (-1, 0.2, 0), (1, 0, 0))[1] == -1


def test_interval_bounds():
    o, d = (0.2, 0.2, 1.0), (0, 0, -1)
    assert hit_py(TRI, o, d, tmin=1.0)[0] == f32(1.0)  # tmin inclusive
    assert hit_py(TRI, o, d, tmin=np.nextafter(f32(1), f32(2)))[0] == INF
    assert hit_py(TRI, o, d, tmax=1.0)[0] == INF  # the leaf test's tmax is exclusive ...
    assert hit_jit(TRI, o, d, tmax=1.0)[0] == f32(1.0)  # ... callers nudge it (inclusive)
    assert hit_jit(TRI, o, d, tmax=np.nextafter(f32(1), f32(0)))[1] == -1
    assert hit_py(TRI, (0.2, 0.2, -1.0), d)[0] == INF  # behind the origin


def test_origin_on_the_triangle_hits_at_zero():
    t, _, _ = hit_py(TRI, (0.2, 0.2, 0.0), (0.3, 0.1, -1))
    assert t == 0.0


def test_matches_float64_reference_away_from_edges():
    rng = np.random.default_rng(0)
    tri = rng.normal(size=(200, 9)).astype(np.float32)
    o = rng.normal(size=(200, 3)) * 3
    target = (tri[:, 0:3] + tri[:, 3:6] + tri[:, 6:9]) / 3 + rng.normal(size=(200, 3)) * 0.3
    rays = RayBatch(o, target - o)
    for r in range(rays.n_rays):
        one = RayBatch(rays.origin[r:r + 1], rays.direction[r:r + 1])
        t64, p64, margin = reference.mt_float64(tri[r:r + 1], one)
        t, _, _ = hit_py(tri[r], rays.origin[r], rays.direction[r])
        if abs(margin[0]) < 1e-4 and np.isfinite(margin[0]):
            continue  # too close to an edge for float32 to agree with float64
        assert np.isfinite(t) == (p64[0] == 0)
        if np.isfinite(t):
            assert np.isclose(t, t64[0], rtol=1e-4)


def test_python_and_jitted_forms_agree_on_random_rays():
    rng = np.random.default_rng(1)
    tri = rng.normal(size=(64, 9)).astype(np.float32)
    rays = RayBatch(rng.normal(size=(64, 3)) * 3, rng.normal(size=(64, 3)))
    ref = reference.python_trace(tri, rays)
    t, prim, _, _ = brute_force_trace(tri, rays.origin, rays.direction, rays.tmin, rays.tmax)
    assert np.array_equal(prim, ref.prim)
    assert np.allclose(t, ref.t, rtol=1e-6)


# Two triangles of an icosphere sharing the edge (1, 3), and a ray through its midpoint
# (o = 2p, d = -p): watertightness requires at least one of them to be hit at t = 1.
CRACK_VERTICES = [
    [-0.7020464539527893, 0.1606220304965973, 0.6937804818153381],
    [-0.7838430404663086, 0.08108629286289215, 0.6156420111656189],
    [-0.7838430404663086, -0.08108629286289215, 0.6156420111656189],
    [-0.7112817168235779, 0.0, 0.7029070258140564],
]
CRACK_FACES = [[0, 1, 3], [2, 3, 1]]
CRACK_O = [-1.4951248168945312, 0.08108629286289215, 1.3185490369796753]
CRACK_D = [0.7475624084472656, -0.040543146431446075, -0.6592745184898376]


def test_shared_edge_python_form_is_watertight():
    mesh = TriangleMesh(CRACK_VERTICES, CRACK_FACES)
    ref = reference.python_trace(reference.tri9(mesh), RayBatch([CRACK_O], [CRACK_D]))
    assert ref.prim[0] >= 0
    assert np.isclose(ref.t[0], 1.0)


def test_shared_edge_jitted_form_is_watertight():
    """Repro of the FMA crack: the jitted test rejects the ray from both triangles."""
    mesh = TriangleMesh(CRACK_VERTICES, CRACK_FACES)
    t, prim, _, _ = hit_jit(reference.tri9(mesh), CRACK_O, CRACK_D)
    assert prim >= 0
    assert np.isclose(t, 1.0)


def test_point_triangle_never_hit_by_jitted_form():
    """Repro: a zero-area triangle (all corners equal) is "hit" far from its point."""
    tri = [[-2, -2, -2], [-1, -0.5, -1], [-1, -0.5, -1], [-1, -0.5, -1], [-2, -2, -2],
           [-2, -2, -0.5]]
    mesh = TriangleMesh(tri, [[1, 2, 3], [0, 1, 5]])
    o, d = [-1.0, -2.0, -0.5], [-1.0, 0.0, -1.5]
    assert hit_py(reference.tri9(mesh), o, d, row=0)[0] == INF
    t, prim, _, _ = hit_jit(reference.tri9(mesh)[:1], o, d)
    assert prim == -1, f"the point triangle was hit at t={t}"

