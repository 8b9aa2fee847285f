"""Oracles, comparison helpers, test meshes and ray sets shared by the test suite.

The oracle is :func:`rayaccel.kernels.brute_force.brute_force_trace`: every ray against
every triangle with the *same* watertight triangle test the structures use, so a
correct structure returns the oracle's closest ``t`` bit for bit and the same
primitive except at exact ties. :func:`python_trace` is the slow, readable form of
the same thing (pure Python over ``ray_triangle_py``) for a handful of rays, and
:func:`mt_float64` is an independent float64 Möller–Trumbore reference used only
for sanity checks away from edges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_kernel
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.counters import COUNTER_NAMES
from rayaccel.kernels.brute_force import brute_force_trace
from rayaccel.kernels.triangle import (
    ray_triangle,
    ray_triangle_py,
    ray_triangle_setup,
    ray_triangle_setup_py,
)
from rayaccel.queries import QUERIES
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene.mesh import TriangleMesh


def structure_of(build_key: str) -> str:
    """The structure a build key (``builder[+step...]``) makes."""
    from rayaccel import registry

    return registry.get_chain(build_key)[0].structure


def is_default_builder(build_key: str) -> bool:
    """Whether ``build_key`` is its structure's default builder (no steps chained)."""
    from rayaccel import registry

    return build_key == registry.default_builder(structure_of(build_key))


def is_core_pair(build_key: str, traversal: str) -> bool:
    """The core pairs of each structure (from the registry's ``default=True`` variants):
    every build key with the structure's default traversal, and every traversal on the
    default builder's tree. Other pairs carry the ``cross`` mark (run with ``--full``)."""
    from rayaccel import registry

    structure = structure_of(build_key)
    return is_default_builder(build_key) or traversal == registry.default_traversal(structure)


def parallel_variants(traversal: str, full: bool) -> list[tuple[str, bool]]:
    """``(query, stats)`` variants whose parallel kernels a test compiles for ``traversal``.

    A traversal's parallel kernels differ from its serial ones only in the ``prange``
    around the shared chunk worker (:mod:`rayaccel.trace.skeleton`), and each still
    costs a few seconds to compile on a cold cache. The default tier runs all four for
    each structure's default traversal and the plain closest-hit one for the others;
    ``--full`` runs all four everywhere.
    """
    from rayaccel import registry

    every = [(q, s) for q in ("closest", "any") for s in (False, True)]
    structure = traversal.split(".")[0]
    if full or traversal == registry.default_traversal(structure):
        return every
    return [("closest", False)]


def fine_options(build_key: str) -> dict:
    """Options that make ``build_key``'s structure as fine as it goes, for stress tests:
    one primitive per leaf for hierarchies (``max_leaf_size=1``); none for grids."""
    import dataclasses

    from rayaccel import registry

    fields = {f.name for f in dataclasses.fields(registry.get_chain(build_key)[0].options)}
    return {"max_leaf_size": 1} if "max_leaf_size" in fields else {}


#: File scenes of over half a million triangles: only ``registry.DEFAULT_BUILD_KEY`` with its
#: default traversal runs there in the default tier.
BIG_FILE_SCENES = ("kitchen", "salle_de_bain")


def file_scene_marks(build_key: str, scene: str, traversal: str | None = None) -> list:
    """``[pytest.mark.cross]`` unless ``build_key`` (and ``traversal``) run on ``scene`` by default.

    File scenes add size, not shapes: every build key's tree shapes are checked on the
    procedural scenes, so the default tier builds only each structure's default tree on
    the file scenes, and on the big ones only the default BVH with its default
    traversal (every traversal's layout over 0.65M and 1.4M triangles, the perfect hash's
    included, cost CI minutes); ``--full`` runs every case. Building each of the
    sixteen keys over the medium file scenes was most of CI's time on two cores.
    """
    import pytest

    from conftest import FILE_SCENES
    from rayaccel import registry

    if scene not in FILE_SCENES:
        return []
    if scene in BIG_FILE_SCENES:
        kept = build_key == registry.DEFAULT_BUILD_KEY and traversal in (
            None, registry.default_traversal(structure_of(build_key)),
        )  # fmt: skip
    else:
        kept = is_default_builder(build_key)
    return [] if kept else [pytest.mark.cross]


def builder_traversal_pairs() -> list:
    """``pytest.param(builder, traversal)`` for every registered builder and traversal of
    its structure; pairs outside the core ones are marked ``cross``."""
    import pytest

    from rayaccel import registry

    params = []
    for builder in registry.variants("builder"):
        for traversal in registry.keys("traversal", builder.structure):
            marks = [] if is_core_pair(builder.key, traversal) else [pytest.mark.cross]
            params.append(
                pytest.param(builder.key, traversal, id=f"{builder.key}-{traversal}", marks=marks)
            )
    return params


# --------------------------------------------------------------------------------- oracles


def tri9(mesh: TriangleMesh) -> np.ndarray:
    """Return the ``(F, 9)`` float32 corner rows the oracle takes."""
    return mesh.hit_rows()


def oracle(mesh: TriangleMesh, rays: RayBatch, query: str = "closest") -> HitBatch:
    """Brute-force hits of ``rays`` (lowest primitive index wins exact ties)."""
    t, prim, u, v = brute_force_trace(
        tri9(mesh), rays.origin, rays.direction, rays.tmin, rays.tmax, QUERIES[query]
    )
    return HitBatch(t, prim, u, v)


@cpu_kernel()
def _eval_prims_kernel(tri, origin, direction, tmin, tmax, prim, out_t, out_u, out_v):
    """Test ray ``r`` against triangle ``prim[r]`` only, exactly as the oracle would."""
    for r in range(origin.shape[0]):
        p = prim[r]
        dx = direction[r, 0]
        dy = direction[r, 1]
        dz = direction[r, 2]
        if p < 0 or not (tmin[r] <= tmax[r]) or (dx == 0 and dy == 0 and dz == 0):
            continue
        if not (np.isfinite(dx) and np.isfinite(dy) and np.isfinite(dz)):
            continue
        kx, ky, kz, Sx, Sy, Sz = ray_triangle_setup(dx, dy, dz)
        upper = np.nextafter(tmax[r], np.float32(np.inf))
        t, u, v = ray_triangle(
            tri,
            p,
            origin[r, kx],
            origin[r, ky],
            origin[r, kz],
            kx,
            ky,
            kz,
            Sx,
            Sy,
            Sz,
            tmin[r],
            upper,
        )
        out_t[r] = t
        out_u[r] = u
        out_v[r] = v


def eval_prims(tri: np.ndarray, rays: RayBatch, prim: np.ndarray) -> HitBatch:
    """Return the hit of every ray on its own triangle ``prim[r]`` (inf where none)."""
    n = rays.n_rays
    t = np.full(n, np.inf, dtype=np.float32)
    u = np.zeros(n, dtype=np.float32)
    v = np.zeros(n, dtype=np.float32)
    prim = np.ascontiguousarray(prim, dtype=np.int32)
    _eval_prims_kernel(tri, rays.origin, rays.direction, rays.tmin, rays.tmax, prim, t, u, v)
    return HitBatch(t, np.where(np.isfinite(t), prim, -1).astype(np.int32), u, v)


def python_trace(tri: np.ndarray, rays: RayBatch) -> HitBatch:
    """Readable pure-Python closest-hit oracle over ``ray_triangle_py`` (a few rays only)."""
    n = rays.n_rays
    out = HitBatch.empty(n)
    f32 = np.float32
    for r in range(n):
        d = [f32(x) for x in rays.direction[r]]
        o = [f32(x) for x in rays.origin[r]]
        lo, hi = f32(rays.tmin[r]), f32(rays.tmax[r])
        if not lo <= hi or d == [0, 0, 0] or not all(math.isfinite(x) for x in d):
            continue
        kx, ky, kz, Sx, Sy, Sz = ray_triangle_setup_py(*d)
        best = np.nextafter(hi, f32(np.inf))
        for p in range(tri.shape[0]):
            t, u, v = ray_triangle_py(tri, p, o[kx], o[ky], o[kz], kx, ky, kz, Sx, Sy, Sz, lo, best)
            if t < best:
                best = t
                out.t[r], out.prim[r], out.u[r], out.v[r] = t, p, u, v
    return out


def mt_float64(tri: np.ndarray, rays: RayBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest hit by float64 Möller–Trumbore; returns ``(t, prim, edge_margin)``.

    ``edge_margin`` is the smallest barycentric of the reported hit relative to 1
    (small means the hit is near an edge, where float32 tests may legitimately
    disagree with this one).
    """
    a = tri[:, 0:3].astype(np.float64)
    e1 = tri[:, 3:6].astype(np.float64) - a
    e2 = tri[:, 6:9].astype(np.float64) - a
    n = rays.n_rays
    best_t = np.full(n, np.inf)
    best_p = np.full(n, -1, dtype=np.int64)
    margin = np.full(n, np.inf)
    o = rays.origin.astype(np.float64)
    d = rays.direction.astype(np.float64)
    for start in range(0, n, 256):
        sl = slice(start, start + 256)
        oo, dd = o[sl, None, :], d[sl, None, :]
        p = np.cross(dd, e2[None])
        det = np.einsum("rfk,fk->rf", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = oo - a[None]
            u = np.einsum("rfk,rfk->rf", s, p) * inv
            q = np.cross(s, e1[None])
            v = np.einsum("rfk,rk->rf", q, d[sl]) * inv
            t = np.einsum("rfk,fk->rf", q, e2) * inv
        ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)
        ok &= (t >= rays.tmin[sl, None]) & (t <= rays.tmax[sl, None])
        t = np.where(ok, t, np.inf)
        arg = np.argmin(t, axis=1)
        rows = np.arange(t.shape[0])
        best_t[sl] = t[rows, arg]
        hit = np.isfinite(best_t[sl])
        best_p[sl] = np.where(hit, arg, -1)
        m = np.minimum(np.minimum(u, v), 1.0 - u - v)[rows, arg]
        margin[sl] = np.where(hit, m, np.inf)
    return best_t, best_p, margin


# ----------------------------------------------------------------------------- comparison


@dataclass
class Agreement:
    """What a comparison with the oracle found (all counts of rays)."""

    n_rays: int = 0
    n_hits: int = 0
    n_ties: int = 0
    n_near_ties: int = 0


#: Closest hits on different primitives may differ by this many float32 ulps of ``t``:
#: coplanar triangles crossed at one point get ``t`` values a rounding apart, and a box
#: whose (rounded) entry distance lies beyond the nearer one may be culled.
NEAR_TIE_ULPS = 16


def assert_closest_matches(
    tri: np.ndarray, rays: RayBatch, ours: HitBatch, ref: HitBatch, label: str = ""
) -> Agreement:
    """Assert a closest-hit result equals the oracle's, allowing only (near-)ties.

    Same hit mask; on a miss ``t = inf, prim = -1, u = v = 0``; on the oracle's
    primitive the same ``t, u, v`` bit for bit. Where the primitive differs (a tie),
    our primitive must really be hit at exactly our ``t`` with our barycentrics
    (re-tested alone with the oracle's triangle test), our ``t`` must not be nearer
    than the oracle's (the oracle is the minimum), and it may be farther by at most
    :data:`NEAR_TIE_ULPS` ulps.
    """
    where = f" [{label}]" if label else ""
    hit = ref.prim >= 0
    bad = np.flatnonzero((ours.prim >= 0) != hit)
    assert bad.size == 0, (
        f"{bad.size} rays disagree with the oracle on hit/miss{where}; first ray {bad[0]}: "
        f"o={rays.origin[bad[0]].tolist()} d={rays.direction[bad[0]].tolist()} "
        f"tmin={rays.tmin[bad[0]]!r} tmax={rays.tmax[bad[0]]!r} ours (t={ours.t[bad[0]]!r}, "
        f"prim={ours.prim[bad[0]]}) oracle (t={ref.t[bad[0]]!r}, prim={ref.prim[bad[0]]})"
    )
    miss = ~hit
    assert np.all(np.isposinf(ours.t[miss])), f"a miss has finite t{where}"
    assert np.all(ours.prim[miss] == -1), f"a miss has prim != -1{where}"
    assert np.all(ours.u[miss] == 0), f"miss with u/v{where}"
    assert np.all(ours.v[miss] == 0), f"miss with u/v{where}"
    same = ours.prim == ref.prim
    for name in ("t", "u", "v"):
        x, y = getattr(ours, name)[same], getattr(ref, name)[same]
        bad = np.flatnonzero(x.view(np.int32) != y.view(np.int32))
        assert bad.size == 0, (
            f"{bad.size} rays hit the oracle's prim with a different {name}{where}; first: "
            f"ours {x[bad[0]]!r} oracle {y[bad[0]]!r}"
        )
    ties = np.flatnonzero(~same)
    n_near = 0
    if ties.size:
        again = eval_prims(tri, rays.subset(ties), ours.prim[ties])
        for name in ("t", "u", "v"):
            x, y = getattr(again, name), getattr(ours, name)[ties]
            wrong = np.flatnonzero(x.view(np.int32) != y.view(np.int32))
            assert wrong.size == 0, (
                f"ray {ties[wrong[0]]}: our prim {ours.prim[ties[wrong[0]]]} re-tested gives "
                f"{name}={x[wrong[0]]!r}, reported {y[wrong[0]]!r}{where}"
            )
        t_ours, t_ref = ours.t[ties], ref.t[ties]
        nearer = np.flatnonzero(t_ours < t_ref)
        assert nearer.size == 0, f"ray {ties[nearer[0]]}: nearer than the oracle{where}"
        gap = (t_ours.astype(np.float64) - t_ref) / np.spacing(np.abs(t_ref))
        far = np.flatnonzero(gap > NEAR_TIE_ULPS)
        assert far.size == 0, (
            f"ray {ties[far[0]]}: prim {ours.prim[ties[far[0]]]} at t={t_ours[far[0]]!r} but "
            f"the oracle's prim {ref.prim[ties[far[0]]]} is nearer at t={t_ref[far[0]]!r} "
            f"({gap[far[0]]:.0f} ulps){where}"
        )
        n_near = int(np.count_nonzero(gap > 0))
    return Agreement(rays.n_rays, int(hit.sum()), int(ties.size) - n_near, n_near)


def assert_any_matches(
    tri: np.ndarray, rays: RayBatch, ours: HitBatch, ref_closest: HitBatch, label: str = ""
) -> None:
    """Assert an any-hit result: same hit mask as the closest hit, and a genuine hit."""
    where = f" [{label}]" if label else ""
    hit = ref_closest.prim >= 0
    bad = np.flatnonzero((ours.prim >= 0) != hit)
    assert bad.size == 0, (
        f"{bad.size} any-hit answers differ from the oracle's hit mask{where}; first ray "
        f"{bad[0]}: o={rays.origin[bad[0]].tolist()} d={rays.direction[bad[0]].tolist()}"
    )
    assert np.all(np.isposinf(ours.t[~hit]))
    assert np.all(ours.prim[~hit] == -1)
    rows = np.flatnonzero(hit)
    again = eval_prims(tri, rays.subset(rows), ours.prim[rows])
    wrong = np.flatnonzero(again.t.view(np.int32) != ours.t[rows].view(np.int32))
    assert wrong.size == 0, (
        f"ray {rows[wrong[0]]}: any-hit prim {ours.prim[rows[wrong[0]]]} re-tested gives "
        f"t={again.t[wrong[0]]!r}, reported t={ours.t[rows[wrong[0]]]!r}{where}"
    )
    assert np.all(ours.t[rows] >= rays.tmin[rows])
    assert np.all(ours.t[rows] <= rays.tmax[rows])
    assert np.array_equal(again.u, ours.u[rows])
    assert np.array_equal(again.v, ours.v[rows])


def assert_hits_identical(a: HitBatch, b: HitBatch, label: str = "") -> None:
    """Assert two results are bit-identical (t, prim, u, v)."""
    for name in ("t", "prim", "u", "v"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, f"{name} dtype/shape [{label}]"
        assert x.shape == y.shape, f"{name} dtype/shape [{label}]"
        assert x.tobytes() == y.tobytes(), f"{name} differs on {int(np.sum(x != y))} rays [{label}]"


def check_counter_invariants(rays: RayBatch, hits: HitBatch) -> None:
    """Assert counter invariants every traversal must satisfy."""
    stats = hits.stats
    assert stats is not None
    assert tuple(stats) == COUNTER_NAMES
    n = rays.n_rays
    for name, column in stats.items():
        assert column.dtype == np.int32, name
        assert column.shape == (n,), name
        assert (column >= 0).all(), f"negative {name}"
    hit = hits.prim >= 0
    assert (stats["prim_tests"][hit] >= 1).all(), "a hit with no primitive test"
    # Hierarchies enter nodes, grids walk cells: a hit needs one or the other.
    walked = stats["nodes"] + stats["cells"]
    assert (walked[hit] >= 1).all(), "a hit with no node entered or cell visited"
    entered = hit & (stats["nodes"] > 0)
    assert (stats["box_tests"][entered] >= 1).all(), "a hit in a hierarchy with no box test"
    assert (stats["bytes"][hit] > 0).all(), "a hit that fetched nothing"
    assert stats["prim_tests"].sum() >= hit.sum()
    invalid = ~rays.valid()
    for name, column in stats.items():
        assert (column[invalid] == 0).all(), f"an invalid ray has {name} > 0"


def check_stack_counters(bvh, rays: RayBatch, closest: HitBatch, any_hit: HitBatch) -> None:
    """Invariants specific to ``bvh2.stack`` (one step per node, two box tests per inner)."""
    from rayaccel.bvh.layouts.bvh2 import STACK_SIZE

    for hits in (closest, any_hit):
        s = hits.stats
        assert s is not None
        valid = rays.valid()
        assert np.array_equal(s["steps"], s["nodes"])
        # The root box test plus two per inner node visited.
        inner = (s["box_tests"] - 1) // 2
        assert (s["box_tests"][valid] % 2 == 1).all()
        assert (inner[valid] <= s["nodes"][valid]).all()
        assert (s["stack_peak"] <= min(STACK_SIZE, bvh.depth())).all()
        leaves = s["nodes"] - np.where(valid, inner, 0)
        assert (s["prim_tests"] <= leaves * int(bvh.node_count.max())).all()
    # Any-hit is a prefix of the closest-hit traversal.
    for name in COUNTER_NAMES:
        assert (any_hit.stats[name] <= closest.stats[name]).all(), name


# --------------------------------------------------------------------------- test meshes


def icosphere(
    subdivisions: int = 2, radius: float = 1.0, centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> TriangleMesh:
    """A closed icosphere; every edge is shared by exactly two triangles."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [
        (-1, t, 0),
        (1, t, 0),
        (-1, -t, 0),
        (1, -t, 0),
        (0, -1, t),
        (0, 1, t),
        (0, -1, -t),
        (0, 1, -t),
        (t, 0, -1),
        (t, 0, 1),
        (-t, 0, -1),
        (-t, 0, 1),
    ]
    faces = [
        (0, 11, 5),
        (0, 5, 1),
        (0, 1, 7),
        (0, 7, 10),
        (0, 10, 11),
        (1, 5, 9),
        (5, 11, 4),
        (11, 10, 2),
        (10, 7, 6),
        (7, 1, 8),
        (3, 9, 4),
        (3, 4, 2),
        (3, 2, 6),
        (3, 6, 8),
        (3, 8, 9),
        (4, 9, 5),
        (2, 4, 11),
        (6, 2, 10),
        (8, 6, 7),
        (9, 8, 1),
    ]
    v = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in verts]
    f = list(faces)
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(i: int, j: int, v=v, cache=cache) -> int:
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = v[i] + v[j]
                v.append(m / np.linalg.norm(m))
                cache[key] = len(v) - 1
            return cache[key]

        nf = []
        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = nf
    vertices = np.array(v) * radius + np.asarray(centre)
    return TriangleMesh(vertices, np.array(f), name=f"icosphere{subdivisions}")


def uv_sphere(n_lat: int = 12, n_lon: int = 24, radius: float = 1.0) -> TriangleMesh:
    """A closed UV sphere with poles (fans at the poles, quads split in two)."""
    verts = [(0.0, 0.0, radius)]
    for i in range(1, n_lat):
        theta = math.pi * i / n_lat
        for j in range(n_lon):
            phi = 2 * math.pi * j / n_lon
            verts.append(
                (
                    radius * math.sin(theta) * math.cos(phi),
                    radius * math.sin(theta) * math.sin(phi),
                    radius * math.cos(theta),
                )
            )
    verts.append((0.0, 0.0, -radius))
    south = len(verts) - 1

    def ring(i: int, j: int) -> int:
        return 1 + (i - 1) * n_lon + j % n_lon

    faces = [(0, ring(1, j), ring(1, j + 1)) for j in range(n_lon)]
    for i in range(1, n_lat - 1):
        for j in range(n_lon):
            a, b = ring(i, j), ring(i, j + 1)
            c, d = ring(i + 1, j), ring(i + 1, j + 1)
            faces += [(a, c, d), (a, d, b)]
    faces += [(south, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)) for j in range(n_lon)]
    return TriangleMesh(np.array(verts), np.array(faces), name="uv_sphere")


def cube(lo: float = -1.0, hi: float = 1.0) -> TriangleMesh:
    """A closed axis-aligned cube of 12 triangles (each face split on a diagonal)."""
    c = np.array([[x, y, z] for x in (lo, hi) for y in (lo, hi) for z in (lo, hi)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [f for a, b, cc, d in quads for f in ((a, b, cc), (a, cc, d))]
    return TriangleMesh(c, np.array(faces), name="cube")


def grid_plane(n: int = 8, z: float = 0.0) -> TriangleMesh:
    """An ``n × n`` grid of unit quads in the plane ``z``, two triangles each."""
    xs = np.arange(n + 1, dtype=np.float64)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    verts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, (i + 1) * (n + 1) + j
            faces += [(a, b, b + 1), (a, b + 1, a + 1)]
    return TriangleMesh(verts, np.array(faces), name=f"grid{n}")


def edges_of(mesh: TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Return the unique undirected edges ``(E, 2)`` and how many faces share each."""
    f = mesh.faces.astype(np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e.sort(axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    return edges, counts


def is_closed(mesh: TriangleMesh) -> bool:
    """Whether every edge is shared by exactly two triangles."""
    return bool(np.all(edges_of(mesh)[1] == 2))


# ------------------------------------------------------------------------------- ray sets


def random_unit(rng: np.random.Generator, n: int) -> np.ndarray:
    """``(n, 3)`` float64 unit vectors, uniform on the sphere."""
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def rays_inside(lo, hi, n: int, seed: int) -> RayBatch:
    """Rays from uniform points inside the box ``[lo, hi]``, uniform directions."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    o = lo + rng.random((n, 3)) * (hi - lo)
    return RayBatch(o, random_unit(rng, n))


def rays_outside(lo, hi, n: int, seed: int) -> RayBatch:
    """Rays from a sphere around the box towards random points inside it."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre, radius = (lo + hi) / 2, max(np.linalg.norm(hi - lo), 1e-3)
    o = centre + 1.5 * radius * random_unit(rng, n)
    target = lo + rng.random((n, 3)) * (hi - lo)
    return RayBatch(o, target - o)


def rays_intervals(lo, hi, n: int, seed: int) -> RayBatch:
    """Rays from inside with random finite ``[tmin, tmax]`` (some empty: ``tmin > tmax``)."""
    base = rays_inside(lo, hi, n, seed)
    rng = np.random.default_rng(seed + 1)
    size = float(np.linalg.norm(np.asarray(hi, np.float64) - np.asarray(lo, np.float64)))
    tmin = rng.random(n) * 0.3 * size
    tmax = tmin + (rng.random(n) - 0.1) * 0.6 * size
    return RayBatch(base.origin, base.direction * np.float32(2.0), tmin, tmax)


def concat(*batches: RayBatch) -> RayBatch:
    """Concatenate ray batches."""
    return RayBatch(
        np.concatenate([b.origin for b in batches]),
        np.concatenate([b.direction for b in batches]),
        np.concatenate([b.tmin for b in batches]),
        np.concatenate([b.tmax for b in batches]),
    )


def subsample(rays: RayBatch, n: int, seed: int = 0) -> RayBatch:
    """Return at most ``n`` rays chosen at random (kept in order)."""
    if rays.n_rays <= n:
        return rays
    rng = np.random.default_rng(seed)
    return rays.subset(np.sort(rng.choice(rays.n_rays, n, replace=False)))


# ------------------------------------------------------------- shared edge-case inputs


def mixed_rays(mesh: TriangleMesh, n: int = 700, seed: int = 0) -> RayBatch:
    """Inside, outside, interval and axis-parallel rays (zero components, ±0)."""
    lo, hi = mesh.bounds()
    rng = np.random.default_rng(seed)
    axis = np.zeros((n // 4, 3))
    axis[np.arange(n // 4), rng.integers(0, 3, n // 4)] = rng.choice([-1.0, 1.0], n // 4)
    axis[::7] *= -0.0
    inside = lo + rng.random((n // 4, 3)) * (hi - lo)
    return concat(
        rays_inside(lo, hi, n // 4, seed + 1),
        rays_outside(lo, hi, n // 4, seed + 2),
        rays_intervals(lo, hi, n // 4, seed + 3),
        RayBatch(inside, axis),
    )


def chain_tree(depth: int) -> tuple[Bvh2, TriangleMesh]:
    """A caterpillar tree of ``depth`` levels: inner child 0, leaf child 1, equal boxes."""
    n_nodes = 2 * depth + 1
    first = np.zeros(n_nodes, np.int32)
    count = np.zeros(n_nodes, np.int32)
    for level in range(depth):
        inner = 0 if level == 0 else 2 * level - 1
        first[inner] = 2 * level + 1
        count[2 * level + 2] = 1
        first[2 * level + 2] = level
    count[2 * depth - 1] = 1
    first[2 * depth - 1] = depth
    lo = np.zeros((n_nodes, 3), np.float32)
    hi = np.tile(np.float32([1, 1, 0]), (n_nodes, 1))
    n_prims = depth + 1
    # Number the leaves' prim slots in depth-first order (child 0 first).
    stack, slot = [0], 0
    while stack:
        k = stack.pop()
        if count[k]:
            first[k] = slot
            slot += 1
        else:
            stack += [first[k] + 1, first[k]]
    tri = np.tile([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], (n_prims, 1))
    mesh = TriangleMesh(tri, np.arange(3 * n_prims).reshape(-1, 3))
    bvh = Bvh2(lo, hi, first, count, np.arange(n_prims, dtype=np.int32), n_prims)
    return bvh, mesh
