"""Property tests (hypothesis): awkward geometry and rays, every structure equals the oracle.

Meshes are drawn from a small lattice of coordinates so that shared vertices,
coplanar and duplicated triangles, zero-area (repeated vertex) and collinear
triangles are common; rays start at vertices, on edges and faces, inside node
boxes and outside, with axis-parallel and ``±0.0`` direction components. Each
example builds with every registered builder (leaf sizes 1..8) and compares
closest and any-hit queries of every traversal with the brute-force oracle.
Examples are bounded by the ``default`` profile in ``conftest.py`` (``--full`` for
more).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

import rayaccel
import reference
from rayaccel.rays.batch import RayBatch
from rayaccel.validation import DIRECTION_FLOOR

PAIRS = reference.builder_traversal_pairs()

LATTICE = (-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0)
coordinate = st.one_of(
    st.sampled_from(LATTICE),
    st.floats(-4.0, 4.0, width=32, allow_nan=False, allow_infinity=False),
)
point = st.tuples(coordinate, coordinate, coordinate)
component = st.one_of(
    st.sampled_from((1.0, -1.0, 0.0, -0.0, 0.5, -2.0)),
    st.floats(-3.0, 3.0, width=32, allow_nan=False, allow_infinity=False),
)


def traceable(direction: np.ndarray) -> np.ndarray:
    """The same ray direction(s), scaled up where shorter than float32 traces.

    RayBatch refuses a nonzero direction whose largest component is below
    ``DIRECTION_FLOOR`` (test_numeric_range); the strategies draw some, e.g.
    ``(2.2e-16, 0, -0.0)`` or a ray aimed at a point ``1e-40`` away.
    """
    largest = np.abs(direction).max(axis=-1, keepdims=True)
    short = (largest > 0) & (largest < DIRECTION_FLOOR["float32"])
    return np.where(short, direction / np.where(short, largest, 1.0), direction)


@st.composite
def meshes(draw, max_triangles: int = 14) -> rayaccel.TriangleMesh:
    """Triangles over a shared vertex pool, with duplicates and degenerate ones."""
    pool = draw(st.lists(point, min_size=3, max_size=10))
    n = draw(st.integers(1, max_triangles))
    faces = []
    for _ in range(n):
        kind = draw(st.sampled_from(("plain", "plain", "plain", "dup", "zero", "collinear")))
        if kind == "dup" and faces:
            faces.append(draw(st.sampled_from(faces)))
            continue
        a, b, c = (draw(st.integers(0, len(pool) - 1)) for _ in range(3))
        if kind == "zero":
            c = a
        elif kind == "collinear":
            pa, pb = np.array(pool[a]), np.array(pool[b])
            pool.append(tuple(float(x) for x in (pa + pb) / 2))
            c = len(pool) - 1
        faces.append((a, b, c))
    return rayaccel.TriangleMesh(np.array(pool, dtype=np.float64), np.array(faces))


@st.composite
def ray_batches(draw, mesh: rayaccel.TriangleMesh, max_rays: int = 24) -> RayBatch:
    """Rays from vertices, edge and face points, box corners and random points."""
    tri = mesh.triangles().astype(np.float64)
    lo, hi = mesh.bounds()
    n = draw(st.integers(1, max_rays))
    origins, directions, tmins, tmaxs = [], [], [], []
    for _ in range(n):
        f = draw(st.integers(0, len(tri) - 1))
        a, b, c = tri[f]
        where = draw(st.sampled_from(("vertex", "edge", "face", "corner", "free", "free")))
        if where == "vertex":
            o = a
        elif where == "edge":
            o = (a + b) / 2
        elif where == "face":
            o = (a + b + c) / 3
        elif where == "corner":
            o = np.where(draw(st.tuples(*[st.booleans()] * 3)), lo, hi)
        else:
            o = np.array(draw(point))
        if draw(st.booleans()):
            # Aim at a vertex, edge midpoint or centroid of some triangle.
            g = tri[draw(st.integers(0, len(tri) - 1))]
            target = draw(st.sampled_from((g[0], (g[0] + g[1]) / 2, g.mean(axis=0))))
            d = target - o
        else:
            d = np.array(draw(st.tuples(component, component, component)))
        origins.append(o)
        directions.append(traceable(d))
        interval = draw(st.sampled_from(("open", "open", "open", "finite", "empty")))
        tmin, tmax = 0.0, np.inf
        if interval == "finite":
            tmin = draw(st.floats(0.0, 1.0, width=32))
            tmax = tmin + draw(st.floats(0.0, 4.0, width=32))
        elif interval == "empty":
            tmin, tmax = 1.0, 0.5
        tmins.append(tmin)
        tmaxs.append(tmax)
    return RayBatch(np.array(origins), np.array(directions), np.array(tmins), np.array(tmaxs))


def _check(mesh: rayaccel.TriangleMesh, rays: RayBatch, builder: str, traversal: str,
           leaf: int) -> None:
    options = {"max_leaf_size": leaf} if reference.fine_options(builder) else {}
    accel = rayaccel.build(mesh, builder, **options)
    accel.validate()
    tri = reference.tri9(mesh)
    ref = reference.oracle(mesh, rays)
    closest = accel.trace(rays, traversal=traversal)
    reference.assert_closest_matches(tri, rays, closest, ref)
    reference.assert_any_matches(tri, rays, accel.trace(rays, query="any", traversal=traversal),
                                 ref)
    counted = accel.trace(rays, traversal=traversal, stats=True)
    reference.assert_hits_identical(closest, counted)
    reference.check_counter_invariants(rays, counted)


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
@given(data=st.data(), leaf=st.sampled_from((1, 2, 8)))
def test_random_meshes_match_oracle(builder, traversal, data, leaf):
    mesh = data.draw(meshes())
    rays = data.draw(ray_batches(mesh))
    _check(mesh, rays, builder, traversal, leaf)


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
@given(data=st.data())
def test_single_triangle(builder, traversal, data):
    mesh = data.draw(meshes(max_triangles=1))
    rays = data.draw(ray_batches(mesh))
    _check(mesh, rays, builder, traversal, 1)
    # The readable pure-Python oracle agrees wherever rounding cannot matter (the jitted
    # form may round the per-ray shear differently: fastmath 'arcp').
    py = reference.python_trace(reference.tri9(mesh), rays)
    ours = rayaccel.build(mesh, builder).trace(rays, traversal=traversal)
    clear = _clear_of_boundaries(mesh.triangles()[0], rays)
    assert np.array_equal(py.prim[clear], ours.prim[clear])


def _clear_of_boundaries(tri: np.ndarray, rays: RayBatch) -> np.ndarray:
    """Rays whose hit or miss on ``tri`` is decided by a margin (float64 barycentrics)."""
    a, b, c = tri.astype(np.float64)
    e1, e2 = b - a, c - a
    o, d = rays.origin.astype(np.float64), rays.direction.astype(np.float64)
    normal = np.cross(e1, e2)
    longest = max(np.dot(e1, e1), np.dot(e2, e2), np.dot(e2 - e1, e2 - e1))
    if not np.linalg.norm(normal) > 1e-3 * longest:  # a sliver: float32 forms may differ
        return ~rays.valid()
    with np.errstate(all="ignore"):
        p = np.cross(d, e2)
        det = p @ e1
        s = o - a
        u = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", q, d) / det
        t = (q @ e2) / det
        cos = np.abs(d @ normal) / (np.linalg.norm(d, axis=1) * np.linalg.norm(normal))
        margin = np.minimum(np.minimum(np.abs(u), np.abs(v)), np.abs(1 - u - v))
        span = np.maximum(np.abs(t), 1.0) * 1e-4
        clear = (cos > 1e-3) & (margin > 1e-4) & np.isfinite(t)
        clear &= (np.abs(t - rays.tmin) > span) & (np.abs(t - rays.tmax) > span)
    return clear | ~rays.valid()


@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
@given(
    data=st.data(),
    axis=st.integers(0, 2),
    sign=st.sampled_from((1.0, -1.0)),
    zeros=st.tuples(st.sampled_from((0.0, -0.0)), st.sampled_from((0.0, -0.0))),
)
def test_axis_parallel_rays(builder, traversal, data, axis, sign, zeros):
    """Directions with two zero components of either sign, from lattice points."""
    mesh = data.draw(meshes())
    lo, hi = mesh.bounds()
    n = 32
    origin = np.array([data.draw(point) for _ in range(n)])
    # Move some origins onto the mesh's box faces.
    on_face = np.array([data.draw(st.booleans()) for _ in range(n)])
    origin[on_face, axis] = lo[axis] if sign > 0 else hi[axis]
    direction = np.empty((n, 3))
    others = [k for k in range(3) if k != axis]
    direction[:, axis] = sign
    direction[:, others[0]], direction[:, others[1]] = zeros
    rays = RayBatch(origin, direction)
    _check(mesh, rays, builder, traversal, data.draw(st.sampled_from((1, 4))))


#: Node boxes are a bvh2 notion: origins inside them stress the hierarchy's box tests.
BVH2_PAIRS = [p for p in PAIRS if reference.structure_of(p.values[0]) == "bvh2"]


@pytest.mark.parametrize(("builder", "traversal"), BVH2_PAIRS)
@given(data=st.data())
def test_origins_inside_node_boxes(builder, traversal, data):
    """Rays starting inside (and on the faces of) the BVH's own node boxes."""
    mesh = data.draw(meshes())
    accel = rayaccel.build(mesh, builder, **reference.fine_options(builder))
    s = accel.structure
    nodes = [data.draw(st.integers(0, s.n_nodes - 1)) for _ in range(16)]
    lo, hi = s.node_lo[nodes].astype(np.float64), s.node_hi[nodes].astype(np.float64)
    frac = np.array([data.draw(st.tuples(*[st.sampled_from((0.0, 0.25, 0.5, 1.0))] * 3))
                     for _ in nodes])
    origin = lo + frac * (hi - lo)
    direction = np.array([data.draw(st.tuples(component, component, component))
                          for _ in nodes])
    assume(np.isfinite(origin).all())
    _check(mesh, RayBatch(origin, traceable(direction)), builder, traversal, 1)
