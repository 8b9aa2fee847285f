"""The numeric range of each precision (docs/reliability.md, "Numbers"): a case per row.

Values beyond the range are refused where ``RayBatch`` and ``TriangleMesh`` convert their
inputs, with a message naming the argument, the row and the range; values at its edges
are traced exactly (the hits equal the oracle's and the analytic distance). The kernels
are the default tree's (``bvh2.binned_sah``, ``bvh2.stack``) and the float32 oracle.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.rays.batch import RayBatch
from rayaccel.validation import COORDINATE_LIMIT, DIRECTION_FLOOR, NORMAL_FLOOR

QUAD = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64)
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]])
#: The ranges as the messages write them.
RANGE = {"float32": re.escape("|x| <= 2^30 (about 1.07e+09)"),
         "float64": re.escape("|x| <= 2^62 (about 4.61e+18)")}  # fmt: skip
FLOOR = {"float32": re.escape("2^-30 (about 9.31e-10)"),
         "float64": re.escape("2^-62 (about 2.17e-19)")}  # fmt: skip
SUGGESTS_FLOAT64 = 'precision="float64"'


def _quad(scale: float = 1.0, precision: str = "float32") -> rayaccel.TriangleMesh:
    """Two triangles covering ``[-scale, scale]^2`` at ``z = 0``."""
    return rayaccel.TriangleMesh(QUAD * scale, QUAD_FACES, precision=precision)


@pytest.fixture(scope="module")
def unit_quads():
    return {p: rayaccel.build(_quad(precision=p)) for p in ("float32", "float64")}


def _refused(match: str, call, *args, **kwargs) -> str:
    """Call and return the message of the ``InvalidInputError`` it raises."""
    with pytest.raises(InvalidInputError, match=match) as info:
        call(*args, **kwargs)
    return str(info.value)


def _assert_suggestion(message: str, suggested: bool) -> None:
    assert (SUGGESTS_FLOAT64 in message) == suggested, message
    if not suggested:
        assert "scale" in message, message


# ----------------------------------------------------------------------------- coordinates


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize(
    ("precision", "value", "suggested"),
    [("float32", 1.5 * 2**30, True), ("float32", -1e10, True), ("float32", 1e20, False),
     ("float32", 1e39, False), ("float64", 1e19, False), ("float64", -1e39, False),
     ("float64", 1e300, False)],
)  # fmt: skip
def test_vertex_beyond_the_range_is_refused(precision, value, suggested):
    v = QUAD.copy()
    v[2, 1] = value
    message = _refused(r"^vertices: vertex 2 .*" + RANGE[precision],
                       rayaccel.TriangleMesh, v, QUAD_FACES, precision=precision)  # fmt: skip
    _assert_suggestion(message, suggested)


def test_refit_and_load_mesh_name_the_vertex_beyond_the_range(tmp_path):
    accel = rayaccel.build(_quad())
    v = QUAD.copy()
    v[3, 0] = 2.0**31
    _refused(r"^new_vertices: vertex 3 .*" + RANGE["float32"], accel.refit, v)
    path = tmp_path / "far.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 5e9 0\nf 1 2 3\n")
    with pytest.raises(SceneFileError, match=r"vertices: vertex 2 .*" + RANGE["float32"]):
        rayaccel.load_mesh(path)


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize(
    ("precision", "value", "suggested"),
    [("float32", 2.0**31, True), ("float32", -1e20, False), ("float32", 1e39, False),
     ("float64", 1e19, False), ("float64", -1e300, False)],
)  # fmt: skip
def test_origin_beyond_the_range_is_refused(precision, value, suggested):
    origins = np.array([[0.1, 0.2, -1.0], [0.1, value, -1.0]])
    message = _refused(r"^origins: row 1 .*" + RANGE[precision],
                       RayBatch, origins, [0, 0, 1.0], precision=precision)  # fmt: skip
    _assert_suggestion(message, suggested)


def test_origins_beyond_the_range_are_refused_on_every_path(unit_quads):
    far = np.array([[0.1, 0.2, -(2.0**40)]])
    batch64 = RayBatch(far, [0, 0, 1.0], precision="float64")
    # A float64 batch traced by a float32 accel is converted, and checked, on the way.
    _refused(r"^origins: row 0 .*" + RANGE["float32"], unit_quads["float32"].trace, batch64)
    _refused(r"^origins: row 0 .*" + RANGE["float32"], unit_quads["float32"].intersect,
             far, [0, 0, 1.0])  # fmt: skip
    hits = unit_quads["float64"].trace(batch64)
    assert hits.t[0] == 2.0**40


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_the_edges_of_the_coordinate_range_are_accepted(precision):
    limit = COORDINATE_LIMIT[precision]
    rays = RayBatch([[limit, -limit, 0.0]], [[-limit, limit, 1.0]], precision=precision)
    assert rays.origin[0, 0] == limit
    rayaccel.TriangleMesh(QUAD * limit, QUAD_FACES, precision=precision)


@pytest.mark.parametrize(
    ("origin", "direction"),
    [([np.inf, 0, -1], [0, 0, 1]), ([np.nan, 0, -1], [0, 0, 1]), ([0, 0, -1], [0, 0, 0]),
     ([0, 0, -1], [np.inf, 0, 1]), ([0, 0, -1], [0, np.nan, 1]), ([0, 0, -1], [0, -0.0, 0])],
)  # fmt: skip
def test_non_finite_and_zero_rays_still_miss(unit_quads, origin, direction):
    """The range checks leave alone what rays define to miss (test_bad_input's rows)."""
    hits = unit_quads["float32"].trace(RayBatch([origin], [direction]))
    assert hits.prim[0] == -1
    assert hits.t[0] == np.inf


# ----------------------------------------------------------------------------- directions


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize(
    ("precision", "direction", "suggested"),
    [("float32", [0, 0, 1e-10], True), ("float32", [1e-40, 1e-40, -1e-40], False),
     ("float32", [np.float32(1e-45), 0, 0], False), ("float32", [1e-50, 0, 0], False),
     ("float64", [0, 0, 1e-20], False), ("float64", [1e-310, 0, 0], False)],
    ids=["1e-10", "subnormal", "smallest-subnormal", "rounds-to-zero", "f64-1e-20",
         "f64-subnormal"],
)  # fmt: skip
def test_direction_below_the_floor_is_refused(precision, direction, suggested):
    """Never traced as a zero direction, including one that rounds to zero in float32."""
    directions = np.array([[0, 0, 1.0], direction])
    message = _refused(r"^directions: row 1 .*below " + FLOOR[precision],
                       RayBatch, [0.1, 0.2, -1.0], directions, precision=precision)  # fmt: skip
    _assert_suggestion(message, suggested)


def test_direction_overflowing_float32_is_refused_and_float64_traces_it(unit_quads):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "overflow encountered in cast" either
        message = _refused(r"^directions: row 0 .*overflows float32", RayBatch,
                           [[0.1, 0.2, -1.0]], [[0, 0, 1e39]])  # fmt: skip
    assert SUGGESTS_FLOAT64 in message
    hits = unit_quads["float64"].trace(RayBatch([[0.1, 0.2, -1.0]], [[0, 0, 1e39]],
                                                precision="float64"))  # fmt: skip
    assert hits.t[0] == pytest.approx(1e-39, rel=1e-15)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_the_direction_floor_is_accepted_and_traced(unit_quads, precision):
    floor = DIRECTION_FLOOR[precision]
    rays = RayBatch([[0.1, 0.2, -1.0]], [[0, 0, floor]], precision=precision)
    hits = unit_quads[precision].trace(rays)
    assert hits.t[0] == 1 / floor


def test_subnormal_direction_components_are_flushed():
    """The slab test divides by the component, the triangle test shears by it.

    Before the flush the ray's box (it starts at ``x = 1.4e-45``) was missed while the
    triangle in it was hit: the accel and the brute-force oracle disagreed.
    """
    tiny = float(np.float32(1.4e-45))
    v = np.array([[tiny, -1, 1], [tiny, 1, 1], [1, 0, 1.0], [-1, -1, 3], [-1, 1, 3],
                  [-tiny, 0, 3]])  # fmt: skip
    mesh = rayaccel.TriangleMesh(v, [[0, 1, 2], [3, 4, 5]])
    accel = rayaccel.build(mesh, max_leaf_size=1)
    directions = np.array([[1e-40, 0, 1], [-1e-40, 0, 1], [2e-38, 0, 1]], dtype=np.float32)
    given = directions.copy()
    rays = RayBatch(np.zeros((3, 3)), directions)
    np.testing.assert_array_equal(directions, given)  # the caller's array is not written
    assert rays.direction[0, 0] == 0
    assert not np.signbit(rays.direction[0, 0])
    assert rays.direction[1, 0] == 0
    assert np.signbit(rays.direction[1, 0])
    assert rays.direction[2, 0] == np.float32(2e-38)  # normal: kept
    hits, expected = accel.trace(rays), reference.oracle(mesh, rays)
    np.testing.assert_array_equal(hits.t, expected.t)
    np.testing.assert_array_equal(hits.prim, expected.prim)
    assert hits.prim.tolist() == [-1, -1, 0]  # the flushed rays run along x = 0 exactly
    f64 = RayBatch(np.zeros((1, 3)), [[1e-310, 0, 1]], precision="float64")
    assert f64.direction[0, 0] == 0


def test_subnormal_components_are_flushed_below_the_normal_floor():
    smallest = np.float32(NORMAL_FLOOR["float32"])
    below = np.nextafter(smallest, np.float32(0))
    rays = RayBatch(np.zeros((2, 3)), np.array([[smallest, 0, 1], [below, 0, 1]]))
    assert rays.direction[0, 0] == smallest
    assert rays.direction[1, 0] == 0


# ----------------------------------------------------------------------------- intervals


@pytest.mark.parametrize(
    ("tmin", "tmax", "as_tmin", "as_tmax", "hit"),
    [(0.0, 1e39, 0.0, np.inf, True), (-1e39, np.inf, -np.inf, np.inf, True),
     (1e39, np.inf, np.inf, np.inf, False), (-np.inf, -1e39, -np.inf, -np.inf, False),
     (0.0, 1e38, 0.0, 1e38, True), (1e38, np.inf, 1e38, np.inf, False)],
)  # fmt: skip
def test_interval_beyond_float32_rounds_to_infinity(unit_quads, tmin, tmax, as_tmin, as_tmax,
                                                    hit):  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "overflow encountered in cast"
        rays = RayBatch([[0.1, 0.2, -1.0]], [[0, 0, 1.0]], np.float64(tmin), np.float64(tmax))
    assert rays.tmin[0] == np.float32(as_tmin)
    assert rays.tmax[0] == np.float32(as_tmax)
    hits = unit_quads["float32"].trace(rays)
    assert hits.t[0] == (1.0 if hit else np.inf)


# ----------------------------------------------------------------------------- triangles


def test_triangles_below_the_resolution_are_zero_area(unit_quads):
    """A quad of 1e-20: its determinant's reciprocal overflows float32.

    Unless collapsed, it is missed by rays from below and hit at ``t = -inf`` by a ray from
    above with ``tmin = -inf``. Zero-area, it is never hit; a float64 mesh hits it.
    """
    s = 1e-20
    origins = np.array([[0.1 * s, 0.2 * s, -1.0], [0.1 * s, 0.2 * s, 1.0]])
    tmin = np.array([0.0, -np.inf])
    small = _quad(s)
    rows = small.hit_rows()
    assert (rows[:, 3:6] == rows[:, 0:3]).all()
    assert (rows[:, 6:9] == rows[:, 0:3]).all()
    hits = rayaccel.build(small).trace(RayBatch(origins, [0, 0, 1.0], tmin))
    assert hits.prim.tolist() == [-1, -1]
    assert (hits.t == np.inf).all()
    exact = rayaccel.build(_quad(s, "float64"))
    hits64 = exact.trace(RayBatch(origins, [0, 0, 1.0], tmin, precision="float64"))
    assert hits64.t.tolist() == [1.0, -1.0]
    # Just above the resolution (1e-18: doubled area 8e-36), float32 hits it.
    above = rayaccel.build(_quad(1e-18))
    assert above.trace(RayBatch([[0.1e-18, 0.2e-18, -1.0]], [0, 0, 1.0])).t[0] == 1.0


# ----------------------------------------------------------------------------- in range


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_the_edges_of_the_range_trace_exactly(precision):
    """A quad spanning the whole range, hit from its far side with the floor's directions.

    The worst case of the scaled distance ``T``: every coordinate difference is up to
    ``2^31`` (``2^63``) and ``1/d`` is ``2^30`` (``2^62``). Every ray hits at the analytic
    distance ``2 * limit / floor`` (``2^61``, ``2^125``).
    """
    limit, floor = COORDINATE_LIMIT[precision], DIRECTION_FLOOR[precision]
    mesh = rayaccel.TriangleMesh(QUAD * limit + [0, 0, limit], QUAD_FACES, precision=precision)
    targets = np.array([[0.5, 0.25, 1], [-0.999, 0.999, 1], [0.9, 0.99, 1], [0, 0, 1],
                        [-0.9, -0.99, 1], [0.3, -0.7, 1]]) * limit  # fmt: skip
    origins = np.array([[-1, -1, -1], [1, -1, -1], [0.999, -0.999, -1], [0.5, 0.5, -0.999],
                        [1, 1, -1], [-1, 1, -1]]) * limit  # fmt: skip
    d = targets - origins
    d = d / np.abs(d).max(axis=1, keepdims=True) * floor  # largest component: floor exactly
    rays = RayBatch(origins, d, precision=precision)
    hits = rayaccel.build(mesh).trace(rays)
    expected = np.abs(targets - origins).max(axis=1) / floor
    np.testing.assert_allclose(hits.t, expected, rtol=1e-6)
    assert hits.hit.all()
    if precision == "float32":
        oracle = reference.oracle(mesh, rays)
        np.testing.assert_array_equal(hits.t, oracle.t)
        np.testing.assert_array_equal(hits.prim, oracle.prim)


def test_tiny_coordinates_are_traced_as_given(unit_quads):
    """Coordinates have no lower bound: subnormal vertices and origins are exact values."""
    sub = float(np.float32(1e-40))
    v = np.array([[sub, -1, 1], [1, -1, 1], [sub, 1, 1]])
    mesh = rayaccel.TriangleMesh(v, [[0, 1, 2]])
    assert mesh.vertices[0, 0] == np.float32(sub)
    rays = RayBatch([[1e-45, 0, 0], [0.5, 1e-39, 0]], [[0, 0, 1.0], [0, 0, 2.0]])
    hits = rayaccel.build(mesh).trace(rays)
    oracle = reference.oracle(mesh, rays)
    np.testing.assert_array_equal(hits.t, oracle.t)
    assert hits.t.tolist() == [np.inf, 0.5]  # x = 1.4e-45 < 1e-40: left of the edge


def test_float64_traces_what_float32_refuses():
    far = QUAD * 2.0**40
    _refused(r"^vertices: vertex 0 .*" + RANGE["float32"], rayaccel.TriangleMesh, far,
             QUAD_FACES)  # fmt: skip
    accel = rayaccel.build(rayaccel.TriangleMesh(far, QUAD_FACES, precision="float64"))
    rays = RayBatch([[3.0, 5.0, -(2.0**40)], [0.1, 0.2, -1.0]], [[0, 0, 1.0], [0, 0, 1e-10]],
                    precision="float64")  # fmt: skip
    hits = accel.trace(rays)
    assert hits.t[0] == 2.0**40
    assert hits.t[1] == pytest.approx(1e10, rel=1e-15)


def test_float64_distances_beyond_float32_are_refused():
    """BVH traversals keep entry distances in float32: beyond its range they were ``inf``.

    With ``t`` near ``1e39`` the stack traversal discarded the nearer child and returned
    the farther triangle (prim 0 at 1.5e39 instead of prim 1 at 1e39). The float64 floor
    keeps every hit distance below ``2^125``.
    """
    tri = [[-1, -1, 5.0], [1, -1, 5.0], [0, 1, 5.0], [-1, -1, 10.0], [1, -1, 10.0], [0, 1, 10.0]]
    mesh = rayaccel.TriangleMesh(tri, [[0, 1, 2], [3, 4, 5]], precision="float64")
    _refused(r"^directions: row 0 .*below " + FLOOR["float64"], RayBatch,
             [[0, -0.5, 20.0]], [[0, 0, -1e-38]], precision="float64")  # fmt: skip
    accel = rayaccel.build(mesh, max_leaf_size=1)
    floor = DIRECTION_FLOOR["float64"]
    hits = accel.trace(RayBatch([[0, -0.5, 20.0]], [[0, 0, -floor]], precision="float64"))
    assert hits.prim[0] == 1
    assert hits.t[0] == 10.0 / floor
