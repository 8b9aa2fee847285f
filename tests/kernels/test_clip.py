"""Triangle clipping (Stich et al. 2009 §4.4; Sutherland & Hodgman 1974): ``kernels/clip.py``."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
from hypothesis import assume, given
from hypothesis import strategies as st

from rayaccel.kernels.clip import (
    clip_triangle_box,
    clip_triangle_box_py,
    polygon_area,
    polygon_bounds,
    split_triangle_bounds,
    split_triangle_bounds_py,
)

coord = st.floats(-100, 100, allow_nan=False, width=32)
triangle = st.lists(coord, min_size=9, max_size=9).map(
    lambda v: np.array(v, dtype=np.float32).reshape(1, 3, 3)
)


def clip(tri, lo, hi, min_vertices=1):
    poly = np.empty((32, 3))
    scratch = np.empty((32, 3))
    m = clip_triangle_box(tri, 0, np.asarray(lo, np.float32), np.asarray(hi, np.float32),
                          poly, scratch, min_vertices)
    return poly[:m], m


def exact_clip(tri, lo, hi, min_vertices=1):
    """The same Python code on Fractions: an exact clip."""
    to_q = np.vectorize(Fraction, otypes=[object])
    poly = np.empty((32, 3), dtype=object)
    scratch = np.empty((32, 3), dtype=object)
    m = clip_triangle_box_py(to_q(np.asarray(tri, np.float64)), 0,
                             to_q(np.asarray(lo, np.float64)), to_q(np.asarray(hi, np.float64)),
                             poly, scratch, min_vertices)
    return poly[:m], m


def area(tri):
    t = tri[0].astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0]))


@given(triangle)
def test_box_around_the_triangle_keeps_it_whole(tri):
    lo, hi = tri[0].min(axis=0), tri[0].max(axis=0)
    poly, m = clip(tri, lo, hi)
    assert m == 3
    assert np.array_equal(poly, tri[0].astype(np.float64))


@given(triangle, st.integers(0, 2), st.floats(0.05, 0.95))
def test_halves_split_the_area(tri, axis, frac):
    """Clipping to the two halves of the bounding box conserves the triangle's area."""
    lo, hi = tri[0].min(axis=0), tri[0].max(axis=0)
    assume(hi[axis] > lo[axis])  # else the triangle lies in the plane and is in both halves
    pos = np.float32(lo[axis] + frac * (hi[axis] - lo[axis]))
    hi_left, lo_right = hi.copy(), lo.copy()
    hi_left[axis] = pos
    lo_right[axis] = pos
    poly_l, m_l = clip(tri, lo, hi_left)
    poly_r, m_r = clip(tri, lo_right, hi)
    total = polygon_area(poly_l, m_l) + polygon_area(poly_r, m_r)
    assert np.isclose(total, area(tri), rtol=1e-9, atol=1e-9 * (1 + area(tri)))


@given(triangle, st.integers(0, 2), st.floats(0.0, 1.0))
def test_split_bounds_contain_the_exactly_clipped_parts(tri, axis, frac):
    """Both parts' boxes contain the exact clipped polygons and are no larger than the box."""
    lo, hi = tri[0].min(axis=0), tri[0].max(axis=0)
    pos = np.float64(np.float32(lo[axis] + frac * (np.float64(hi[axis]) - lo[axis])))
    bounds = np.concatenate([lo, hi]).astype(np.float32)
    left = np.empty(6, np.float32)
    right = np.empty(6, np.float32)
    split_triangle_bounds(tri, 0, bounds, axis, pos, left, right)
    left_py = np.empty(6, np.float32)
    right_py = np.empty(6, np.float32)
    split_triangle_bounds_py(tri, 0, bounds, axis, pos, left_py, right_py)
    assert np.array_equal(left, left_py)
    assert np.array_equal(right, right_py)
    hi_left, lo_right = hi.copy(), lo.copy()
    hi_left[axis] = pos
    lo_right[axis] = pos
    for box, (b_lo, b_hi) in ((left, (lo, hi_left)), (right, (lo_right, hi))):
        poly, m = exact_clip(tri, b_lo, b_hi)
        if m == 0:
            continue
        part = poly.astype(np.float64)
        assert (part >= box[:3] - 1e-30).all()
        assert (part <= box[3:] + 1e-30).all()
        # Tight: the outward rounding (2 ulps) and one float32 rounding at most.
        tol = 4e-7 * np.abs(part).max() + 1e-30
        assert (box[:3] >= part.min(axis=0) - tol).all()
        assert (box[3:] <= part.max(axis=0) + tol).all()


def test_split_bounds_by_hand():
    tri = np.array([[[0, 0, 0], [4, 0, 0], [0, 4, 0]]], dtype=np.float32)
    left = np.empty(6, np.float32)
    right = np.empty(6, np.float32)
    everywhere = np.array([-np.inf] * 3 + [np.inf] * 3, np.float32)
    split_triangle_bounds(tri, 0, everywhere, 0, 1.0, left, right)
    # Left part: x in [0, 1], y up to 4 (the vertex (0, 4)); right part: x in [1, 4], y up to 3.
    assert np.allclose(left, [0, 0, 0, 1, 4, 0], atol=1e-6)
    assert np.allclose(right, [1, 0, 0, 4, 3, 0], atol=1e-6)
    assert right[4] >= 3.0  # rounded outward
    # A plane missing the triangle leaves that side empty (lo = inf on the free axes).
    split_triangle_bounds(tri, 0, everywhere, 0, 5.0, left, right)
    assert np.array_equal(left, [0, 0, 0, 4, 4, 0])
    assert right[1] == np.inf
    # Within a part's box: both sides are clamped to it.
    part = np.array([0, 0, 0, 2, 1, 0], np.float32)
    split_triangle_bounds(tri, 0, part, 0, 1.0, left, right)
    assert np.allclose(left, [0, 0, 0, 1, 1, 0], atol=1e-6)
    assert np.allclose(right, [1, 0, 0, 2, 1, 0], atol=1e-6)


def test_touching_box_clips_to_a_point_not_to_nothing():
    tri = np.array([[[0, 0, 0], [-1, 0, 0], [0, -1, 0]]], dtype=np.float32)
    poly, m = clip(tri, [0, 0, 0], [1, 1, 1])
    assert m >= 1
    assert np.array_equal(np.unique(poly, axis=0), [[0.0, 0.0, 0.0]])
    # Area-only callers see either an early stop (m < 3) or a zero area.
    poly3, m3 = clip(tri, [0, 0, 0], [1, 1, 1], min_vertices=3)
    assert m3 < 3 or polygon_area(poly3, m3) == 0.0


def test_polygon_bounds_round_outward_within_the_box():
    tri = np.array([[[0, 0, 0], [3, 0, 0], [0, 3, 3]]], dtype=np.float32)
    lo = np.array([0.5, 0.25, 0.0], np.float32)
    hi = np.array([2.0, 2.0, 1.0], np.float32)
    poly, m = clip(tri, lo, hi)
    out = np.empty(6, np.float32)
    polygon_bounds(poly, m, lo, hi, out, 0.0)
    exact, _ = exact_clip(tri, lo, hi)
    exact = exact.astype(np.float64)
    assert (out[:3] <= exact.min(axis=0)).all()
    assert (out[3:] >= exact.max(axis=0)).all()
    assert (out[:3] >= lo).all()
    assert (out[3:] <= hi).all()
