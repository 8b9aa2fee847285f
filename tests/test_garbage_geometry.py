"""Garbage geometry (issue 20): every builder builds a valid structure or refuses clearly.

Hypothesis draws meshes of at most 64 triangles from hostile strategies: random
float32 bit patterns (NaN, ±inf, subnormals, ±0, huge and tiny normals), vertices
scaled by 1e-30 … 1e30 and float32's limits, small-integer lattices (duplicate,
collinear and coplanar vertices), a few special values sprinkled into ordinary
coordinates; faces with random indices (negative, out of range, beyond int32,
non-integer floats), degenerate triangles (repeated corners) and duplicated faces.

For every registered builder, constructing the :class:`~rayaccel.TriangleMesh` and
building must either raise a :class:`~rayaccel.errors.RayAccelError` with a message,
or give a structure that passes ``validate()`` and whose closest and any hits on a
few rays (through the triangles' centroids, random, axis-parallel) equal the
brute-force oracle's. Anything else (another exception type, a crash, a wrong hit)
fails. CI runs the default profile (40 examples per builder); ``--full`` 400.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import event, given, note
from hypothesis import strategies as st
from hypothesis.control import currently_in_test_context
from hypothesis.extra import numpy as hnp

import rayaccel
import reference
from rayaccel import registry
from rayaccel.errors import InvalidInputError, RayAccelError

BUILDERS = registry.keys("builder")
MAX_TRIANGLES = 64
MAX_VERTICES = 24

SPECIALS = np.array(
    [np.nan, np.inf, -np.inf, 0.0, -0.0, 1e-45, -1e-45, 1e-40, 1.1754944e-38, 3.4028235e38,
     -3.4028235e38, 1e39, 2.0**30, 2.0**30 + 128, 2.0**31, 1e30, -1e30, 1e-30],
)  # fmt: skip
SCALES = (1e-30, 1e-20, 1e-10, 1e-5, 1.0, 1e5, 1e9, 2.0**30, 2.0**31, 1e20, 1e30, 3.4e38)


@st.composite
def vertex_arrays(draw: st.DrawFn) -> np.ndarray:
    """``(V, 3)`` coordinates, float32 or float64, of one of several hostile kinds."""
    n = draw(st.integers(1, MAX_VERTICES))
    kind = draw(st.sampled_from(["bits", "lattice", "scaled", "sprinkled"]))
    note(f"vertex kind {kind}")
    if kind == "bits":
        bits = draw(hnp.arrays(np.uint32, (n, 3), elements=st.integers(0, 2**32 - 1)))
        v = bits.view(np.float32)
    elif kind == "lattice":
        v = draw(hnp.arrays(np.int64, (n, 3), elements=st.integers(-3, 3))).astype(np.float64)
        v *= draw(st.sampled_from(SCALES))
    elif kind == "scaled":
        unit = st.floats(-1, 1, width=32, allow_subnormal=True)
        v = draw(hnp.arrays(np.float32, (n, 3), elements=unit)).astype(np.float64)
        v = v * draw(st.sampled_from(SCALES)) + draw(st.sampled_from((0.0, 1.0, 1e6, -(2.0**29))))
    else:
        v = draw(hnp.arrays(np.int64, (n, 3), elements=st.integers(-4, 4))).astype(np.float64)
        k = draw(st.integers(1, 3))
        rows = draw(st.lists(st.integers(0, n - 1), min_size=k, max_size=k))
        cols = draw(st.lists(st.integers(0, 2), min_size=k, max_size=k))
        vals = draw(st.lists(st.sampled_from(SPECIALS.tolist()), min_size=k, max_size=k))
        v[rows, cols] = vals
    if draw(st.booleans()):  # duplicate vertices
        v = np.concatenate([v, v[: draw(st.integers(1, n))]])
    return v


@st.composite
def face_arrays(draw: st.DrawFn, n_vertices: int) -> np.ndarray:
    """``(F, 3)`` indices: valid, degenerate, duplicated, out of range or not integers."""
    n_f = draw(st.integers(0 if draw(st.booleans()) else 1, MAX_TRIANGLES))
    kind = draw(st.sampled_from(["valid", "valid", "degenerate", "wild", "huge", "float"]))
    note(f"face kind {kind}")
    top = n_vertices - 1
    if kind in ("valid", "degenerate"):
        f = draw(hnp.arrays(np.int64, (n_f, 3), elements=st.integers(0, top)))
        if kind == "degenerate" and n_f:
            f[: max(1, n_f // 2), 1] = f[: max(1, n_f // 2), 0]
            f[: max(1, n_f // 4), 2] = f[: max(1, n_f // 4), 0]
        if n_f and draw(st.booleans()):  # duplicated faces, also with rotated corners
            f = np.concatenate([f, np.roll(f[: draw(st.integers(1, n_f))], 1, axis=1)])
        return f
    if kind == "wild":
        return draw(hnp.arrays(np.int64, (n_f, 3), elements=st.integers(-3, top + 3)))
    if kind == "huge":
        big = st.sampled_from([2**31, 2**32, 2**32 + 1, 2**40, -(2**31) - 1, -(2**63)])
        f = draw(hnp.arrays(np.int64, (n_f, 3), elements=st.integers(0, top)))
        if n_f:
            f[draw(st.integers(0, n_f - 1)), draw(st.integers(0, 2))] = draw(big)
        return f
    floats = st.sampled_from([0.0, 1.0, 0.5, -0.0, np.nan, np.inf, 1e20, float(top)])
    return draw(hnp.arrays(np.float64, (n_f, 3), elements=floats))


@st.composite
def garbage(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    vertices = draw(vertex_arrays())
    return vertices, draw(face_arrays(vertices.shape[0]))


def _rays(mesh: rayaccel.TriangleMesh, seed: int) -> rayaccel.RayBatch:
    """Rays at every centroid from around the bounds, random and axis-parallel ones.

    Origins stay inside the coordinate range rays may use (``|x| <= 2^29``) and
    directions are scaled to a largest component of 1. A flat mesh's thin axis gets a
    quarter of its largest extent: an origin within rounding of its plane (1e-31 from
    a 1e-10 triangle) makes the triangle test's distance underflow to ``-0.0``, a hit
    at the origin that box-culling traversals miss (docs/reliability.md, "Numbers":
    tiny scales).
    """
    rng = np.random.default_rng(seed)
    lo, hi = (b.astype(np.float64) for b in mesh.bounds())
    centre = (lo + hi) / 2
    scale = max(float((hi - lo).max()), 1e-3 * float(np.abs(centre).max()), 1e-30)
    size = np.maximum(hi - lo, 0.25 * scale)
    tri = mesh.triangles().astype(np.float64)
    target = np.concatenate([tri.mean(axis=1), lo + rng.random((32, 3)) * size])
    origin = centre + (rng.random(target.shape) - 0.5) * 3 * size
    axis = np.zeros((24, 3))
    axis[np.arange(24), rng.integers(0, 3, 24)] = rng.choice([-1.0, 1.0], 24)
    direction = np.concatenate([target - origin, axis])
    origin = np.concatenate([origin, lo + rng.random((24, 3)) * size])
    origin = np.clip(origin, -(2.0**29), 2.0**29)
    scale = np.abs(direction).max(axis=1, keepdims=True)
    direction = np.where(scale > 0, direction / np.where(scale > 0, scale, 1), 0.0)
    return rayaccel.RayBatch(origin, direction)


def _refused(exc: RayAccelError | None, what: str) -> bool:
    """Whether ``exc`` is a refusal; it must carry a message."""
    if exc is None:
        return False
    assert str(exc).strip(), f"{what}: {type(exc).__name__} without a message"
    _record(f"{what} refused", str(exc))
    return True


def _record(what: str, detail: str = "") -> None:
    """Note and count an outcome inside a hypothesis test (the plain tests share the check)."""
    if currently_in_test_context():
        note(f"{what}: {detail}")
        event(what)


def _check_builder(builder: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    error: RayAccelError | None = None
    try:
        mesh = rayaccel.TriangleMesh(vertices, faces)
    except RayAccelError as exc:
        error = exc
    if _refused(error, "mesh"):
        assert isinstance(error, InvalidInputError)
        return
    try:
        accel = rayaccel.build(mesh, builder)
    except RayAccelError as exc:
        error = exc
    if _refused(error, "build"):
        return
    _record("built")
    accel.validate()
    rays = _rays(mesh, seed=0)
    ref = reference.oracle(mesh, rays)
    tri = reference.tri9(mesh)
    # The structure's default traversal (the others walk the same structure).
    reference.assert_closest_matches(tri, rays, accel.trace(rays), ref, builder)
    reference.assert_any_matches(tri, rays, accel.trace(rays, query="any"), ref, builder)


@pytest.mark.parametrize("builder", BUILDERS)
@given(mesh=garbage())
def test_garbage_builds_a_valid_structure_or_raises_a_clear_error(builder, mesh):
    _check_builder(builder, *mesh)


@pytest.mark.parametrize("builder", BUILDERS)
@pytest.mark.parametrize("scale", [1e-30, 1e-20, 1e-12, 1.0, 1e9, 2.0**30])
def test_a_closed_mesh_at_every_scale(builder, scale):
    """Huge and tiny scales of an ordinary mesh: built and traced like the unit one."""
    base = reference.icosphere(1)
    _check_builder(builder, base.vertices.astype(np.float64) * scale, base.faces)


@pytest.mark.parametrize("builder", BUILDERS)
def test_only_degenerate_triangles(builder):
    """Points, segments and duplicates only: nothing can be hit."""
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 0], [1, 1, 1]], dtype=np.float64)
    f = np.array([[0, 0, 0], [0, 1, 2], [0, 3, 0], [4, 4, 4], [0, 1, 2], [2, 1, 0]])
    mesh = rayaccel.TriangleMesh(v, f)
    accel = rayaccel.build(mesh, builder)
    accel.validate()
    rays = _rays(mesh, seed=1)
    assert not accel.trace(rays).hit.any()
    assert not accel.trace(rays, query="any").hit.any()


# ---------------------------------------------------------------- kd sweep, bounds-checked


def _sweep_both_ways(mesh: rayaccel.TriangleMesh, mode: int) -> None:
    """Run the kd sweep kernel compiled and as plain Python (numpy checks every index):
    the same tree, and no index out of bounds."""
    from rayaccel.kdtree.builders import sweep

    tri = np.ascontiguousarray(mesh.triangles(), dtype=np.float32)
    lo, hi = (np.ascontiguousarray(b, dtype=np.float32) for b in mesh.bounds())
    events = sweep.initial_events(tri)
    scale = max(float(np.abs(lo).max()), float(np.abs(hi).max()))
    depth = min(sweep.max_depth_for(tri.shape[0]), 30)
    params = sweep.SweepParams(
        mode, 15.0, 20.0, 0.8, depth, 4, True, 0, scale * 2.0**-40, sweep.MAX_DUPLICATION
    )
    args = (tri, lo, hi, *events, params, tri.shape[0], 0, 1.0, 0)
    compiled = sweep._build_kernel(*args)
    python = sweep._build_kernel.py_func(*args)
    for a, b in zip(compiled[:5], python[:5], strict=True):
        assert np.array_equal(a, b)


KD_MODES = [pytest.param(0, id="sah"), pytest.param(1, id="median")]


@pytest.mark.parametrize("mode", KD_MODES)
def test_kd_sweep_with_more_events_below_than_at_the_root(mode):
    """Degenerate triangles at 1e-30: a node held more events than the root once its
    triangles were clipped, and the kept-event scratch (sized for the root) was
    written past its end (heap corruption; found by the strategy above under
    ``NUMBA_BOUNDSCHECK=1``)."""
    v = np.array([[-1e-30, 0, -1e-30]] + [[-1e-30, -1e-30, -1e-30]] * 8 + [[1e-30, -1e-30, -1e-30]])
    f = np.array([[0, 9, 9], [1, 9, 9], [9, 9, 9], [9, 9, 9], [9, 9, 9]])
    mesh = rayaccel.TriangleMesh(v, f)
    _sweep_both_ways(mesh, mode)
    for builder in ("kdtree.median", "kdtree.sah"):
        _check_builder(builder, v, f)


@pytest.mark.parametrize("mode", KD_MODES)
@given(mesh=garbage())
def test_kd_sweep_as_python_on_garbage(mode, mesh):
    try:
        built = rayaccel.TriangleMesh(*mesh)
    except RayAccelError:
        return
    _sweep_both_ways(built, mode)


@pytest.mark.parametrize("builder", ["kdtree.sah", "kdtree.median"])
def test_kd_validation_of_a_small_scene_far_from_the_origin(builder):
    """A scene 1e-5 wide at 1.0: validate() shrank the cells by a millionth of 1e-5,
    below float32's spacing there, and flagged a point triangle on a split plane as
    missing from the cell it only touches."""
    v = np.array([[1.000005, 1.00001, 1.0]] + [[1.0, 1.0, 1.0]] * 8 + [[1.00001, 1.0, 1.0]])
    f = np.array([[1, 9, 0], [0, 0, 0], [0, 0, 0]])
    _check_builder(builder, v, f)
