"""Rays aimed exactly at the shared edges and vertices of closed meshes (leak tests).

Shared by ``tests/test_leaks.py`` (the CI tier, a few thousand rays per case) and
``benchmarks/leak_test.py`` (over a million rays per case). Every ray made here
*must* hit the mesh, whatever the structure:

- **Targets** ``p`` lie on the shared edges and at the vertices of closed,
  consistently oriented components (every edge shared by exactly two triangles,
  once in each direction). An edge point is ``a + f·(b − a)`` for a dyadic fraction
  ``f``; it is chosen, where float32 allows, so that the float32 point lies
  *exactly* on the segment (checked with error-free float64 sums, see
  :func:`exact_sum`); otherwise it is the rounding of the true point.
- **Interior points** ``c``: from each triangle's centroid, half way to the first
  surface behind it along the inward normal; kept only when the generalised
  winding number there is ``±1`` (within 0.25) and the point is well away from the
  surface, so ``c`` is certainly inside.
- **Inside rays** start at ``c`` (of a triangle next to the target) and point at
  ``p``; **outside rays** start at ``o = p + s·(p − c)`` (``s`` a power of two) and
  point back at ``c``. A ray from a point of winding number ``±1`` to infinity, or
  from a point of winding number 0 to one of ``±1``, must cross the closed surface:
  a structure that misses it leaks. The origin is nudged by at most a rounding so
  that the ray passes *exactly* through ``p`` (``o + t·d = p`` in exact arithmetic)
  where float32 allows; :class:`LeakRays` records which rays are exact.

The float32 origin of an outside ray is classified by its winding number: outside
(``|w| < 0.25``) or not (then it is another inside ray: it still must hit).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import rayaccel
from rayaccel.bvh.geometry import winding_number
from rayaccel.rays.batch import RayBatch
from rayaccel.scene.mesh import TriangleMesh

#: Dyadic fractions tried along each edge, most exact-friendly first.
FRACTIONS = np.array(
    [1 / 2, 1 / 4, 3 / 4, 1 / 8, 3 / 8, 5 / 8, 7 / 8]
    + [k / 16 for k in (1, 3, 5, 7, 9, 11, 13, 15)]
    + [k / 64 for k in (1, 7, 19, 33, 45, 63)]
    + [1 / 1024, 1023 / 1024, 1 / 2**20]
)
#: Multipliers ``s`` of the outside origin ``p + s·(p − c)``.
OUTSIDE_SCALES = (1.0, 0.5, 2.0, 0.25)


# ------------------------------------------------------------------------- meshes


def torus(
    n_major: int = 48,
    n_minor: int = 24,
    major: float = 1.0,
    minor: float = 0.35,
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> TriangleMesh:
    """A closed, outward-oriented torus (genus 1: no point sees all of it)."""
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    u = 2 * np.pi * i / n_major
    v = 2 * np.pi * j / n_minor
    r = major + minor * np.cos(v)
    verts = np.stack([r * np.cos(u), r * np.sin(u), minor * np.sin(v)], axis=-1).reshape(-1, 3)
    idx = np.arange(n_major * n_minor).reshape(n_major, n_minor)
    a = idx
    b = np.roll(idx, -1, axis=0)
    c = np.roll(np.roll(idx, -1, axis=0), -1, axis=1)
    d = np.roll(idx, -1, axis=1)
    faces = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    )
    return TriangleMesh(verts + np.asarray(centre), faces, name="torus")


def jittered(mesh: TriangleMesh, scale: float, seed: int = 0) -> TriangleMesh:
    """``mesh`` with every vertex moved at random by up to ``scale`` (same topology)."""
    rng = np.random.default_rng(seed)
    v = mesh.vertices.astype(np.float64)
    v = v + rng.uniform(-scale, scale, v.shape)
    return TriangleMesh(v, mesh.faces, name=f"{mesh.name}-jittered")


def components(faces: np.ndarray) -> np.ndarray:
    """Label of each face's edge-connected component (faces sharing a vertex pair)."""
    f = faces.astype(np.int64)
    n = f.shape[0]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    face = np.tile(np.arange(n), 3)
    key = e[:, 0] * (int(f.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    same = key[order][1:] == key[order][:-1]
    a, b = face[order][:-1][same], face[order][1:][same]
    label = np.arange(n)
    while True:  # min-label propagation with pointer jumping: O(log n) rounds
        low = np.minimum(label[a], label[b])
        new = label.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        new = new[new]
        if np.array_equal(new, label):
            return label
        label = new


def closed_parts(mesh: TriangleMesh, name: str | None = None) -> TriangleMesh | None:
    """The closed, consistently oriented components of ``mesh`` as one mesh (or None).

    A component qualifies when each of its undirected edges is used by exactly two of
    its triangles, once in each direction (so it bounds a volume and its winding
    number is an integer off the surface), and no triangle is degenerate.
    """
    f = mesh.faces.astype(np.int64)
    n_v = mesh.n_vertices
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    und = np.sort(directed, axis=1)
    key = und[:, 0] * n_v + und[:, 1]
    _, inverse, count = np.unique(key, return_inverse=True, return_counts=True)
    # Consistent orientation: each undirected edge once per direction.
    forward = (directed[:, 0] < directed[:, 1]).astype(np.int64)
    n_forward = np.bincount(inverse, weights=forward, minlength=count.size)
    good_edge = (count == 2) & (n_forward == 1)
    tri = mesh.triangles().astype(np.float64)
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    bad_face = ~good_edge[inverse].reshape(3, -1).all(axis=0) | ~(area2 > 0)
    label = components(mesh.faces)
    bad_label = np.zeros(f.shape[0], dtype=bool)
    bad_label[label[bad_face]] = True
    keep = ~bad_label[label]
    if not keep.any():
        return None
    faces = f[keep]
    used, compact = np.unique(faces, return_inverse=True)
    return TriangleMesh(
        mesh.vertices[used], compact.reshape(-1, 3), name=name or f"{mesh.name}-closed"
    )


# --------------------------------------------------------------------- exactness


def exact_sum(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(a + b, exact)``: the float64 sum and whether it has no rounding error.

    Knuth's TwoSum: the error term is computed exactly, and is zero exactly when the
    float64 sum equals the real one.
    """
    s = a + b
    bb = s - a
    err = (a - (s - bb)) + (b - bb)
    return s, (err == 0) & np.isfinite(s)


def is_float32(x: np.ndarray) -> np.ndarray:
    """Whether each float64 value is exactly a float32 value."""
    with np.errstate(over="ignore"):
        return x.astype(np.float32).astype(np.float64) == x


# ---------------------------------------------------------------------- targets


@dataclass
class Targets:
    """Points on the surface, each with the triangle whose interior point aims at it."""

    point: np.ndarray  # (n, 3) float32
    face: np.ndarray  # (n,) int64: a triangle containing the point
    exact: np.ndarray  # (n,) bool: the float32 point is exactly on the edge / a vertex
    kind: np.ndarray  # (n,) int8: 0 vertex, 1 edge


def _lattice_steps(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``(step, g, unit)`` with ``b − a = g·step·unit`` exactly, per edge.

    ``unit`` is the finest float32 spacing among the edge's nonzero coordinates (a
    power of two), ``b − a`` in units of it is an integer vector whose gcd is ``g``:
    every float32 point exactly on the segment (in a region of uniform spacing) is
    ``a + k·step·unit`` for some ``0 < k < g``. ``g = 1`` where that fails (integers
    past 2**53, zero edges).
    """
    coords = np.concatenate([a, b], axis=1).astype(np.float32)
    spacing = np.spacing(np.abs(coords)).astype(np.float64)
    spacing = np.where(coords != 0, spacing, np.inf)
    unit = spacing.min(axis=1)
    unit = np.where(np.isfinite(unit), unit, 1.0)
    diff, ok = exact_sum(b, -a)
    units = diff / unit[:, None]
    ok = ok.all(axis=1) & (np.abs(units) < 2.0**53).all(axis=1)
    ok &= (units == np.round(units)).all(axis=1)
    d_int = np.where(ok[:, None], np.round(units), 0).astype(np.int64)
    g = np.gcd.reduce(np.abs(d_int), axis=1)
    g = np.where(ok & (g > 0), g, 1)
    step = d_int // g[:, None]
    return step, g, unit


def edge_targets(mesh: TriangleMesh, per_edge: int, rng: np.random.Generator) -> Targets:
    """``per_edge`` points on every shared edge, for each of its two triangles.

    Points exactly on the segment in float32 are taken where any exist: dyadic
    fractions (:data:`FRACTIONS`) and random lattice points ``a + k·(b − a)/g``
    (:func:`_lattice_steps`), each checked to be free of rounding. An edge with too
    few is completed with the float32 rounding of the point at a random fraction.
    """
    f = mesh.faces.astype(np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    face = np.tile(np.arange(f.shape[0]), 3)
    # One row per directed edge: each shared edge appears once from each triangle,
    # always parametrised from its lower vertex index (the same points for both).
    lo_first = directed[:, 0] < directed[:, 1]
    a_idx = np.where(lo_first, directed[:, 0], directed[:, 1])
    b_idx = np.where(lo_first, directed[:, 1], directed[:, 0])
    a = mesh.vertices[a_idx].astype(np.float64)
    b = mesh.vertices[b_idx].astype(np.float64)
    n_e = a.shape[0]
    diff, ok_diff = exact_sum(b, -a)
    points, exact = [], []
    for frac in FRACTIONS:
        p, ok = exact_sum(a, frac * diff)
        points.append(p)
        exact.append((ok & ok_diff & is_float32(p)).all(axis=1))
    step, g, unit = _lattice_steps(a, b)
    for _ in range(2 * per_edge):
        k = rng.integers(1, np.maximum(g, 2))
        offset = (k[:, None] * step).astype(np.float64) * unit[:, None]
        p, ok = exact_sum(a, offset)
        ok &= is_float32(p) & (g > 1)[:, None]
        points.append(p)
        exact.append(ok.all(axis=1))
    cand = np.stack(points, axis=1)  # (E, M, 3)
    ok = np.stack(exact, axis=1)  # (E, M)
    # Exact candidates first, then (distinct) random ones.
    m = ok.shape[1]
    rank = np.where(ok, rng.random((n_e, m)), 1.0 + np.arange(m))
    order = np.argsort(rank, axis=1, kind="stable")[:, :per_edge]
    rows = np.arange(n_e)[:, None]
    chosen = cand[rows, order]
    chosen_exact = ok[rows, order]
    rand = rng.uniform(0.05, 0.95, (n_e, per_edge, 1))
    fallback = a[:, None, :] + rand * (b - a)[:, None, :]
    chosen = np.where(chosen_exact[:, :, None], chosen, fallback)
    return Targets(
        chosen.reshape(-1, 3).astype(np.float32),
        np.repeat(face, per_edge),
        chosen_exact.ravel(),
        np.ones(n_e * per_edge, dtype=np.int8),
    )


def vertex_targets(mesh: TriangleMesh) -> Targets:
    """Every vertex, once for each triangle around it (always exact)."""
    f = mesh.faces.astype(np.int64)
    return Targets(
        mesh.vertices[f.ravel()],
        np.repeat(np.arange(f.shape[0]), 3),
        np.ones(f.size, dtype=bool),
        np.zeros(f.size, dtype=np.int8),
    )


# -------------------------------------------------------------------- interiors


def interior_points(mesh: TriangleMesh, accel: rayaccel.Accel) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(c, ok)``: a certainly interior float32 point per triangle, and which are.

    ``accel`` is any BVH accel over ``mesh`` (used for one ray per triangle, the
    winding numbers and the distances; the rays made from these points are then
    checked against every structure, and against the brute-force oracle in the tests).
    """
    tri = mesh.triangles().astype(np.float64)
    centroid = tri.mean(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    size = np.sqrt(np.linalg.norm(normal, axis=1))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    inward = -normal  # closed_parts keeps outward or inward components: fixed below
    # The first surface behind the triangle, along either normal; inside is where
    # the winding number is ±1.
    points = np.empty_like(centroid, dtype=np.float32)
    ok = np.zeros(centroid.shape[0], dtype=bool)
    for sign in (1.0, -1.0):
        todo = ~ok
        if not todo.any():
            break
        d = sign * inward[todo]
        rays = RayBatch(centroid[todo], d, tmin=1e-3 * size[todo])
        hit = accel.trace(rays)
        depth = np.where(np.isfinite(hit.t), hit.t, 0.0).astype(np.float64)
        c = (centroid[todo] + d * depth[:, None] / 2).astype(np.float32)
        c64 = c.astype(np.float64)
        w = winding_number(accel.structure, accel.mesh, c64)
        dist = accel.compute_distance(c64)
        good = (depth > 0) & (np.abs(np.abs(w) - 1.0) < 0.25)
        good &= dist > np.maximum(1e-3 * size[todo], 1e-5 * np.abs(c64).max(axis=1))
        idx = np.flatnonzero(todo)
        points[idx[good]] = c[good]
        ok[idx[good]] = True
    return points, ok


# ------------------------------------------------------------------------- rays


@dataclass
class LeakRays:
    """A ray set that must hit everywhere, with what each ray is aimed at."""

    name: str
    rays: RayBatch
    exact: np.ndarray  # (n,) bool: target exactly on the surface and ray exactly through it
    target_kind: np.ndarray  # (n,) int8: 0 vertex, 1 edge
    outside: np.ndarray  # (n,) bool: origin of winding number 0
    dropped: dict[str, int] = field(default_factory=dict)

    @property
    def n_rays(self) -> int:
        return self.rays.n_rays

    def subset(self, index: np.ndarray) -> LeakRays:
        return LeakRays(
            self.name,
            self.rays.subset(index),
            self.exact[index],
            self.target_kind[index],
            self.outside[index],
            dict(self.dropped),
        )


def _through(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A float32 ray from about ``q`` through ``p``: ``(origin, direction, exact)``.

    Two ways to make ``o + 1·d = p`` hold exactly, each moving the origin by at most
    a few float32 spacings: round ``d = p − q`` to float32 and start at ``p − d``;
    or round ``q`` to a grid as coarse as ``p``'s and ``q``'s spacings, so that
    ``d = p − o`` is a float32 value. Where neither is exact, the ray goes from the
    float32 rounding of ``q`` towards ``p`` as closely as rounding allows.
    """
    p64 = p.astype(np.float64)
    q64 = q.astype(np.float64)
    # A: exact direction first, origin p − d.
    d_a = (p64 - q64).astype(np.float32).astype(np.float64)
    o_a, ok = exact_sum(p64, -d_a)
    exact_a = (ok & is_float32(o_a)).all(axis=1)
    # B: the origin on a coarse grid, direction p − o.
    grid = np.maximum(
        np.spacing(np.abs(p).astype(np.float32)), np.spacing(np.abs(q64).astype(np.float32))
    ).astype(np.float64)
    o_b = np.round(q64 / grid) * grid
    d_b, ok = exact_sum(p64, -o_b)
    exact_b = (ok & is_float32(o_b) & is_float32(d_b)).all(axis=1)
    # Otherwise: from the rounded q, aimed at p.
    o_c = q64.astype(np.float32).astype(np.float64)
    d_c = (p64 - o_c).astype(np.float32).astype(np.float64)
    origin = np.where(exact_a[:, None], o_a, np.where(exact_b[:, None], o_b, o_c))
    direction = np.where(exact_a[:, None], d_a, np.where(exact_b[:, None], d_b, d_c))
    return origin.astype(np.float32), direction.astype(np.float32), exact_a | exact_b


def leak_rays(
    mesh: TriangleMesh,
    per_edge: int = 2,
    seed: int = 0,
    accel: rayaccel.Accel | None = None,
    name: str | None = None,
) -> LeakRays:
    """Inside and outside rays at every vertex and ``per_edge`` points of every edge.

    ``mesh`` may hold open parts too: only its closed parts (:func:`closed_parts`)
    are aimed at, but the rays are traced against the whole mesh.
    """
    rng = np.random.default_rng(seed)
    closed = closed_parts(mesh)
    if closed is None:
        raise ValueError(f"{mesh.name}: no closed, consistently oriented part")
    accel = (
        accel
        if accel is not None and accel.mesh is closed
        else rayaccel.build(closed, "bvh2.binned_sah")
    )
    interior, ok = interior_points(closed, accel)
    targets = [vertex_targets(closed), edge_targets(closed, per_edge, rng)]
    point = np.concatenate([t.point for t in targets])
    face = np.concatenate([t.face for t in targets])
    on_exact = np.concatenate([t.exact for t in targets])
    kind = np.concatenate([t.kind for t in targets])
    keep = ok[face]
    dropped = {"targets without an interior point": int((~keep).sum())}
    point, face, on_exact, kind = point[keep], face[keep], on_exact[keep], kind[keep]
    c = interior[face]
    # Inside: from c through p.
    o_in, d_in, ex_in = _through(point, c)
    # Outside: from p + s·(p − c) back through p towards c.
    s = np.asarray(OUTSIDE_SCALES)[rng.integers(0, len(OUTSIDE_SCALES), point.shape[0])]
    far = point.astype(np.float64) + s[:, None] * (point.astype(np.float64) - c)
    o_out, d_out, ex_out = _through(point, far)
    w = winding_number(accel.structure, accel.mesh, o_out.astype(np.float64))
    outside = np.abs(w) < 0.25
    origin = np.concatenate([o_in, o_out])
    direction = np.concatenate([d_in, d_out])
    zero = ~np.any(direction != 0, axis=1)
    dropped["zero directions"] = int(zero.sum())
    live = ~zero
    rays = RayBatch(origin[live], direction[live])
    exact = np.concatenate([ex_in & on_exact, ex_out & on_exact])[live]
    return LeakRays(
        name or mesh.name,
        rays,
        exact,
        np.concatenate([kind, kind])[live],
        np.concatenate([np.zeros(point.shape[0], dtype=bool), outside])[live],
        dropped,
    )


# ------------------------------------------------------------------------ cases


def leak_cases() -> list[tuple[str, str]]:
    """``(build key, traversal)`` pairs: every traversal on its structure's default
    builder, and every builder with its structure's default traversal."""
    from rayaccel import registry

    cases = []
    for builder in registry.keys("builder"):
        structure = registry.get(builder, "builder").structure
        default_builder = registry.default_builder(structure)
        for traversal in registry.keys("traversal"):
            if registry.get(traversal, "traversal").structure != structure:
                continue
            if builder == default_builder or traversal == registry.default_traversal(structure):
                cases.append((builder, traversal))
    return cases


def misses(accel: rayaccel.Accel, rays: RayBatch, traversal: str, query: str) -> np.ndarray:
    """Indices of the rays that ``accel`` misses with ``traversal`` and ``query``."""
    hits = accel.trace(rays, query=query, traversal=traversal)
    return np.flatnonzero(hits.prim < 0)
