"""The triangle-row kernels against numpy: the mesh's rows and the gather by references."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rayaccel.kernels.triangle_rows import gather_rows, hit_rows, triangle_corners
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.validation import NORMAL_FLOOR


def numpy_hit_rows(mesh: TriangleMesh) -> np.ndarray:
    """The rows by numpy: the float64 cross product's magnitudes, degenerate rows collapsed."""
    positions = mesh.vertices if mesh.vertices64 is None else mesh.vertices64
    tri = positions[mesh.faces]
    wide = tri.astype(np.float64)
    cross = np.cross(wide[:, 1] - wide[:, 0], wide[:, 2] - wide[:, 0])
    doubled_area = np.abs(cross[:, 0]) + np.abs(cross[:, 1]) + np.abs(cross[:, 2])
    degenerate = ~(doubled_area >= NORMAL_FLOOR[mesh.precision])
    rows = tri.reshape(-1, 9).copy()
    rows[degenerate, 3:6] = rows[degenerate, 0:3]
    rows[degenerate, 6:9] = rows[degenerate, 0:3]
    return rows


def _mixed_mesh(precision: str, seed: int) -> TriangleMesh:
    """Random triangles plus collinear, repeated-corner and sub-resolution ones."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(60, 3)) * rng.choice([1e-3, 1.0, 1e4], size=(60, 1))
    special = np.array([
        [0, 0, 0], [1, 1, 1], [2, 2, 2],  # collinear
        [1e-20, 0, 0], [0, 1e-20, 0],  # doubled area 1e-40: below float32's normal floor
        [3, 0, 0], [3, 1e-7, 0],  # with the origin: thin, not degenerate
    ])  # fmt: skip
    vertices = np.concatenate([points, special])
    n = len(points)
    faces = rng.integers(0, n, size=(200, 3))
    faces = np.concatenate([
        faces, [[n, n + 1, n + 2], [n, n, n + 1], [n, n + 3, n + 4], [n + 5, n + 6, n]],
    ])  # fmt: skip
    return TriangleMesh(vertices, faces.astype(np.int32), precision=precision)


@pytest.mark.parametrize("precision", ["float32", "float64"])
@pytest.mark.parametrize("seed", [0, 1])
def test_hit_rows_match_numpy_bit_for_bit(precision: str, seed: int) -> None:
    mesh = _mixed_mesh(precision, seed)
    rows = mesh.hit_rows()
    expected = numpy_hit_rows(mesh)
    assert rows.dtype == expected.dtype == (np.float64 if precision == "float64" else np.float32)
    assert np.array_equal(rows.view(np.uint8), expected.view(np.uint8))
    # The special triangles: collinear and repeated corners collapse in both precisions;
    # the 1e-20 one only in float32.
    collapsed = (rows[:, 3:6] == rows[:, 0:3]).all(axis=1) & (rows[:, 6:9] == rows[:, 0:3]).all(1)
    assert collapsed[-4]
    assert collapsed[-3]
    assert not collapsed[-1]
    assert collapsed[-2] == (precision == "float32")


@settings(max_examples=30, deadline=None)
@given(
    st.lists(
        st.tuples(*[st.floats(-1e6, 1e6, allow_nan=False, width=32)] * 3),
        min_size=3,
        max_size=12,
    ),
    st.randoms(use_true_random=False),
)
def test_hit_rows_match_numpy_on_any_float32_mesh(points, random) -> None:
    vertices = np.array(points, dtype=np.float32)
    n = len(vertices)
    faces = np.array([[random.randrange(n) for _ in range(3)] for _ in range(20)], np.int32)
    mesh = TriangleMesh(vertices, faces)
    assert np.array_equal(mesh.hit_rows(), numpy_hit_rows(mesh))


def test_hit_rows_kernel_takes_the_precision_floor() -> None:
    """The floor decides: a tiny triangle is kept under a lower floor."""
    vertices = np.array([[0, 0, 0], [1e-20, 0, 0], [0, 1e-20, 0]], dtype=np.float32)
    faces = np.array([[0, 1, 2]], dtype=np.int32)
    kept = hit_rows(vertices, faces, 1e-45)
    assert kept[0].tolist() == vertices.reshape(-1).tolist()
    collapsed = hit_rows(vertices, faces, float(NORMAL_FLOOR["float32"]))
    assert collapsed[0].tolist() == [0.0] * 9


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gather_rows_is_fancy_indexing(dtype) -> None:
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(50, 9)).astype(dtype)
    index = rng.integers(0, 50, size=120).astype(np.int32)
    out = gather_rows(rows, index)
    assert out.dtype == dtype
    assert out.flags.c_contiguous
    assert np.array_equal(out, rows[index])


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_triangle_corners_are_fancy_indexing(precision: str) -> None:
    mesh = _mixed_mesh(precision, 2)
    corners = mesh.triangles()
    assert corners.dtype == np.float32
    assert corners.flags.c_contiguous
    assert np.array_equal(corners, mesh.vertices[mesh.faces])
    if mesh.vertices64 is not None:
        assert np.array_equal(
            triangle_corners(mesh.vertices64, mesh.faces), mesh.vertices64[mesh.faces]
        )


@pytest.mark.parametrize("n_faces", [1, 5, 63, 64, 65, 1000])
def test_corner_bounds_cover_only_referenced_vertices(n_faces: int) -> None:
    rng = np.random.default_rng(n_faces)
    vertices = rng.normal(size=(300, 3)).astype(np.float32)
    vertices[0] = [1e6, -1e6, 1e6]  # never referenced
    faces = rng.integers(1, 300, size=(n_faces, 3)).astype(np.int32)
    lo, hi = TriangleMesh(vertices, faces).bounds()
    used = vertices[faces.reshape(-1)]
    assert lo.dtype == hi.dtype == np.float32
    assert lo.tolist() == used.min(axis=0).tolist()
    assert hi.tolist() == used.max(axis=0).tolist()
