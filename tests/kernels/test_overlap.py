"""Triangle/box overlap (Akenine-Möller 2001) against an exact clipping oracle."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rayaccel.kernels.clip import clip_triangle_box_py
from rayaccel.kernels.overlap import triangle_box_overlap, triangle_box_overlap_py

#: Coordinates on a coarse dyadic grid: every product the test forms is exact in float64,
#: and triangles often touch boxes exactly (shared planes, edges and corners).
grid = st.integers(-12, 12).map(lambda k: k / 4)


def oracle(tri, lo, hi):
    """Exact: clip the triangle to the closed box with Fractions; non-empty means overlap."""
    to_q = np.vectorize(Fraction, otypes=[object])
    poly = np.empty((16, 3), dtype=object)
    scratch = np.empty((16, 3), dtype=object)
    corners = to_q(tri.astype(np.float64).reshape(1, 3, 3))
    m = clip_triangle_box_py(corners, 0, to_q(lo.astype(np.float64)),
                             to_q(hi.astype(np.float64)), poly, scratch, 1)
    return m >= 1


def overlaps(tri, lo, hi):
    tri = np.asarray(tri, np.float32).reshape(1, 3, 3)
    lo = np.asarray(lo, np.float32)
    hi = np.asarray(hi, np.float32)
    jit = triangle_box_overlap(tri, 0, lo, hi)
    assert triangle_box_overlap_py(tri, 0, lo, hi) == jit
    return jit


@st.composite
def triangle_and_box(draw):
    corners = [draw(grid) for _ in range(9)]
    kind = draw(st.sampled_from(["any", "repeated", "collinear"]))
    tri = np.array(corners, np.float32).reshape(3, 3)
    if kind == "repeated":
        tri[2] = tri[draw(st.integers(0, 1))]
    elif kind == "collinear":
        tri[2] = tri[0] + (tri[1] - tri[0]) * draw(st.sampled_from([-1.0, 0.5, 2.0]))
    a = np.array([draw(grid) for _ in range(3)], np.float32)
    b = np.array([draw(grid) for _ in range(3)], np.float32)
    if draw(st.booleans()):
        b[draw(st.integers(0, 2))] = a[0]  # flat boxes too
    return tri, np.minimum(a, b), np.maximum(a, b)


@given(triangle_and_box())
def test_agrees_with_exact_clipping(case):
    tri, lo, hi = case
    assert overlaps(tri, lo, hi) == oracle(tri, lo, hi)


@given(triangle_and_box(), st.integers(0, 2), st.booleans())
def test_touching_counts_as_overlap(case, axis, upper):
    """Move the box so that its face just touches the triangle's extreme vertex."""
    tri, lo, hi = case
    size = hi - lo
    lo = lo.copy()
    if upper:
        lo[axis] = tri[:, axis].max()
    else:
        lo[axis] = tri[:, axis].min() - size[axis]
    # The box's other axes are moved over the touching vertex too.
    vertex = tri[np.argmax(tri[:, axis])] if upper else tri[np.argmin(tri[:, axis])]
    for k in range(3):
        if k != axis:
            lo[k] = vertex[k] - size[k] / 2
    hi = lo + size
    assert oracle(tri, lo, hi)
    assert overlaps(tri, lo, hi)


TRI = [[3, 0, 0], [0, 3, 0], [0, 0, 3]]  # the plane x + y + z = 3


@pytest.mark.parametrize(
    ("lo", "hi", "expected"),
    [
        ([0, 0, 0], [1, 1, 1], True),  # the plane passes through the corner (1, 1, 1)
        ([0, 0, 0], [0.96875, 0.96875, 0.96875], False),  # just below the plane
        ([1, 1, 1], [2, 2, 2], True),  # corner (1, 1, 1) from the other side
        ([3, 0, 0], [4, 1, 1], True),  # a vertex on the box's corner
        ([3.03125, 0, 0], [4, 1, 1], False),  # just past the vertex
        ([1.5, 1.5, -1], [2, 2, 0], True),  # edge (3,0,0)-(0,3,0) meets the corner (1.5, 1.5, 0)
        ([1.5625, 1.5625, -1], [2, 2, 0], False),  # just beside that edge (an edge axis separates)
        ([-5, -5, -5], [5, 5, 5], True),  # the triangle inside the box
        ([0.5, 0.5, 0.5], [1.5, 1.5, 1.5], True),  # the box around a point inside the triangle
    ],
)
def test_cases_by_hand(lo, hi, expected):
    tri = np.array(TRI, np.float32)
    assert overlaps(tri, lo, hi) == expected
    assert oracle(tri, np.array(lo, np.float32), np.array(hi, np.float32)) == expected


def test_degenerate_triangles():
    point = np.array([[1, 1, 1]] * 3, np.float32)
    assert overlaps(point, [1, 1, 1], [2, 2, 2])
    assert not overlaps(point, [1.25, 1, 1], [2, 2, 2])
    # A segment from (0,0,0) to (2,2,0) passes the box [1,2]x[0,1] only at its corner (1,1).
    segment = np.array([[0, 0, 0], [2, 2, 0], [1, 1, 0]], np.float32)
    assert overlaps(segment, [1, 0, -1], [2, 1, 1])
    assert not overlaps(segment, [1.25, 0, -1], [2, 1, 1])
