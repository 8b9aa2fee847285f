"""The facade users call: ``build(mesh, key, **options)`` returning an :class:`Accel`.

An :class:`Accel` owns a mesh, the canonical structure a registered builder made
from it, and a cache of layouts derived from that structure for particular
traversals (built on first use, counted in ``info()["bytes"]``). Queries name a
registered traversal by key; extra keywords are that traversal's options::

    accel = rayaccel.build(mesh, "bvh2.binned_sah", max_leaf_size=4)
    hits = accel.intersect(origins, directions, stats=True)
    blocked = accel.occluded(origins, directions, tmin=1e-4, tmax=1.0)
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from rayaccel import config, registry
from rayaccel.counters import counters_to_dict, empty_counters
from rayaccel.dtypes import BoolArray
from rayaccel.errors import InvalidInputError
from rayaccel.queries import QUERY_KINDS
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.structure import QualityMetrics, Structure


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
        self.structure = structure
        self.options = options
        self.build_ms = build_ms
        self.step_ms = dict(step_ms or {key: build_ms})
        self.structure_name = registry.get_chain(key)[0].structure
        self._cache: dict[str, Any] = {}
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"Accel({self.key!r}, {self.mesh!r})"

    # -- queries -------------------------------------------------------------------------------

    def trace(
        self,
        rays: RayBatch,
        *,
        query: str = "closest",
        traversal: str | None = None,
        stats: bool = False,
        **options: Any,
    ) -> HitBatch:
        """Trace a :class:`RayBatch` with a registered traversal.

        Parameters
        ----------
        rays : RayBatch
            The rays; their ``tmin``/``tmax`` bound each search.
        query : {"closest", "any"}
            ``"any"`` stops at the first hit found (``prim`` is some hit, not the closest).
        traversal : str, optional
            Traversal registry key; default: the structure's default traversal
            (:func:`rayaccel.registry.default_traversal`).
        stats : bool
            Fill ``hits.stats`` with per-ray counters.
        **options
            Options of the traversal (unknown names raise with a suggestion).
        """
        if query not in QUERY_KINDS:
            raise InvalidInputError(f"query: expected one of {QUERY_KINDS}, got {query!r}")
        if not isinstance(rays, RayBatch):
            raise InvalidInputError(f"rays: expected a RayBatch, got {type(rays).__name__}")
        key = traversal or registry.default_traversal(self.structure_name)
        variant = registry.get(key, "traversal")
        if variant.structure != self.structure_name:
            raise InvalidInputError(
                f"traversal {key!r} walks {variant.structure!r}, but this accel is a "
                f"{self.structure_name!r} (built by {self.key!r})"
            )
        opts = variant.make_options(options)
        if rays.n_rays == 0:
            empty = HitBatch.empty(0)
            if stats:
                return HitBatch(
                    empty.t,
                    empty.prim,
                    empty.u,
                    empty.v,
                    stats=counters_to_dict(empty_counters(0, True)),
                )
            return empty
        with self._lock:
            cache = self._cache
        return variant.func(  # type: ignore[no-any-return]
            self.structure, self.mesh, rays, query=query, stats=stats, options=opts, cache=cache
        )

    def intersect(
        self,
        origins: Any,
        directions: Any,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        *,
        traversal: str | None = None,
        stats: bool = False,
        **options: Any,
    ) -> HitBatch:
        """Return the closest hit of every ray.

        Parameters
        ----------
        origins, directions : (n, 3) array_like of float
            Coerced once to float32. Directions need not be normalised; a zero or
            non-finite direction is a miss.
        tmin, tmax : float or (n,) array_like of float
            Hits are accepted in ``[tmin, tmax]``; ``tmin > tmax`` is a miss.
        traversal : str, optional
            Traversal registry key (``rayaccel list``); default: the structure's default.
        stats : bool
            Also return per-ray counters (``hits.stats["nodes"]`` etc.).
        **options
            Options of the traversal.

        Returns
        -------
        HitBatch
            ``t`` (inf on a miss), ``prim`` (-1 on a miss), barycentrics ``u, v``.
        """
        rays = RayBatch(origins, directions, tmin, tmax)
        return self.trace(rays, query="closest", traversal=traversal, stats=stats, **options)

    def occluded(
        self,
        origins: Any,
        directions: Any,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        *,
        traversal: str | None = None,
        **options: Any,
    ) -> BoolArray:
        """Return ``(n,)`` bool: whether anything is hit in ``[tmin, tmax]`` (any-hit query).

        For per-ray counters of an any-hit query use ``trace(rays, query="any", stats=True)``.
        """
        rays = RayBatch(origins, directions, tmin, tmax)
        return self.trace(rays, query="any", traversal=traversal, **options).hit

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
        _, start = registry.pausable(self.structure_name)
        rays = RayBatch(origins, directions, tmin, tmax)
        with self._lock:
            cache = self._cache
        return start(self.structure, self.mesh, rays, cache=cache)

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
        (canonical plus every derived layout built so far), ``options``; ``epo`` and
        ``lcv`` when requested.

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
        s: Structure = self.structure
        derived_bytes = sum(int(v.nbytes()) for v in self._cache.values() if hasattr(v, "nbytes"))
        info: dict[str, Any] = {
            "builder": self.key,
            "structure": self.structure_name,
            "build_ms": round(self.build_ms, 3),
            "step_ms": {k: round(v, 3) for k, v in self.step_ms.items()},
            "n_prims": self.mesh.n_triangles,
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
        info["bytes"] = int(s.nbytes()) + derived_bytes
        info["options"] = {
            k: getattr(self.options, k) for k in getattr(self.options, "__slots__", ())
        }
        return info

    def validate(self) -> None:
        """Check every invariant of the structure; raise ``StructureInvariantError`` if broken."""
        self.structure.validate(self.mesh.triangles())


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
        than one pre-build step, or the builder cannot take pre-built references.
    """
    if not isinstance(mesh, TriangleMesh):
        raise InvalidInputError(
            f"mesh: expected a rayaccel.TriangleMesh, got {type(mesh).__name__} "
            "(use rayaccel.TriangleMesh(vertices, faces) or rayaccel.load_mesh(path))"
        )
    key = key or registry.DEFAULT_BUILD_KEY
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
    build_ms = (time.perf_counter() - start) * 1e3
    accel = Accel(key, mesh, structure, opts, build_ms, step_ms)
    if config.DEBUG:
        accel.validate()
    return accel
