"""Open3D's geometry queries on a mesh: all hits, closest points, (signed) distance, occupancy.

What ``open3d.t.geometry.RaycastingScene`` offers beside ray casting, answered with
a binary BVH:

* ``count_intersections`` / ``list_intersections``: every triangle each ray crosses
  within ``[tmin, tmax]``, once, by the two-pass all-hits traversal of
  :mod:`rayaccel.bvh.traverse.all_hits` (sorted by ray, ``t``, primitive id; no
  repeats from spatial splits);
* ``closest_points`` / ``distance``: the nearest point of the mesh, by the
  branch-and-bound walk of :mod:`rayaccel.bvh.traverse.closest_point`;
* ``signed_distance`` / ``occupancy``: the distance, negative inside, and 1 inside /
  0 outside. The inside test is either the generalised winding number (``"winding"``,
  the default: Jacobson et al. 2013, evaluated hierarchically as in Barill et al.
  2018, :mod:`rayaccel.bvh.traverse.winding`; inside where ``w > 1/2``) or ray parity
  (``"parity"``, Open3D's approach: a point is inside when a ray from it crosses the
  mesh an odd number of times; a majority vote over ``n_rays`` fixed directions
  outvotes a ray that grazes an edge or a vertex and counts a crossing twice or not
  at all).

On a closed, consistently oriented mesh both methods agree away from the surface.
On an open mesh, "inside" is not defined: the winding number degrades gracefully
(a point is inside when the mesh wraps more than half way around it, so a cup that
is nearly closed still contains the points in it, and a flat sheet contains
nothing), while ray parity depends on which directions escape through the holes.
The winding number also needs a consistent orientation (outward normals, counter-
clockwise corners seen from outside); parity ignores orientation.

Precision: a float64 accel (``TriangleMesh(..., precision="float64")``) answers in
float64: rays, points, ``t``, barycentrics, closest points, normals and distances, over
its float32 tree with boxes widened to contain the float64 triangles
(:mod:`rayaccel.bvh.precision`; a companion tree is widened the same way), so every
bound the walks prune by still holds.

Structures: a ``bvh2`` accel is queried through its own tree (the winding number
needs each triangle once in the tree, so a tree with spatial splits gets a
companion tree for it). Other families (``kdtree``, ``grid``) have no box hierarchy
to prune by distance, so their accel builds a companion ``bvh2.binned_sah`` over the
same mesh on the first such query (memoised in the accel, counted in its ``bytes``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from rayaccel.bvh.builders.binned_sah import build_binned_sah
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.precision import conservative_bvh2
from rayaccel.bvh.traverse.all_hits import count_all_hits, list_all_hits
from rayaccel.bvh.traverse.closest_point import barycentric_points, closest_points
from rayaccel.bvh.traverse.winding import winding_numbers
from rayaccel.dtypes import REAL, FloatArray, Int64Array, IntArray
from rayaccel.errors import InvalidInputError
from rayaccel.rays.batch import RayBatch
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.run import memoised_layout
from rayaccel.validation import check_finite_rows, check_real, rows_of_three

#: Inside tests of :func:`signed_distance` and :func:`occupancy`.
SIGN_METHODS = ("winding", "parity")
#: Seed of the fixed ray directions of the parity vote (the same on every call).
PARITY_SEED = 20240519


@dataclass(frozen=True, slots=True, eq=False)
class CompanionBvh:
    """A ``bvh2`` built beside an accel's own structure for these queries, with its memo."""

    bvh: Bvh2
    cache: dict[str, Any]

    def nbytes(self) -> int:
        """Bytes of the tree and every layout derived from it so far."""
        derived = sum(int(v.nbytes()) for v in self.cache.values() if hasattr(v, "nbytes"))
        return int(self.bvh.nbytes()) + derived


@dataclass(frozen=True, slots=True, eq=False)
class MemoArray:
    """An array memoised in an accel's cache beside its layouts (counted in its bytes)."""

    array: FloatArray

    def nbytes(self) -> int:
        """Bytes of the array."""
        return int(self.array.nbytes)


class _FieldMapping:
    """Read a result's fields by name too (``result["t_hit"]``), as Open3D's dicts are read."""

    __slots__ = ()

    def keys(self) -> tuple[str, ...]:
        """Return the field names (Open3D's dictionary keys)."""
        return tuple(f.name for f in fields(self))  # type: ignore[arg-type]

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self.keys():
            raise KeyError(f"{key!r} (fields: {', '.join(self.keys())})")
        return getattr(self, key)  # type: ignore[no-any-return]


@dataclass(frozen=True, slots=True, eq=False)
class IntersectionList(_FieldMapping):
    """Every hit of every ray, CSR by ray (Open3D's ``list_intersections`` fields).

    Also readable as a mapping (``result["t_hit"]``), like Open3D's dict.

    Attributes
    ----------
    ray_splits : (n_rays + 1,) int64
        Ray ``r``'s hits are entries ``ray_splits[r]:ray_splits[r + 1]``.
    ray_ids : (n_hits,) int32
        The ray of each hit.
    t_hit : (n_hits,) float32 (float64 for a float64 accel)
        Distance along the ray, in units of its direction's length.
    primitive_ids : (n_hits,) int32
        The triangle hit.
    primitive_uvs : (n_hits, 2) float32 (float64 for a float64 accel)
        Barycentrics ``(u, v)`` of the hit point ``(1-u-v)·A + u·B + v·C``.
    """

    ray_splits: Int64Array
    ray_ids: IntArray
    t_hit: FloatArray
    primitive_ids: IntArray
    primitive_uvs: FloatArray


@dataclass(frozen=True, slots=True, eq=False)
class ClosestPoints(_FieldMapping):
    """The nearest point of the mesh to each query point (Open3D's ``compute_closest_points``).

    Also readable as a mapping (``result["points"]``), like Open3D's dict.

    Attributes (float32, or float64 for a float64 accel)
    ----------
    points : (n, 3) float
        The closest point on the mesh.
    primitive_ids : (n,) int32
        Its triangle (the lowest id among triangles at exactly the same distance).
    primitive_uvs : (n, 2) float
        Its barycentrics ``(u, v)`` on that triangle: ``(1-u-v)·A + u·B + v·C``.
    primitive_normals : (n, 3) float
        The triangle's unit geometric normal.
    distance : (n,) float
        Euclidean distance from the query point (computed in float64).
    """

    points: FloatArray
    primitive_ids: IntArray
    primitive_uvs: FloatArray
    primitive_normals: FloatArray
    distance: FloatArray


def coerce_points(points: Any, name: str = "points") -> np.ndarray:
    """Return ``points`` as a C-contiguous ``(n, 3)`` float64 array, or raise naming ``name``.

    Raises
    ------
    InvalidInputError
        Not an ``(n, 3)`` array of real numbers, or a coordinate is NaN or infinite.
    """
    array = rows_of_three(name, points, "n", "float")
    check_real(name, array)
    out = np.ascontiguousarray(array, dtype=np.float64)
    check_finite_rows(name, out, "point", "points")
    return out


def query_bvh(
    structure: Any, mesh: TriangleMesh, cache: dict[str, Any] | None, *, unique: bool = False
) -> tuple[Bvh2, dict[str, Any] | None]:
    """Return the ``bvh2`` these queries walk for an accel, and the memo for its layouts.

    The accel's own tree when it is a ``bvh2`` (and, with ``unique``, references each
    triangle once); otherwise a companion ``bvh2.binned_sah`` built on first use and
    memoised in ``cache`` (see the module docstring).
    """
    if isinstance(structure, Bvh2) and (not unique or structure.n_refs == structure.n_prims):
        return structure, cache
    companion = memoised_layout(
        cache,
        "geometry.bvh2",
        lambda: CompanionBvh(conservative_bvh2(build_binned_sah(mesh), mesh), {}),
    )
    return companion.bvh, companion.cache


def count_intersections(
    structure: Any, mesh: TriangleMesh, rays: RayBatch, cache: dict[str, Any] | None = None
) -> IntArray:
    """Return ``(n_rays,)`` int32: the triangles each ray crosses in ``[tmin, tmax]``, once each."""
    bvh, memo = query_bvh(structure, mesh, cache)
    return count_all_hits(bvh, mesh, rays, memo)


def list_intersections(
    structure: Any, mesh: TriangleMesh, rays: RayBatch, cache: dict[str, Any] | None = None
) -> IntersectionList:
    """Return every hit of every ray in ``[tmin, tmax]``, by ray, then ``t``, then primitive."""
    bvh, memo = query_bvh(structure, mesh, cache)
    splits, t, prim, u, v = list_all_hits(bvh, mesh, rays, memo)
    ray_ids = np.repeat(np.arange(rays.n_rays, dtype=np.int32), np.diff(splits))
    uvs = np.ascontiguousarray(np.stack([u, v], axis=1), dtype=t.dtype).reshape(-1, 2)
    return IntersectionList(splits, ray_ids, t, prim, uvs)


def closest(
    structure: Any, mesh: TriangleMesh, points: np.ndarray, cache: dict[str, Any] | None = None
) -> ClosestPoints:
    """Return the nearest point of ``mesh`` to each of ``points`` ((n, 3) float64, validated)."""
    bvh, memo = query_bvh(structure, mesh, cache)
    d2, prim, u, v = closest_points(bvh, mesh, points, memo)
    n = points.shape[0]
    real = real_of(mesh)
    if n == 0:
        zero = np.zeros((0, 3), dtype=real)
        return ClosestPoints(
            zero, prim, np.zeros((0, 2), dtype=real), zero.copy(), np.zeros(0, dtype=real)
        )
    where = barycentric_points(mesh, prim, u, v).astype(real)
    uvs = np.stack([u, v], axis=1).astype(real)
    normals = memoised_layout(
        memo, "geometry.normals", lambda: MemoArray(mesh_normals(mesh))
    ).array
    return ClosestPoints(where, prim, uvs, normals[prim], np.sqrt(d2).astype(real))


def real_of(mesh: TriangleMesh) -> type[np.floating[Any]]:
    """Return the float type these queries answer in: float32, or float64 for a float64 mesh."""
    return np.float64 if mesh.precision == "float64" else REAL


def mesh_normals(mesh: TriangleMesh) -> np.ndarray:
    """Return ``(F, 3)`` unit geometric normals in the mesh's precision (float64 corners)."""
    if mesh.vertices64 is None:
        return mesh.normals()
    tri = mesh.vertices64[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit: np.ndarray = np.where(length > 0, cross / np.where(length > 0, length, 1.0), 0.0)
    return unit


def distance(
    structure: Any, mesh: TriangleMesh, points: np.ndarray, cache: dict[str, Any] | None = None
) -> np.ndarray:
    """Return ``(n,)`` distances from each point to the mesh (computed in float64).

    float32, or float64 for a float64 mesh.
    """
    bvh, memo = query_bvh(structure, mesh, cache)
    d2 = closest_points(bvh, mesh, points, memo)[0]
    out: FloatArray = np.sqrt(d2).astype(real_of(mesh))
    return out


def _check_method(method: str, n_rays: int) -> None:
    if method not in SIGN_METHODS:
        raise InvalidInputError(f"method: expected one of {SIGN_METHODS}, got {method!r}")
    if (
        isinstance(n_rays, bool)
        or not isinstance(n_rays, (int, np.integer))
        or n_rays < 1
        or n_rays % 2 == 0
    ):
        raise InvalidInputError(f"n_rays: expected an odd positive integer, got {n_rays!r}")


def parity_directions(n_rays: int) -> np.ndarray:
    """Return the ``(n_rays, 3)`` float64 unit directions of the parity vote (fixed seed)."""
    rng = np.random.default_rng(PARITY_SEED)
    d = rng.normal(size=(n_rays, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)  # type: ignore[no-any-return]


def inside(
    structure: Any,
    mesh: TriangleMesh,
    points: np.ndarray,
    cache: dict[str, Any] | None = None,
    *,
    method: str = "winding",
    n_rays: int = 3,
) -> np.ndarray:
    """Return ``(n,)`` bool: which points are inside the mesh (see the module docstring).

    Raises
    ------
    InvalidInputError
        Unknown ``method``, or ``n_rays`` not an odd positive integer.
    """
    _check_method(method, n_rays)
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, dtype=bool)
    if method == "winding":
        return winding_number(structure, mesh, points, cache) > 0.5
    bvh, memo = query_bvh(structure, mesh, cache)
    votes = np.zeros(n, dtype=np.int32)
    for direction in parity_directions(int(n_rays)):
        rays = RayBatch(
            points, np.broadcast_to(direction, (n, 3)), 0.0, np.inf, precision=mesh.precision
        )
        votes += count_all_hits(bvh, mesh, rays, memo) % 2
    return votes > int(n_rays) // 2


def winding_number(
    structure: Any, mesh: TriangleMesh, points: np.ndarray, cache: dict[str, Any] | None = None
) -> np.ndarray:
    """Return ``(n,)`` float64 generalised winding numbers (fast, Barill et al. 2018)."""
    bvh, memo = query_bvh(structure, mesh, cache, unique=True)
    rows = memoised_layout(memo, "geometry.rows", lambda: MemoArray(mesh.hit_rows())).array
    return winding_numbers(bvh, rows, points, memo)


def signed_distance(
    structure: Any,
    mesh: TriangleMesh,
    points: np.ndarray,
    cache: dict[str, Any] | None = None,
    *,
    method: str = "winding",
    n_rays: int = 3,
) -> np.ndarray:
    """Return ``(n,)`` distances to the mesh, negative inside (:func:`inside`).

    float32, or float64 for a float64 mesh.
    """
    _check_method(method, n_rays)
    dist = distance(structure, mesh, points, cache)
    sign = np.where(inside(structure, mesh, points, cache, method=method, n_rays=n_rays), -1.0, 1.0)
    return (dist * sign).astype(real_of(mesh))


def occupancy(
    structure: Any,
    mesh: TriangleMesh,
    points: np.ndarray,
    cache: dict[str, Any] | None = None,
    *,
    method: str = "winding",
    n_rays: int = 3,
) -> FloatArray:
    """Return ``(n,)`` 1 inside the mesh, 0 outside (Open3D's ``compute_occupancy``).

    float32, or float64 for a float64 mesh.
    """
    return inside(structure, mesh, points, cache, method=method, n_rays=n_rays).astype(
        real_of(mesh)
    )
