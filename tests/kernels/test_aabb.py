"""The robust slab test (Williams et al. 2005; Ize 2013): ``kernels/aabb.py``."""

from __future__ import annotations

import numpy as np
import pytest

from rayaccel.kernels.aabb import culling_pad_py, ray_box_entry, ray_box_entry_py
from rayaccel.kernels.triangle import ray_triangle_py, ray_triangle_setup_py

f32 = np.float32
INF = f32(np.inf)


def entry(lo, hi, o, d, tmin=0.0, tmax=np.inf, fn=ray_box_entry_py):
    """Call the slab test the way traversals do: near/far planes picked by sign(1/d)."""
    with np.errstate(all="ignore"):  # 1/0 = inf and 0*inf = NaN are intended
        inv = [f32(1) / f32(x) for x in d]
        near = [f32(lo[a]) if inv[a] >= 0 else f32(hi[a]) for a in range(3)]
        far = [f32(hi[a]) if inv[a] >= 0 else f32(lo[a]) for a in range(3)]
        return fn(*(f32(x) for x in o), *inv, *near, *far, f32(tmin), f32(tmax))


LO, HI = (0.0, 0.0, 0.0), (1.0, 2.0, 3.0)


def test_hit_from_outside_returns_entry_distance():
    assert entry(LO, HI, (-1, 1, 1), (1, 0, 0)) == f32(1.0)
    assert entry(LO, HI, (0.5, 1, 5), (0, 0, -2)) == f32(1.0)


def test_origin_inside_returns_tmin():
    assert entry(LO, HI, (0.5, 1, 1), (1, 1, 1)) == f32(0.0)
    assert entry(LO, HI, (0.5, 1, 1), (1, 1, 1), tmin=0.25) == f32(0.25)


@pytest.mark.parametrize(
    ("o", "d"),
    [((-1, 1, 1), (-1, 0, 0)),  # pointing away
     ((-1, 3, 1), (1, 0, 0)),  # parallel, outside the y slab
     ((-1, -1, -1), (1, 5, -1)),  # skew
     ((2, 3, 4), (1, 1, 1))],  # behind
)
def test_misses(o, d):
    assert entry(LO, HI, o, d) == INF


def test_interval_culls():
    assert entry(LO, HI, (-1, 1, 1), (1, 0, 0), tmax=0.5) == INF
    assert entry(LO, HI, (-1, 1, 1), (1, 0, 0), tmin=2.5) == INF
    assert entry(LO, HI, (-1, 1, 1), (1, 0, 0), tmax=1.0) == f32(1.0)  # inclusive


@pytest.mark.parametrize("zero", [0.0, -0.0])
def test_axis_parallel_with_signed_zero(zero):
    # Inside the x and y slabs: the infinite slab distances impose no constraint.
    assert entry(LO, HI, (0.5, 1, -1), (zero, zero, 1)) == f32(1.0)
    assert entry(LO, HI, (0.5, 1, 4), (zero, -zero, -1)) == f32(1.0)
    # Outside the x slab: never enters.
    assert entry(LO, HI, (1.5, 1, -1), (zero, zero, 1)) == INF
    assert entry(LO, HI, (-0.5, 1, -1), (zero, zero, 1)) == INF


def test_origin_on_a_slab_plane_with_zero_direction_is_kept():
    # (plane - o) * inf = 0 * inf = NaN: treated as no constraint (conservative).
    assert entry(LO, HI, (0.0, 1, -1), (0.0, 0.0, 1)) == f32(1.0)
    assert entry(LO, HI, (1.0, 1, -1), (-0.0, 0.0, 1)) == f32(1.0)
    assert entry(LO, HI, (1.0, 2.0, -1), (0.0, -0.0, 1)) == f32(1.0)


def test_flat_box_is_hit():
    lo, hi = (0.0, 0.0, 1.0), (1.0, 1.0, 1.0)
    assert entry(lo, hi, (0.5, 0.5, 0), (0, 0, 1)) == f32(1.0)
    assert entry(lo, hi, (0.3, 0.2, 3), (0.1, 0.2, -1)) == f32(2.0)


def test_grazing_edges_and_corners_are_hit():
    # Rays through an edge and a corner of the box, exactly representable.
    assert entry(LO, HI, (-1, 0, 1), (1, 0, 0)) == f32(1.0)
    assert entry(LO, HI, (-1, -2, -3), (1, 2, 3)) == f32(1.0)
    assert entry(LO, HI, (2, 4, 6), (-1, -2, -3)) == f32(1.0)


def _exact_slab(lo, hi, o, d, tmin, tmax):
    """Float64 slab test with exact handling of zero components (None on a miss)."""
    t0, t1 = tmin, tmax
    for a in range(3):
        if d[a] == 0:
            if not lo[a] <= o[a] <= hi[a]:
                return None
            continue
        ta, tb = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return t0 if t0 <= t1 else None


def test_no_false_misses_against_float64():
    """Conservative (Ize 2013): whenever the exact test hits, the float32 test hits."""
    rng = np.random.default_rng(0)
    n_checked = 0
    for _ in range(4000):
        lo = rng.normal(size=3).astype(np.float32)
        hi = lo + rng.exponential(size=3).astype(np.float32) * (rng.random(3) > 0.1)
        o = (rng.normal(size=3) * 4).astype(np.float32)
        # Aim at a corner, an edge point or a face point of the box.
        t = np.where(rng.random(3) < 0.5, lo, hi).astype(np.float64)
        k = rng.integers(0, 3)
        t[k] = lo[k] + rng.random() * (hi[k] - lo[k])
        d = (t - o).astype(np.float32)
        d[rng.random(3) < 0.05] = 0.0
        exact = _exact_slab(lo.astype(np.float64), hi.astype(np.float64), o.astype(np.float64),
                            d.astype(np.float64), 0.0, np.inf)
        got = entry(lo, hi, o, d)
        if exact is not None:
            n_checked += 1
            assert got < INF, f"false miss: lo={lo} hi={hi} o={o} d={d}"
            assert got <= exact * (1 + 1e-5) + 1e-6
    assert n_checked > 1000


def test_jitted_form_matches_python_form():
    rng = np.random.default_rng(1)
    for _ in range(500):
        lo = rng.normal(size=3).astype(np.float32)
        hi = lo + rng.exponential(size=3).astype(np.float32)
        o = (rng.normal(size=3) * 3).astype(np.float32)
        d = rng.normal(size=3).astype(np.float32)
        d[rng.random(3) < 0.2] = 0.0
        a = entry(lo, hi, o, d)
        b = entry(lo, hi, o, d, fn=ray_box_entry)
        assert (a == INF) == (b == INF)
        if a < INF:
            assert np.isclose(a, b, rtol=1e-6, atol=0)


def test_box_never_culls_its_triangle_hit_at_interval_ends():
    """A ray hitting a triangle at t enters the triangle's box with tmax = t or tmin = t.

    The triangle lies in a box face, so the slab distances and the triangle's t are
    rounded along different paths; traversals cull against the widened interval.
    """
    rng = np.random.default_rng(0)
    lost_tmax = lost_tmin = 0
    for _ in range(3000):
        tri = rng.normal(size=(3, 3)).astype(np.float32)
        tri[:, 2] = f32(rng.normal())  # flat in z: the triangle lies in a box face
        o = (rng.normal(size=3) * 4).astype(np.float32)
        d = (rng.dirichlet([1, 1, 1]) @ tri.astype(np.float64) - o).astype(np.float32)
        kx, ky, kz, Sx, Sy, Sz = ray_triangle_setup_py(*d)
        t, _, _ = ray_triangle_py(tri.reshape(1, 9), 0, o[kx], o[ky], o[kz], kx, ky, kz,
                                  Sx, Sy, Sz, f32(0), INF)
        if t == INF:
            continue
        lo, hi = tri.min(axis=0), tri.max(axis=0)
        upper = np.nextafter(t, INF)  # how traversals make tmax inclusive
        pad = culling_pad_py(o[kz], Sz, lo[kz], hi[kz])
        lost_tmax += entry(lo, hi, o, d, 0.0, upper + pad) == INF
        lost_tmin += entry(lo, hi, o, d, t - pad, np.inf) == INF
    assert lost_tmax == 0, f"{lost_tmax} triangle hits at tmax culled by their own box"
    assert lost_tmin == 0, f"{lost_tmin} triangle hits at tmin culled by their own box"
