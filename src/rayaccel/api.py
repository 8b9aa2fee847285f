"""The facade users call: ``build(mesh, key, **options)`` returning an :class:`Accel`.

An :class:`Accel` owns a mesh, the canonical structure a registered builder made
from it, and a cache of layouts derived from that structure for particular
traversals (built on first use, counted in ``info()["bytes"]``). Queries name a
registered traversal by key; extra keywords are that traversal's options::

    accel = rayaccel.build(mesh, "bvh2.binned_sah", max_leaf_size=4)
    hits = accel.intersect(origins, directions, stats=True)
    blocked = accel.occluded(origins, directions, tmin=1e-4, tmax=1.0)

Precision is the mesh's: ``TriangleMesh(vertices, faces, precision="float64")`` gives an
accel whose queries take and return float64 (rays, ``t``, ``u``, ``v``) over the same
float32 structure, made to hold the float64 triangles: BVH boxes widened
(:mod:`rayaccel.bvh.precision`), kd-tree leaves listing every float64 triangle they
touch (:mod:`rayaccel.kdtree.precision`), grid cells whose margins already do
(:mod:`rayaccel.grid.precision`). BVH, kd-tree and grid builders accept float64
meshes, except ``grid.irregular``.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rayaccel import chunked, config, persist, registry
from rayaccel import refit as refitting
from rayaccel.bvh import geometry
from rayaccel.bvh.builders.refit_vertices import refit_bvh2
from rayaccel.bvh.layouts import released_bounds
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.precision import conservative_bvh2
from rayaccel.counters import counters_to_dict, empty_counters
from rayaccel.dtypes import BoolArray, FloatArray, IntArray
from rayaccel.errors import AccelFileError, InvalidInputError, UnknownVariantError
from rayaccel.grid.layouts.two_level import TwoLevelGrid
from rayaccel.grid.layouts.uniform import UniformGrid
from rayaccel.grid.precision import FLOAT64_REFUSED
from rayaccel.grid.precision import check_conservative as check_grid_float64
from rayaccel.kdtree.layouts.kdtree import KdTree
from rayaccel.kdtree.precision import check_conservative, conservative_kdtree
from rayaccel.queries import QUERY_KINDS
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.rays.coherence import packet_coherence
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.run import LAYOUT_MS
from rayaccel.trace.structure import QualityMetrics, Structure

if TYPE_CHECKING:
    from rayaccel.cuda.device import DeviceRays

#: Where queries run: numba's CPU kernels, or the same bodies compiled for CUDA.
DEVICES = ("cpu", "cuda")


class Accel:
    """An acceleration structure over a mesh, ready for queries.

    Use :func:`build` to make one. Thread-safe: several Python threads may query one
    ``Accel`` at once (parallel kernels are serialised when numba's threading layer
    is not thread-safe, see :mod:`rayaccel.config`).

    Attributes
    ----------
    key : str
        The builder's registry key.
    mesh : TriangleMesh
        Its ``precision`` is the accel's (:attr:`precision`).
    structure : Structure
        The canonical structure the builder made (:class:`rayaccel.trace.structure.Structure`).
    options : object
        The builder options used.
    build_ms : float
        Wall-clock build time (includes numba compilation on a process's first build).
    step_ms : dict of str to float
        Wall-clock time of each pre-build step, the builder and each post-build step,
        by registry key, in the order they ran.
    """

    def __init__(
        self,
        key: str,
        mesh: TriangleMesh,
        structure: Any,
        options: Any,
        build_ms: float,
        step_ms: dict[str, float] | None = None,
    ):
        self.key = key
        self.mesh = mesh
        self._lock = threading.RLock()
        self._structure: Any = structure
        #: The BVH boxes: ``"held"`` (may be released), ``"released"`` or ``"kept"``.
        self._boxes = "held"
        self.options = options
        self.build_ms = build_ms
        self.step_ms = dict(step_ms or {key: build_ms})
        self.structure_name = registry.get_chain(key)[0].structure
        self._cache: dict[str, Any] = {}
        #: The mesh and its box's diagonal, the scale of a batch's coherence.
        self._scene_diagonal: tuple[TriangleMesh, float] | None = None
        #: Options of each build step by step name (set by :func:`build`), for rebuilds.
        self.step_options: dict[str, Any] = {}
        #: SAH cost at build time; computed on first need (:meth:`refit`, :meth:`save`).
        self.build_sah: float | None = None
        #: The report of the last :meth:`refit` (also ``info()["refit"]``).
        self.last_refit: dict[str, Any] | None = None
        #: What refits of this topology keep from one to the next (:mod:`rayaccel.refit`).
        self._refit_memo: dict[str, Any] = {}

    def __repr__(self) -> str:
        return f"Accel({self.key!r}, {self.mesh!r})"

    # -- the canonical structure, and its boxes released after the default queries -------------

    @property
    def structure(self) -> Any:
        """The canonical structure the builder made (its BVH boxes restored if released).

        Whoever reads it may derive layouts from the tree's boxes while a default query
        finishes, so from the first read on the boxes are kept for good.
        """
        if self._boxes != "kept":
            with self._lock:
                if self._boxes == "released":
                    self._structure = released_bounds.with_boxes(
                        self._structure, self.mesh.vertices, self.mesh.faces, self._cache
                    )
                self._boxes = "kept"
        return self._structure

    @structure.setter
    def structure(self, structure: Any) -> None:
        with self._lock:
            self._structure = structure
            self._boxes = "held"

    def _full_structure(self) -> Any:
        """Return the canonical structure with its boxes (recomputed, not kept, if released)."""
        with self._lock:
            if self._boxes != "released":
                return self._structure
            return refit_bvh2(self._structure, self.mesh.vertices, self.mesh.faces)

    def _release_boxes(self) -> None:
        """Drop the BVH's node boxes once the cache holds only the default queries' layouts.

        See :mod:`rayaccel.bvh.layouts.released_bounds`: the boxes go only when a refit
        gives them back exactly (checked once), and come back, for good, on the first
        use that reads them.
        """
        with self._lock:
            if self._boxes != "held" or not released_bounds.releasable(self._cache):
                return
            tree, mesh = self._structure, self.mesh
            if (
                not isinstance(tree, Bvh2)
                or mesh.precision != "float32"
                or not released_bounds.boxes_are_unions(tree, mesh.vertices, mesh.faces)
            ):
                self._boxes = "kept"
                return
            self._structure = released_bounds.without_boxes(tree, self._cache)
            self._boxes = "released"

    @property
    def precision(self) -> str:
        """``"float32"`` or ``"float64"``: the mesh's, and that of the rays and hits of queries."""
        return self.mesh.precision

    # -- queries -------------------------------------------------------------------------------

    def trace(
        self,
        rays: RayBatch | DeviceRays,
        *,
        query: str = "closest",
        traversal: str | None = None,
        stats: bool = False,
        device: str = "cpu",
        **options: Any,
    ) -> HitBatch:
        """Trace a :class:`RayBatch` with a registered traversal.

        Parameters
        ----------
        rays : RayBatch
            The rays; their ``tmin``/``tmax`` bound each search. A batch of the other
            precision is converted to the accel's (:attr:`precision`) first.
        query : {"closest", "any"}
            ``"any"`` stops at the first hit found (``prim`` is some hit, not the closest).
        traversal : str, optional
            Traversal registry key; default: the structure's fastest CPU traversal
            for this batch (:func:`rayaccel.registry.query_traversal`: for BVHs
            ``bvh2.packet`` when the batch is coherent, such as camera rays in image
            order or shadow rays towards one light, and ``bvh2.wide`` otherwise or
            when ``options`` are given), and on ``device="cuda"`` its default traversal
            (:func:`rayaccel.registry.default_traversal`, ``bvh2.stack``).
        stats : bool
            Fill ``hits.stats`` with per-ray counters.
        device : {"cpu", "cuda"}
            ``"cuda"`` runs the traversal's kernel on the GPU (:mod:`rayaccel.cuda`); ``rays``
            may then also be :class:`rayaccel.cuda.device.DeviceRays`.
        **options
            Options of the traversal (unknown names raise with a suggestion).
        """
        if device not in DEVICES:
            raise InvalidInputError(f"device: expected one of {DEVICES}, got {device!r}")
        if query not in QUERY_KINDS:
            raise InvalidInputError(f"query: expected one of {QUERY_KINDS}, got {query!r}")
        if not isinstance(stats, (bool, np.bool_)):
            raise InvalidInputError(f"stats: expected True or False, got {stats!r}")
        if traversal is not None and not isinstance(traversal, str):
            raise InvalidInputError(f"traversal: expected a registry key, got {traversal!r}")
        if not isinstance(rays, RayBatch) and not (device == "cuda" and _is_device_rays(rays)):
            raise InvalidInputError(f"rays: expected a RayBatch, got {type(rays).__name__}")
        if traversal is not None:
            key = traversal
        elif device == "cuda":
            key = registry.default_traversal(self.structure_name)
        elif isinstance(rays, RayBatch) and not options:
            key = self.query_traversal(rays)
        else:
            key = registry.query_traversal(self.structure_name)
        variant = registry.get(key, "traversal")
        if variant.structure != self.structure_name:
            raise InvalidInputError(
                f"traversal {key!r} walks {variant.structure!r}, but this accel is a "
                f"{self.structure_name!r} (built by {self.key!r})"
            )
        opts = variant.make_options(options)
        if rays.n_rays == 0:
            empty = HitBatch.empty(0, self.precision)
            if stats:
                return HitBatch(
                    empty.t,
                    empty.prim,
                    empty.u,
                    empty.v,
                    stats=counters_to_dict(empty_counters(0, True)),
                )
            return empty
        if device == "cuda":
            return self._trace_cuda(key, variant, rays, query, stats, opts)
        # The default queries' traversals (named or not) with their default options read
        # derived layouts only: the tree's boxes may stay released.
        default = not options and key in released_bounds.TRAVERSALS
        with self._lock:
            # One consistent snapshot: refit() swaps the three together.
            structure = self._structure if default else self.structure
            cache, mesh = self._cache, self.mesh
        rays = rays.astype(mesh.precision)
        hits: HitBatch = variant.func(
            structure, mesh, rays, query=query, stats=stats, options=opts, cache=cache
        )
        if default and self._boxes == "held":
            self._release_boxes()
        return hits

    def query_traversal(self, rays: RayBatch) -> str:
        """Return the traversal :meth:`trace` uses for ``rays`` when it is given none.

        The structure's packet traversal when the batch is coherent (the share of its
        coherent packets, :func:`rayaccel.rays.coherence.packet_coherence`, reaches
        :data:`rayaccel.registry.COHERENT_SHARE`), else its fastest single-ray one
        (:func:`rayaccel.registry.query_traversal`).
        """
        if self.structure_name not in registry.COHERENT_TRAVERSAL:
            return registry.query_traversal(self.structure_name)
        mesh = self.mesh
        memo = self._scene_diagonal
        if memo is None or memo[0] is not mesh:
            lo, hi = mesh.bounds()
            memo = self._scene_diagonal = (mesh, float(np.linalg.norm(hi.astype(np.float64) - lo)))
        return registry.query_traversal(self.structure_name, packet_coherence(rays, memo[1]))

    def _trace_cuda(
        self, key: str, variant: Any, rays: Any, query: str, stats: bool, opts: Any
    ) -> HitBatch:
        """Run traversal ``key`` on the GPU (:mod:`rayaccel.cuda.device`)."""
        from rayaccel.cuda import device as cuda_device

        if key not in cuda_device.CUDA_TRAVERSALS:
            raise InvalidInputError(
                f"traversal {key!r} has no CUDA kernel; device='cuda' runs "
                f"{', '.join(cuda_device.CUDA_TRAVERSALS)}"
            )
        if self.precision != "float32":
            raise InvalidInputError("device='cuda' traces float32 accels only")
        with self._lock:
            cache, structure, mesh = self._cache, self.structure, self.mesh
            memo = cache.setdefault("cuda.arrays", {})
        with cuda_device.on_cuda(memo):
            return variant.func(  # type: ignore[no-any-return]
                structure, mesh, rays, query=query, stats=stats, options=opts, cache=cache
            )

    def to_device(self, traversal: str | None = None, **options: Any) -> Accel:
        """Copy the layout ``traversal`` needs to the GPU now, instead of on its first query.

        The copy is kept with the accel (one per layout, shared by every later
        ``device="cuda"`` query, never copied per launch) and dropped by :meth:`refit`.
        Returns ``self``.
        """
        from rayaccel.cuda import device as cuda_device

        empty = cuda_device.device_rays(
            np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), 0.0, np.inf
        )
        key = traversal or registry.default_traversal(self.structure_name)
        variant = registry.get(key, "traversal")
        self._trace_cuda(key, variant, empty, "closest", False, variant.make_options(options))
        return self

    def intersect(
        self,
        origins: Any,
        directions: Any,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        *,
        traversal: str | None = None,
        stats: bool = False,
        device: str = "cpu",
        **options: Any,
    ) -> HitBatch:
        """Return the closest hit of every ray.

        Parameters
        ----------
        origins, directions : (n, 3) array_like of float, or Dask arrays
            Coerced once to float32 (float64 for a float64 accel). Directions need not
            be normalised; a zero or non-finite direction is a miss. Beyond
            ``rayaccel.config.RAY_BUDGET`` bytes of copies the rays are traced in chunks;
            Dask arrays give Dask arrays in the result, traced block by block when
            computed (:mod:`rayaccel.chunked`).
        tmin, tmax : float or (n,) array_like of float
            Hits are accepted in ``[tmin, tmax]``; ``tmin > tmax`` is a miss.
        traversal : str, optional
            Traversal registry key (``rayaccel list``); default: the structure's default.
        stats : bool
            Also return per-ray counters (``hits.stats["nodes"]`` etc.).
        device : {"cpu", "cuda"}
            ``"cuda"`` traces on the GPU (:mod:`rayaccel.cuda`): rays may then be numpy
            arrays (hits come back as numpy) or device arrays with
            ``__cuda_array_interface__`` (CuPy, PyTorch, Numba; float32, used without a
            copy), and hits then stay on the GPU as Numba device arrays.
        **options
            Options of the traversal.

        Returns
        -------
        HitBatch
            ``t`` (inf on a miss), ``prim`` (-1 on a miss), barycentrics ``u, v``; float32,
            or float64 for a float64 accel.
        """
        return self._query(
            origins, directions, tmin, tmax, "closest", traversal, stats, options, device
        )

    def occluded(
        self,
        origins: Any,
        directions: Any,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        *,
        traversal: str | None = None,
        device: str = "cpu",
        **options: Any,
    ) -> BoolArray:
        """Return ``(n,)`` bool: whether anything is hit in ``[tmin, tmax]`` (any-hit query).

        For per-ray counters of an any-hit query use ``trace(rays, query="any", stats=True)``.
        ``device="cuda"`` as in :meth:`intersect` (a device bool array for device rays).
        """
        hits = self._query(
            origins, directions, tmin, tmax, "any", traversal, False, options, device
        )
        if device == "cuda" and not isinstance(hits.prim, np.ndarray):
            from rayaccel.cuda.device import hit_mask

            return hit_mask(hits.prim)
        return hits.hit

    def _query(
        self,
        origins: Any,
        directions: Any,
        tmin: Any,
        tmax: Any,
        query: str,
        traversal: str | None,
        stats: bool,
        options: dict[str, Any],
        device: str = "cpu",
    ) -> HitBatch:
        """Trace numpy rays, in chunks beyond the ray budget, or Dask arrays of rays lazily."""
        if device == "cuda":
            from rayaccel.cuda.device import device_rays

            rays_on_gpu = device_rays(origins, directions, tmin, tmax)
            return self.trace(rays_on_gpu, query=query, traversal=traversal, stats=stats,
                              device="cuda", **options)  # fmt: skip
        if any(chunked.is_dask_array(a) for a in (origins, directions, tmin, tmax)):
            if stats:
                raise InvalidInputError("stats: per-ray counters are not available for Dask arrays")
            return chunked.trace_dask(self, origins, directions, tmin, tmax, query=query,
                                      traversal=traversal, options=options)  # fmt: skip
        n = chunked.count_rays(origins, directions)
        # Float64 rays take twice the bytes of the float32 copies the budget counts.
        budget = config.RAY_BUDGET // (2 if self.precision == "float64" else 1)
        chunk = chunked.rays_per_chunk(budget)
        if n is not None and n > chunk:
            return chunked.trace_in_chunks(
                lambda rays: self.trace(
                    rays, query=query, traversal=traversal, stats=stats, **options
                ),
                origins, directions, tmin, tmax, n, chunk, self.precision,
            )  # fmt: skip
        rays = RayBatch(origins, directions, tmin, tmax, precision=self.precision)
        return self.trace(rays, query=query, traversal=traversal, stats=stats, **options)

    def traversal_state(
        self,
        origins: Any,
        directions: Any,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
    ) -> Any:
        """Return a pausable traversal per ray (Binder & Keller 2016, building block 5).

        Each ``state.next_hits()`` call resumes every ray where it stopped and returns
        its next hit in traversal order; ``state.all_hits()`` collects every hit in
        ``[tmin, tmax]`` sorted by ray, ``t`` and primitive. The structure's pausable
        traversal is looked up in the registry (:func:`rayaccel.registry.pausable`).

        Raises
        ------
        InvalidInputError
            No traversal of this structure can pause and resume.
        """
        if self.precision != "float32":
            raise InvalidInputError(
                "traversal_state: a float32 accel's debugging view of the traversal order "
                "(its pausable walk keeps float32 state); a float64 accel lists every hit "
                "in float64 with list_intersections"
            )
        _, start = registry.pausable(self.structure_name)
        rays = RayBatch(origins, directions, tmin, tmax)
        with self._lock:
            cache, structure, mesh = self._cache, self.structure, self.mesh
        return start(structure, mesh, rays, cache=cache)

    # -- Open3D's geometry queries (rayaccel.bvh.geometry) ---------------------------------------

    def _geometry_snapshot(self) -> tuple[Any, TriangleMesh, dict[str, Any]]:
        with self._lock:
            return self.structure, self.mesh, self._cache

    def count_intersections(
        self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf
    ) -> IntArray:
        """Return ``(n,)`` int32: how many triangles each ray crosses in ``[tmin, tmax]``.

        Every triangle is counted once per ray, also where the structure references
        it from several leaves (spatial splits, pre-splitting). Open3D's
        ``RaycastingScene.count_intersections``; arguments as :meth:`intersect`. A
        ``bvh2`` is walked directly; other structures get a companion BVH on first use
        (:mod:`rayaccel.bvh.geometry`).
        """
        rays = RayBatch(origins, directions, tmin, tmax, precision=self.precision)
        structure, mesh, cache = self._geometry_snapshot()
        return geometry.count_intersections(structure, mesh, rays, cache)

    def list_intersections(
        self, origins: Any, directions: Any, tmin: Any = 0.0, tmax: Any = np.inf
    ) -> geometry.IntersectionList:
        """Return every hit of every ray in ``[tmin, tmax]``, once, by ray, ``t`` and primitive.

        Open3D's ``RaycastingScene.list_intersections``: CSR arrays ``ray_splits``
        (ray ``r``'s hits are ``ray_splits[r]:ray_splits[r + 1]``), ``ray_ids``,
        ``t_hit``, ``primitive_ids``, ``primitive_uvs``
        (:class:`rayaccel.bvh.geometry.IntersectionList`, also indexable by those
        names). Arguments as :meth:`intersect`.
        """
        rays = RayBatch(origins, directions, tmin, tmax, precision=self.precision)
        structure, mesh, cache = self._geometry_snapshot()
        return geometry.list_intersections(structure, mesh, rays, cache)

    def compute_closest_points(self, points: Any) -> geometry.ClosestPoints:
        """Return the nearest point of the mesh to each query point.

        Open3D's ``RaycastingScene.compute_closest_points``: ``points``,
        ``primitive_ids``, ``primitive_uvs``, ``primitive_normals``, plus ``distance``
        (:class:`rayaccel.bvh.geometry.ClosestPoints`), by a BVH nearest-point walk
        (:mod:`rayaccel.bvh.traverse.closest_point`).

        Parameters
        ----------
        points : (n, 3) array_like of float
            Finite query points (computed in float64).

        Raises
        ------
        InvalidInputError
            ``points`` is not ``(n, 3)`` real numbers or holds a NaN or inf.
        """
        query = geometry.coerce_points(points)
        structure, mesh, cache = self._geometry_snapshot()
        return geometry.closest(structure, mesh, query, cache)

    def compute_distance(self, points: Any) -> FloatArray:
        """Return ``(n,)`` distances from each point to the mesh (unsigned).

        float32, or float64 for a float64 accel (as every geometry query's floats).
        """
        query = geometry.coerce_points(points)
        structure, mesh, cache = self._geometry_snapshot()
        return geometry.distance(structure, mesh, query, cache)

    def compute_signed_distance(
        self, points: Any, *, method: str = "winding", n_rays: int = 3
    ) -> FloatArray:
        """Return ``(n,)`` distances to the mesh, negative inside (float64 for a float64 accel).

        Parameters
        ----------
        points : (n, 3) array_like of float
            Finite query points.
        method : {"winding", "parity"}
            Inside test: generalised winding number above 1/2 (Jacobson et al. 2013,
            fast evaluation of Barill et al. 2018; robust on open and imperfect
            meshes, needs outward orientation) or a majority vote of ray parities
            over ``n_rays`` fixed directions (Open3D's approach; ignores orientation).
            Behaviour on open meshes: :mod:`rayaccel.bvh.geometry`.
        n_rays : int
            Odd number of parity rays.
        """
        query = geometry.coerce_points(points)
        structure, mesh, cache = self._geometry_snapshot()
        return geometry.signed_distance(structure, mesh, query, cache, method=method, n_rays=n_rays)

    def compute_occupancy(
        self, points: Any, *, method: str = "winding", n_rays: int = 3
    ) -> FloatArray:
        """Return ``(n,)`` 1 for points inside the mesh, 0 outside (float64 for float64 accels).

        Open3D's ``RaycastingScene.compute_occupancy``; ``method`` and ``n_rays`` as in
        :meth:`compute_signed_distance`.
        """
        query = geometry.coerce_points(points)
        structure, mesh, cache = self._geometry_snapshot()
        return geometry.occupancy(structure, mesh, query, cache, method=method, n_rays=n_rays)

    # -- structure -----------------------------------------------------------------------------

    def derived(self, name: str) -> Any:
        """Return the derived layout ``name`` if a traversal has built it, else None."""
        return self._cache.get(name)

    def info(
        self,
        *,
        inner_cost: float = 1.2,
        prim_cost: float = 1.0,
        epo: bool = False,
        lcv_rays: RayBatch | None = None,
    ) -> dict[str, Any]:
        """Return build and quality figures.

        Keys: ``builder``, ``structure``, ``build_ms``, ``step_ms``, ``n_prims``, the
        structure's own figures (:meth:`rayaccel.trace.structure.Structure.info`; for
        a BVH ``n_nodes``, ``n_leaves``, ``n_refs``, ``depth``, ``sah``,
        ``mean_leaf_size``), ``refs_per_prim`` when it counts references, ``bytes``
        (canonical plus every derived layout built so far, plus ``refit_bytes``, what a
        BVH keeps between refits, once refitted), ``layouts`` (each derived
        layout built so far, e.g. the 8-wide BVH of the default query traversal: its
        ``bytes`` and ``build_ms``, which includes the layouts it derives from when they
        were built for it), ``options``; ``epo`` and ``lcv`` when requested.

        Parameters
        ----------
        inner_cost, prim_cost : float
            SAH (and EPO) constants ``C_inner`` and ``C_prim`` (Aila et al. 2013: 1.2, 1).
        epo : bool
            Also compute the end-point overlap (seconds to a minute on million-triangle
            scenes).
        lcv_rays : RayBatch, optional
            Also compute the leaf count variability over these rays (closest hits
            found with the default traversal).

        Raises
        ------
        InvalidInputError
            ``epo`` or ``lcv_rays`` asked of a structure without quality metrics.
        """
        s: Structure = self._full_structure()
        info: dict[str, Any] = {
            "builder": self.key,
            "structure": self.structure_name,
            "build_ms": round(self.build_ms, 3),
            "step_ms": {k: round(v, 3) for k, v in self.step_ms.items()},
            "n_prims": self.mesh.n_triangles,
            "precision": self.precision,
        }
        info.update(s.info(inner_cost, prim_cost))
        if "n_refs" in info:
            info["refs_per_prim"] = info["n_refs"] / max(self.mesh.n_triangles, 1)
        if epo or lcv_rays is not None:
            if not isinstance(s, QualityMetrics):
                raise InvalidInputError(
                    f"epo and lcv are defined for hierarchies of boxes; a {self.structure_name!r} "
                    "has no quality metrics"
                )
            segments = None
            if lcv_rays is not None:
                hits = self.trace(lcv_rays)
                t_hit = np.minimum(hits.t, lcv_rays.tmax)
                segments = (lcv_rays.origin, lcv_rays.direction, lcv_rays.tmin, t_hit)
            quality = s.quality(
                self.mesh.triangles(),
                epo=epo,
                segments=segments,
                inner_cost=inner_cost,
                prim_cost=prim_cost,
            )
            info.update(quality)
        layout_ms = self._cache.get(LAYOUT_MS, {})
        layouts = {
            name: {"bytes": int(v.nbytes()), "build_ms": round(layout_ms.get(name, 0.0), 3)}
            for name, v in self._cache.items()
            if hasattr(v, "nbytes")
        }
        refit_bytes = sum(int(v.nbytes()) for v in tuple(self._refit_memo.values()))
        info["bytes"] = (
            int(self._structure.nbytes())
            + sum(entry["bytes"] for entry in layouts.values())
            + refit_bytes
        )
        info["layouts"] = layouts
        if isinstance(s, Bvh2):
            info["boxes_released"] = self._boxes == "released"
        if refit_bytes:
            info["refit_bytes"] = refit_bytes
        if self.last_refit is not None:
            info["refit"] = dict(self.last_refit)
        info["options"] = {
            k: getattr(self.options, k) for k in getattr(self.options, "__slots__", ())
        }
        return info

    def validate(self) -> None:
        """Check every invariant of the structure; raise ``StructureInvariantError`` if broken."""
        if self.mesh.precision == "float64":
            _validate_float64(self.structure, self.mesh)
        else:
            self.structure.validate(self.mesh.triangles())

    # -- deformation, files and copies ---------------------------------------------------------

    def refit(self, new_vertices: Any, *, rebuild_if_worse: float | None = None) -> dict[str, Any]:
        """Move the mesh's vertices and update the structure (same faces, same topology).

        A BVH keeps its tree and has every box recomputed bottom-up in parallel; a
        kd-tree or a grid cannot be refitted (its planes and cells are positions in
        space) and is rebuilt with the same builder and options. Every derived
        traversal layout is dropped and derived again on its next use. See
        :mod:`rayaccel.refit`.

        Parameters
        ----------
        new_vertices : (V, 3) array_like of float
            The new positions, one per vertex of ``self.mesh`` (coerced to float32;
            every one finite). The accel then holds a new :class:`TriangleMesh` with these
            vertices and the same faces.
        rebuild_if_worse : float, optional
            Rebuild from scratch (same builder, steps and options) when the refitted
            tree's SAH cost exceeds this many times the SAH cost at build time.

        Returns
        -------
        dict
            ``method`` (``"refit"`` or ``"rebuild"``) and ``reason``; ``sah_build``,
            ``sah_before``, ``sah_refit`` (the refitted tree's cost, before any rebuild)
            and ``sah_after`` (the cost of the structure now held); ``ratio`` =
            ``sah_refit / sah_build`` (the SAH degradation); ``refit_ms``,
            ``rebuild_ms``, ``ms``; ``dropped`` (derived layouts dropped). SAH values
            are None for grids. The same dict is ``info()["refit"]``.

        Raises
        ------
        InvalidInputError
            ``new_vertices`` has another shape or vertex count, or a NaN or inf;
            ``rebuild_if_worse`` is not a positive number.
        """

        def rebuild(mesh: TriangleMesh) -> tuple[Any, float, dict[str, float]]:
            fresh = build(mesh, self.key, **self.build_options())
            return fresh.structure, fresh.build_ms, fresh.step_ms

        outcome = refitting.refit_structure(
            self.structure,
            self.mesh,
            new_vertices,
            build_sah=self.build_sah,
            rebuild_if_worse=rebuild_if_worse,
            rebuild=rebuild,
            structure_name=self.structure_name,
            sah_now=None if self.last_refit is None else self.last_refit["sah_after"],
            memo=self._refit_memo,
        )
        with self._lock:
            outcome.report["dropped"] = sorted(k for k in self._cache if k != LAYOUT_MS)
            self.mesh = outcome.mesh
            self.structure = outcome.structure
            self.build_sah = outcome.build_sah
            self._cache = {}
            if outcome.rebuilt is not None:
                self._refit_memo = {}
                self.build_ms = outcome.rebuilt[0]
                self.step_ms = dict(outcome.rebuilt[1])
            self.last_refit = outcome.report
        return outcome.report

    def build_options(self) -> dict[str, Any]:
        """Return the keywords that make :func:`build` rebuild this accel (steps as dicts)."""
        out = persist.options_dict(self.options)
        out.update({name: persist.options_dict(o) for name, o in self.step_options.items()})
        return out

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write this accel (mesh, structure, builder and options) to ``path``; return it.

        One ``.npz`` archive with a JSON header, written atomically and loaded back with
        :func:`load_accel` (format and checks: :mod:`rayaccel.persist`). Derived
        layouts are not saved; they are derived again on first use.

        Raises
        ------
        OSError
            The file cannot be written (an existing file is then left unchanged).
        """
        if self.build_sah is None:
            self.build_sah = refitting.sah_cost(self.structure)
        return persist.save(
            path,
            key=self.key,
            structure_name=self.structure_name,
            mesh=self.mesh,
            structure=self.structure,
            options=self.options,
            step_options=self.step_options,
            build_ms=self.build_ms,
            step_ms=self.step_ms,
            build_sah=self.build_sah,
        )

    def __getstate__(self) -> dict[str, Any]:
        """Pickle everything but the lock and the derived layouts (derived again on use)."""
        self.structure  # noqa: B018 (a copy reads the boxes: restored, and kept here)
        with self._lock:
            state = self.__dict__.copy()
        state.pop("_lock", None)
        state["_cache"] = {}
        state["_boxes"] = "held"  # nothing has read the copy's tree yet
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Restore a pickled (or copied) accel with a lock and an empty layout cache of its own."""
        self.__dict__.update(state)
        self._cache = {}
        self._lock = threading.RLock()


#: Structures whose builders accept float64 meshes: BVH boxes widened by one float32 ulp
#: (:mod:`rayaccel.bvh.precision`), kd-tree leaves listing every float64 triangle they
#: touch (:mod:`rayaccel.kdtree.precision`), grid cells whose margins already exceed the
#: float64 triangles' offset (:mod:`rayaccel.grid.precision`; ``grid.irregular`` is
#: refused, :data:`rayaccel.grid.precision.FLOAT64_REFUSED`).
FLOAT64_STRUCTURES = ("bvh2", "kdtree", "grid")


def _conservative(structure: Any, mesh: TriangleMesh) -> Any:
    """Return ``structure`` made to hold ``mesh``'s float64 triangles (as it is for float32)."""
    if mesh.precision != "float64":
        return structure
    if isinstance(structure, Bvh2):
        return conservative_bvh2(structure, mesh)
    if isinstance(structure, KdTree):
        return conservative_kdtree(structure, mesh)
    return structure


def _validate_float64(structure: Any, mesh: TriangleMesh) -> None:
    """Check ``structure``'s invariants and that it holds ``mesh``'s float64 triangles.

    A float64 kd-tree lists each triangle in every leaf its float64 version touches by a
    test without the triangle's plane axis (:mod:`rayaccel.kdtree.precision`), so a
    listed triangle may miss its leaf's cell: its lists are checked for holding every
    triangle where it touches (``check_conservative``), not for listing only those.
    """
    if isinstance(structure, KdTree):
        structure.validate()
        check_conservative(structure, mesh)
        return
    structure.validate(mesh.triangles())
    if isinstance(structure, (UniformGrid, TwoLevelGrid)):
        check_grid_float64(structure, mesh)


def _is_device_rays(rays: Any) -> bool:
    """Whether ``rays`` are :class:`rayaccel.cuda.device.DeviceRays`."""
    from rayaccel.cuda.device import DeviceRays

    return isinstance(rays, DeviceRays)


def build(mesh: TriangleMesh, key: str | None = None, **options: Any) -> Accel:
    """Build an acceleration structure over ``mesh`` with the registered builder ``key``.

    Parameters
    ----------
    mesh : TriangleMesh
        The triangles to build over; the returned :class:`Accel` keeps a reference.
    key : str, optional
        Builder registry key (``rayaccel list``), e.g. ``"bvh2.binned_sah"`` (the
        default, :data:`rayaccel.registry.DEFAULT_BUILD_KEY`),
        optionally followed by build steps: ``"bvh2.lbvh+presplit+reinsert"``. A
        pre-build step (stage ``"before"``, at most one) runs first and makes the
        references the builder builds over (``refs=``); post-build steps (stage
        ``"after"``) then run in key order on the built structure.
    **options
        The builder's options (e.g. ``max_leaf_size=4``); a step's options go in a
        dict named after the step (``reinsert={"iterations": 2}``). Unknown names raise.

    Returns
    -------
    Accel

    Raises
    ------
    UnknownVariantError
        Unknown key or option, with suggestions.
    InvalidInputError
        ``mesh`` is not a TriangleMesh, an option is out of range, the key chains more
        than one pre-build step, the builder cannot take pre-built references, or
        the mesh is float64 and the builder's structure is not one of
        :data:`FLOAT64_STRUCTURES` (or the builder is ``grid.irregular``).

    Notes
    -----
    A float64 mesh (``TriangleMesh(..., precision="float64")``) is built over its float32
    rounding like any other, then made to hold the float64 triangles (included in
    ``build_ms``): a BVH's boxes widened by one float32 ulp
    (:func:`rayaccel.bvh.precision.conservative_bvh2`), a kd-tree's scene box widened
    and each float64 triangle added to every leaf it touches
    (:func:`rayaccel.kdtree.precision.conservative_kdtree`); a grid's cell margins hold
    them already (:mod:`rayaccel.grid.precision`). Every traversal of the structure
    traces float64 rays.
    """
    if not isinstance(mesh, TriangleMesh):
        raise InvalidInputError(
            f"mesh: expected a rayaccel.TriangleMesh, got {type(mesh).__name__} "
            "(use rayaccel.TriangleMesh(vertices, faces) or rayaccel.load_mesh(path))"
        )
    key = key or registry.DEFAULT_BUILD_KEY
    variant, opts, before, after = _resolve_chain(key, options)
    if mesh.precision == "float64" and variant.structure not in FLOAT64_STRUCTURES:
        raise InvalidInputError(
            f"{key}: a {variant.structure!r} cannot hold a float64 mesh (its split planes "
            "and cells are placed between float32 triangles); precision='float64' is "
            f"supported by the {', '.join(FLOAT64_STRUCTURES)} builders: "
            + ", ".join(
                k
                for s in FLOAT64_STRUCTURES
                for k in registry.keys("builder", s)
                if k not in FLOAT64_REFUSED
            )
        )
    if mesh.precision == "float64" and variant.key in FLOAT64_REFUSED:
        raise InvalidInputError(
            f"{key}: cannot hold a float64 mesh yet ({FLOAT64_REFUSED[variant.key]}); "
            "precision='float64' grids: "
            + ", ".join(k for k in registry.keys("builder", "grid") if k not in FLOAT64_REFUSED)
        )
    start = time.perf_counter()
    step_ms: dict[str, float] = {}
    with config.parallel_section():
        refs = None
        for step, step_opt in before:
            step_start = time.perf_counter()
            refs = step.func(mesh, step_opt)
            step_ms[step.key] = (time.perf_counter() - step_start) * 1e3
        build_start = time.perf_counter()
        if refs is None:
            structure = variant.func(mesh, opts)
        else:
            structure = variant.func(mesh, opts, refs=refs)
        step_ms[variant.key] = (time.perf_counter() - build_start) * 1e3
        for step, step_opt in after:
            step_start = time.perf_counter()
            structure = step.func(structure, mesh, step_opt)
            step_ms[step.key] = (time.perf_counter() - step_start) * 1e3
        # Float64 meshes: the structure must hold the float64 triangles.
        structure = _conservative(structure, mesh)
    build_ms = (time.perf_counter() - start) * 1e3
    accel = Accel(key, mesh, structure, opts, build_ms, step_ms)
    accel.step_options = {s.key.split("+", 1)[1]: o for s, o in (*before, *after)}
    if config.DEBUG:
        accel.validate()
    return accel


def check_build_options(key: str, options: dict[str, Any]) -> None:
    """Check a builder key (with its steps) and its options without building anything.

    Raises
    ------
    UnknownVariantError, InvalidInputError
        As :func:`build` would.
    """
    _resolve_chain(key, dict(options))


def _resolve_chain(key: str, options: dict[str, Any]) -> tuple[Any, Any, list[Any], list[Any]]:
    """Return the builder, its options, and the pre- and post-build steps with theirs.

    Step options are popped from ``options`` (a dict named after each step).
    """
    variant, steps = registry.get_chain(key)
    step_names = [step.key.split("+", 1)[1] for step in steps]
    step_values = {name: options.pop(name) for name in set(step_names) if name in options}
    step_opts = []
    for step, name in zip(steps, step_names, strict=True):
        values = step_values.get(name)
        if values is not None and not isinstance(values, dict):
            raise InvalidInputError(f"{name}: step options are a dict, got {values!r}")
        step_opts.append(step.make_options(values))
    opts = variant.make_options(options)
    before = [(s, o) for s, o in zip(steps, step_opts, strict=True) if s.stage == "before"]
    after = [(s, o) for s, o in zip(steps, step_opts, strict=True) if s.stage == "after"]
    if len(before) > 1:
        raise InvalidInputError(
            f"{key}: at most one pre-build step per key, got {', '.join(s.key for s, _ in before)}"
        )
    if before and not variant.takes_refs:
        raise InvalidInputError(
            f"{variant.key} cannot build over the references made by {before[0][0].key} "
            "(it takes no refs)"
        )
    return variant, opts, before, after


def load_accel(path: str | os.PathLike[str]) -> Accel:
    """Load an accel written by :meth:`Accel.save`, checking and validating it.

    The file is read without unpickling; its format version, content hash, arrays and
    structure are checked and the structure validated against the mesh
    (:func:`rayaccel.persist.load`); the builder key and options must be known to this
    rayaccel.

    Raises
    ------
    AccelFileError
        Missing, truncated, tampered, foreign or other-version file, or a builder or
        options this rayaccel does not know.
    """
    saved = persist.load(path)
    try:
        variant, steps = registry.get_chain(saved.key)
        if variant.structure != saved.structure_name:
            raise InvalidInputError(
                f"{saved.key!r} builds a {variant.structure!r}, the file holds a "
                f"{saved.structure_name!r}"
            )
        options = variant.make_options(saved.options)
        step_options = {}
        for step in steps:
            name = step.key.split("+", 1)[1]
            step_options[name] = step.make_options(saved.step_options.get(name))
    except (UnknownVariantError, InvalidInputError) as exc:
        raise AccelFileError(
            f"{path}: its builder {saved.key!r} or options do not match this rayaccel: {exc}"
        ) from exc
    accel = Accel(saved.key, saved.mesh, saved.structure, options, saved.build_ms, saved.step_ms)
    accel.step_options = step_options
    accel.build_sah = saved.build_sah
    return accel
