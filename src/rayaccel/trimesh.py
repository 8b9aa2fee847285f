"""trimesh's ray interface on a rayaccel BVH: ``mesh.ray = RayMeshIntersector(mesh)``.

A drop-in for ``trimesh.ray.ray_triangle.RayMeshIntersector`` and
``trimesh.ray.ray_pyembree.RayMeshIntersector``: the same methods (``intersects_id``,
``intersects_location``, ``intersects_first``, ``intersects_any``,
``contains_points``), arguments, dtypes and shapes, so code written for ``mesh.ray``
runs unchanged, on a ``bvh2`` structure traced by numba kernels on every core::

    import trimesh
    from rayaccel.trimesh import RayMeshIntersector

    mesh = trimesh.load("part.stl")
    mesh.ray = RayMeshIntersector(mesh)           # mesh.contains() uses it too
    locations, index_ray, index_tri = mesh.ray.intersects_location(origins, directions)

What it answers, and where it differs from trimesh's two intersectors:

* **Every hit once, in order.** ``multiple_hits=True`` lists every surface crossing
  along each ray, sorted by ray, then distance (then triangle), found in one
  all-hits walk (:mod:`rayaccel.bvh.traverse.all_hits_wide`) rather than by
  re-casting from just past each hit (Embree's route in trimesh, which skips hits
  closer than its offset and stops after ``max_hits=100``) or by testing every
  candidate triangle of an r-tree (``ray_triangle``, which reports a crossing of a
  shared edge on both triangles, trimesh #2504/#2524).
* **No slip-through, no double count on shared edges.** Triangles are tested with the
  watertight test of Woop, Benthin, Wald 2013, so a ray through a shared edge or
  vertex hits at least one of the triangles around it. A crossing there is reported
  by each of them; they are merged into **one hit** (the nearest, the lower triangle
  index on a tie; :mod:`rayaccel.kernels.crossings`): two hits of one ray on
  triangles that share an edge are one crossing exactly when the triangles lie on
  opposite sides of the plane through that edge and the ray (a surface the ray
  passes through), and a fan of triangles around a vertex merges edge by edge. A ray
  that touches a ridge or valley edge (both triangles on one side, the ray enters and
  leaves there) keeps both hits, so the parity of the count stays right. The test is
  exact geometry in float64, not a distance tolerance, and does not depend on the
  faces' winding. A face listed twice (the same three corners) is hit once; other
  triangles hit at one point without sharing an edge there (overlapping faces,
  T-junctions) are each reported.
* **Locations** are where the ray meets the hit triangle's plane, in float64 (as
  trimesh computes them); which triangles a ray hits is decided in float32, relative
  to the centre of the mesh's bounding box (the frame trimesh's Embree wrapper also
  moves to), so meshes far from the origin keep their precision, or in float64 with
  ``precision="float64"``.
* **Ordering**: by ray, then distance, for every query (trimesh's Embree route orders
  by depth round, its r-tree route by candidate order).
* ``max_hits`` (default ``None``: every hit) keeps the nearest ``max_hits`` hits of
  each ray.
* ``contains_points`` follows trimesh (``ray_util.contains_points``): points outside
  the bounding box are outside; a ray is cast both ways along a fixed direction and
  the point is inside when both cross the surface an odd number of times; a ray
  leaving to free space one way decides outside. It retries, along other fixed
  directions, any point whose two rays disagree, whose ray passes through a vertex,
  or which lies on the surface, and reports still undecided points (on the surface,
  or in a hole of an open mesh) as outside. Crossings are counted exactly once
  (above), which is what makes parity trustworthy.

Invalid arguments (shapes, dtypes, NaN or infinite values, origins and directions of
different lengths) raise :class:`~rayaccel.errors.InvalidInputError`, a
``ValueError``, naming the argument. A zero direction is a miss. The structure is
built on construction and rebuilt when the mesh changes (trimesh's content hash).
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh

from rayaccel import api, registry
from rayaccel.bvh.traverse.all_hits_wide import list_all_hits_wide
from rayaccel.dtypes import check_precision
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.crossings import crossings_kernel, frame_kernel, hit_points_kernel
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene.mesh import TriangleMesh

__all__ = ["RayMeshIntersector"]

F64Array = npt.NDArray[np.float64]
I64Array = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: trimesh's fixed direction for ``contains_points`` (``ray_util.contains_points``).
CONTAINS_DIRECTION = np.array([0.4395064455, 0.617598629942, 0.652231566745])
#: Directions ``contains_points`` tries per point before calling it outside.
CONTAINS_TRIES = 6
#: Seed of the further directions of ``contains_points`` (the same on every call).
CONTAINS_SEED = 2504
#: Rays traced per kernel call (bounds the all-hits buffers of huge batches).
RAYS_PER_CALL = 1 << 20


# -- argument checks -----------------------------------------------------------------------------


def _as_vectors(name: str, value: object) -> F64Array:
    """Return ``value`` as a C-contiguous (n, 3) float64 array of finite numbers."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: expected an (n, 3) float array ({exc})") from exc
    if array.size == 0 and array.ndim <= 2 and (array.ndim < 2 or array.shape[-1] in (0, 3)):
        return np.zeros((0, 3), dtype=np.float64)
    if array.dtype == np.bool_ or not (
        np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)
    ):
        raise InvalidInputError(f"{name}: expected a float array, got dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidInputError(f"{name}: expected shape (n, 3), got {array.shape}")
    array = np.ascontiguousarray(array, dtype=np.float64)
    if np.isfinite(array).all():
        return array
    finite = np.isfinite(array).all(axis=1)
    row = int(np.argmin(finite))
    what = "NaN" if np.isnan(array[row]).any() else "an infinite value"
    raise InvalidInputError(
        f"{name}: row {row} holds {what} ({array[row].tolist()}); "
        f"{int((~finite).sum())} non-finite rows in all"
    )


def _as_rays(ray_origins: object, ray_directions: object) -> tuple[F64Array, F64Array]:
    """Check origins and directions; return both as (n, 3) float64 arrays."""
    origins = _as_vectors("ray_origins", ray_origins)
    directions = _as_vectors("ray_directions", ray_directions)
    if origins.shape[0] != directions.shape[0]:
        raise InvalidInputError(
            f"ray_directions: expected {origins.shape[0]} rows to match ray_origins, "
            f"got {directions.shape[0]}"
        )
    return origins, directions


def _as_max_hits(max_hits: object) -> int:
    if max_hits is None:
        return int(np.iinfo(np.int64).max)
    if isinstance(max_hits, (bool, np.bool_)) or not isinstance(max_hits, (int, np.integer)):
        raise InvalidInputError(f"max_hits: expected a positive int or None, got {max_hits!r}")
    if max_hits < 1:
        raise InvalidInputError(f"max_hits: expected a positive int or None, got {max_hits}")
    return int(max_hits)


@dataclass(frozen=True, slots=True, eq=False)
class _Rays:
    """Rays of one call, in the mesh's frame and in the structure's."""

    origin: F64Array  # (n, 3) float64, as given
    unit: F64Array  # (n, 3) float64 unit directions (zero: a miss)
    batch: RayBatch  # float32, relative to the structure's centre
    offset: F64Array  # (n,) float64 distance of each origin from that centre


def _parts(n: int) -> list[slice]:
    """Slices of at most :data:`RAYS_PER_CALL` rays covering ``n`` rays (one if ``n == 0``)."""
    return [slice(b, min(n, b + RAYS_PER_CALL)) for b in range(0, max(n, 1), RAYS_PER_CALL)]


# -- the intersector -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class _Built:
    """The structure over one state of the mesh, and what queries need beside it."""

    mesh_hash: int
    accel: api.Accel | None  # None: the mesh has no faces
    precision: str  # "float32" or "float64": of the structure's triangles and rays
    centre: F64Array  # (3,) float64: the frame the structure is built in
    bounds: F64Array  # (2, 3) float64: trimesh's bounds of the mesh (contains_points)
    vertices: F64Array  # (V, 3) float64, the mesh's own
    faces: I64Array  # (F, 3) int64
    scale: float  # bounding box diagonal
    layouts: dict[str, Any]  # layouts derived from the structure, made on first use


class RayMeshIntersector:
    """trimesh's ray queries on a rayaccel BVH (see the module docstring).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The mesh to query; kept as :attr:`mesh` (what trimesh's intersectors expose).
        The structure is rebuilt when the mesh changes.
    builder : str, optional
        Build key of a ``bvh2`` builder (``rayaccel list``), with optional build steps;
        default :data:`rayaccel.registry.DEFAULT_BUILD_KEY`.
    precision : {"float32", "float64"}
        Which triangles a ray hits is decided in float32 (the default, relative to the
        centre of the mesh's bounds) or in float64 (``rayaccel.TriangleMesh``'s
        ``precision``: for meshes whose extent, not only their position, needs double
        precision). Locations are float64 either way.
    **options
        The builder's options (e.g. ``max_leaf_size=4``).

    Attributes
    ----------
    mesh : trimesh.Trimesh
    builder : str
    precision : str
    options : dict

    Raises
    ------
    InvalidInputError
        ``mesh`` is not a ``trimesh.Trimesh``, its vertices are not finite, the
        builder does not make a ``bvh2``, or ``precision`` is unknown.
    UnknownVariantError
        Unknown builder key or option.
    """

    def __init__(
        self,
        mesh: Any,
        builder: str | None = None,
        *,
        precision: str = "float32",
        **options: Any,
    ) -> None:
        if not isinstance(mesh, trimesh.Trimesh):
            raise InvalidInputError(f"mesh: expected a trimesh.Trimesh, got {type(mesh).__name__}")
        self.precision = check_precision(precision)
        key = builder or registry.DEFAULT_BUILD_KEY
        variant, _ = registry.get_chain(key)
        if variant.structure != "bvh2":
            raise InvalidInputError(
                f"builder: expected a bvh2 builder (rayaccel list), got {key!r}, which builds "
                f"a {variant.structure!r}"
            )
        api.check_build_options(key, options)
        self.mesh = mesh
        self.builder = key
        self.options = dict(options)
        self._lock = threading.Lock()
        self._built: _Built | None = None
        self._current()

    def __repr__(self) -> str:
        extra = "" if self.precision == "float32" else f", precision={self.precision!r}"
        return f"RayMeshIntersector({self.mesh!r}, builder={self.builder!r}{extra})"

    # -- the structure ------------------------------------------------------------------------

    @property
    def accel(self) -> api.Accel | None:
        """The :class:`rayaccel.Accel` over the mesh's current state (None without faces)."""
        return self._current().accel

    def _current(self) -> _Built:
        """Return the structure over the mesh as it is now, rebuilding it if it changed."""
        mesh_hash = self.mesh.__hash__()
        with self._lock:
            built = self._built
            if built is None or built.mesh_hash != mesh_hash:
                built = self._build(mesh_hash)
                self._built = built
            return built

    def _build(self, mesh_hash: int) -> _Built:
        vertices = np.ascontiguousarray(self.mesh.vertices, dtype=np.float64)
        faces = np.ascontiguousarray(self.mesh.faces, dtype=np.int64).reshape(-1, 3)
        if faces.shape[0] == 0:
            empty = np.zeros((2, 3))
            return _Built(mesh_hash, None, self.precision, empty[0], empty, vertices, faces,
                          1.0, {})  # fmt: skip
        if not np.isfinite(vertices).all():
            TriangleMesh(vertices, faces)  # raises, naming the vertex
        bounds = np.array(self.mesh.bounds, dtype=np.float64)  # of the referenced vertices
        centre = bounds.mean(axis=0)
        scale = float(np.linalg.norm(bounds[1] - bounds[0])) or 1.0
        local = TriangleMesh(vertices - centre, faces, name="trimesh", precision=self.precision)
        accel = api.build(local, self.builder, **self.options)
        return _Built(mesh_hash, accel, self.precision, centre, bounds, vertices, faces, scale, {})

    # -- trimesh's queries --------------------------------------------------------------------

    def intersects_id(
        self,
        ray_origins: npt.ArrayLike,
        ray_directions: npt.ArrayLike,
        multiple_hits: bool = True,
        max_hits: int | None = None,
        return_locations: bool = False,
    ) -> tuple[I64Array, I64Array] | tuple[I64Array, I64Array, F64Array]:
        """Return the triangles hit by each ray, optionally every hit along it.

        Parameters
        ----------
        ray_origins : (n, 3) float
            Ray origin points.
        ray_directions : (n, 3) float
            Ray direction vectors (any length; a zero vector is a miss).
        multiple_hits : bool
            Every surface crossing along each ray (True), or the first only.
        max_hits : int, optional
            Keep the nearest ``max_hits`` crossings of each ray (default: all).
        return_locations : bool
            Also return the hit points.

        Returns
        -------
        index_tri : (h,) int64
            Index into ``mesh.faces`` of each hit.
        index_ray : (h,) int64
            Ray of each hit; hits are sorted by ray, then distance.
        locations : (h, 3) float64
            Hit points (only with ``return_locations``).

        Raises
        ------
        InvalidInputError
            Wrong shapes or dtypes, non-finite values, row counts that differ.
        """
        origins, directions = _as_rays(ray_origins, ray_directions)
        cap = _as_max_hits(max_hits)
        index_tri, index_ray, locations, _, _ = self._hits(
            origins, directions, bool(multiple_hits), cap, bool(return_locations)
        )
        if return_locations:
            return index_tri, index_ray, locations
        return index_tri, index_ray

    def intersects_location(
        self,
        ray_origins: npt.ArrayLike,
        ray_directions: npt.ArrayLike,
        multiple_hits: bool = True,
        **kwargs: Any,
    ) -> tuple[F64Array, I64Array, I64Array]:
        """Return where the rays hit the surface.

        Parameters
        ----------
        ray_origins, ray_directions : (n, 3) float
            As :meth:`intersects_id`.
        multiple_hits : bool
            Every surface crossing along each ray (True), or the first only.
        **kwargs
            ``max_hits``, passed to :meth:`intersects_id`.

        Returns
        -------
        locations : (h, 3) float64
            Hit points, sorted by ray, then distance.
        index_ray : (h,) int64
        index_tri : (h,) int64
        """
        index_tri, index_ray, locations = self.intersects_id(  # type: ignore[misc]
            ray_origins, ray_directions, multiple_hits=multiple_hits, return_locations=True,
            **kwargs,
        )  # fmt: skip
        return locations, index_ray, index_tri

    def intersects_first(
        self, ray_origins: npt.ArrayLike, ray_directions: npt.ArrayLike
    ) -> I64Array:
        """Return ``(n,)`` int64: the first triangle each ray hits, -1 for a miss."""
        first: I64Array = self._per_ray(ray_origins, ray_directions, "closest", "prim", -1)
        return first

    def intersects_any(
        self, ray_origins: npt.ArrayLike, ray_directions: npt.ArrayLike
    ) -> BoolArray:
        """Return ``(n,)`` bool: whether each ray hits the surface at all."""
        hit: BoolArray = self._per_ray(ray_origins, ray_directions, "any", "hit", False)
        return hit

    def _per_ray(
        self, ray_origins: npt.ArrayLike, ray_directions: npt.ArrayLike, query: str,
        field: str, miss: Any,
    ) -> np.ndarray:  # fmt: skip
        """Trace the rays in parts; return each one's ``field`` of its hits (``miss``: none)."""
        origins, directions = _as_rays(ray_origins, ray_directions)
        out = np.full(origins.shape[0], miss)
        built = self._current()
        if built.accel is not None:
            for part in _parts(origins.shape[0]):
                rays = _frame(built, origins[part], directions[part])
                out[part] = getattr(_trace(built, rays.batch, query), field)
        return out

    def contains_points(self, points: npt.ArrayLike) -> BoolArray:
        """Return ``(n,)`` bool: whether each point is inside the mesh (ray parity).

        trimesh's test (``trimesh.ray.ray_util.contains_points``), made robust: see the
        module docstring. A point on the surface is reported outside.

        Parameters
        ----------
        points : (n, 3) float
            Points in space.

        Raises
        ------
        InvalidInputError
            Wrong shape or dtype, or non-finite values.
        """
        points64 = _as_vectors("points", points)
        contains = np.zeros(points64.shape[0], dtype=bool)
        built = self._current()
        if built.accel is None or points64.shape[0] == 0:
            return contains
        lo, hi = built.bounds
        pending = np.flatnonzero(((points64 > lo) & (points64 < hi)).all(axis=1))
        rng = np.random.default_rng(CONTAINS_SEED)
        for attempt in range(CONTAINS_TRIES):
            if pending.shape[0] == 0:
                break
            if attempt == 0:
                direction = CONTAINS_DIRECTION / np.linalg.norm(CONTAINS_DIRECTION)
            else:
                direction = rng.normal(size=3)
                direction /= np.linalg.norm(direction)
            n = pending.shape[0]
            origins = np.concatenate([points64[pending], points64[pending]])
            directions = np.concatenate([np.tile(direction, (n, 1)), np.tile(-direction, (n, 1))])
            _, _, _, kept, flags = self._hits(
                origins, directions, True, int(np.iinfo(np.int64).max), False
            )
            forward, backward = kept[:n], kept[n:]
            odd_forward, odd_backward = forward % 2 == 1, backward % 2 == 1
            unsure = (flags[:n] | flags[n:]) != 0
            agree = odd_forward == odd_backward
            free = (forward == 0) | (backward == 0)
            decided = ~unsure & (agree | free)
            inside = decided & agree & odd_forward
            contains[pending[inside]] = True
            pending = pending[~decided]
        return contains

    # -- all hits -----------------------------------------------------------------------------

    def _hits(
        self,
        origins: F64Array,
        directions: F64Array,
        multiple_hits: bool,
        max_hits: int,
        with_locations: bool,
    ) -> tuple[I64Array, I64Array, F64Array, I64Array, npt.NDArray[np.uint8]]:
        """Return ``(index_tri, index_ray, locations, crossings per ray, flags per ray)``.

        ``locations`` is ``(h, 3)`` with ``with_locations`` and ``(0, 3)`` without.
        """
        built = self._current()
        parts = [
            _crossings(built, _frame(built, origins[part], directions[part]), multiple_hits,
                       max_hits, with_locations, part.start)
            for part in _parts(origins.shape[0])
        ]  # fmt: skip
        if len(parts) == 1:
            return parts[0]
        tri, ray, loc, kept, flags = (np.concatenate(column) for column in zip(*parts, strict=True))
        return tri, ray, loc, kept, flags

    # -- copies and pickles (trimesh copies and pickles meshes with their intersector) -----------

    def __getstate__(self) -> dict[str, Any]:
        return {
            "mesh": self.mesh,
            "builder": self.builder,
            "precision": self.precision,
            "options": self.options,
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.mesh = state["mesh"]
        self.builder = state["builder"]
        self.precision = state["precision"]
        self.options = dict(state["options"])
        self._lock = threading.Lock()
        self._built = None

    def __copy__(self) -> RayMeshIntersector:
        clone = RayMeshIntersector.__new__(RayMeshIntersector)
        clone.__setstate__(self.__getstate__())
        clone._built = self._built  # read-only once built: shared
        return clone

    def __deepcopy__(self, memo: dict[int, Any]) -> RayMeshIntersector:
        clone = RayMeshIntersector.__new__(RayMeshIntersector)
        clone.__setstate__(copy.deepcopy(self.__getstate__(), memo))
        clone._built = self._built  # rebuilt if the copied mesh hashes differently
        return clone


def _frame(built: _Built, origins: F64Array, directions: F64Array) -> _Rays:
    """Return the rays in the structure's frame (:func:`frame_kernel`)."""
    n = origins.shape[0]
    real = np.float64 if built.precision == "float64" else np.float32
    local = np.empty((n, 3), dtype=real)
    unit = np.empty((n, 3), dtype=real)
    unit64 = np.empty((n, 3), dtype=np.float64)
    offset = np.empty(n, dtype=np.float64)
    if n:
        frame_kernel(origins, directions, built.centre, local, unit, unit64, offset)
    return _Rays(origins, unit64, RayBatch(local, unit, precision=built.precision), offset)


def _trace(built: _Built, rays: RayBatch, query: str) -> Any:
    """Closest or any hit of each ray by ``bvh2.wide`` (the fastest CPU traversal)."""
    assert built.accel is not None
    if rays.n_rays == 0:
        return HitBatch.empty(0)
    wide = registry.get("bvh2.wide", "traversal")
    return wide.func(
        built.accel.structure, built.accel.mesh, rays, query=query,
        options=wide.make_options(), cache=built.layouts,
    )  # fmt: skip


def _crossings(
    built: _Built,
    rays: _Rays,
    multiple_hits: bool,
    max_hits: int,
    with_locations: bool,
    first_ray: int,
) -> tuple[I64Array, I64Array, F64Array, I64Array, npt.NDArray[np.uint8]]:
    """Hits of one part of the rays, one per crossing (:meth:`RayMeshIntersector._hits`)."""
    n = rays.batch.n_rays
    if built.accel is None or n == 0:
        empty = np.zeros(0, dtype=np.int64)
        return (empty, empty.copy(), np.zeros((0, 3)), np.zeros(n, dtype=np.int64),
                np.zeros(n, dtype=np.uint8))  # fmt: skip
    if multiple_hits:
        splits, t, prim, _, _ = list_all_hits_wide(
            built.accel.structure, built.accel.mesh, rays.batch, cache=built.layouts
        )
    else:
        hits = _trace(built, rays.batch, "closest")
        found = hits.hit
        splits = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(found, out=splits[1:])
        t, prim = hits.t[found], hits.prim[found]
    keep = np.empty(t.shape[0], dtype=bool)
    kept = np.empty(n, dtype=np.int64)
    flags = np.empty(n, dtype=np.uint8)
    crossings_kernel(
        splits, t, prim, rays.unit, rays.offset, built.vertices, built.faces, built.scale,
        max_hits, keep, kept, flags,
    )  # fmt: skip
    out_splits = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(kept, out=out_splits[1:])
    h = int(out_splits[-1])
    index_tri = np.empty(h, dtype=np.int64)
    index_ray = np.empty(h, dtype=np.int64)
    locations = np.empty((h if with_locations else 0, 3), dtype=np.float64)
    hit_points_kernel(
        splits, keep, out_splits, prim, t, rays.origin, rays.unit, built.vertices,
        built.faces, first_ray, index_tri, index_ray, locations, with_locations,
    )  # fmt: skip
    return index_tri, index_ray, locations, kept, flags
