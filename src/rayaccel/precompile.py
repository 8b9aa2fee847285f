"""Compile kernels ahead of their first call, in parallel processes (layer 8).

numba compiles a kernel on its first call and keeps the machine code in the on-disk
cache (:mod:`rayaccel._jit`). One traversal's chunk worker takes ten to forty seconds
to compile on a laptop core, and a traversal has two of them (with and without
statistics), each run by four small kernels (closest or any hit, serial or parallel),
so a cold cache
makes the first query of each kind slow. Compilation holds the interpreter lock, so
one process compiles one kernel at a time; :func:`precompile` spreads the kernels over
worker processes, each writing its kernels into the shared cache, where every later
process loads them in milliseconds. ``rayaccel cache warm`` is its command line;
``make test`` runs it before the suite.

A :class:`Job` names one build key (compiling its builder, its build steps and the
structure's validation) or one traversal kernel (traversal, query, statistics,
serial or parallel), run on a small procedural mesh.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

import numpy as np

from rayaccel import api, registry
from rayaccel.errors import UnknownVariantError
from rayaccel.queries import QUERY_KINDS
from rayaccel.rays.batch import RayBatch
from rayaccel.scene import procedural
from rayaccel.trace.run import PARALLEL_MIN_RAYS

#: Triangles of the mesh every job builds (enough for a few tree levels).
MESH_TRIANGLES = 600
#: Rays of a serial job (a parallel job traces :data:`PARALLEL_MIN_RAYS`).
SERIAL_RAYS = 16


@dataclasses.dataclass(frozen=True)
class Job:
    """One unit of compilation: a build key, or one traversal kernel.

    ``traversal`` is None for a build job; otherwise ``build_key`` is the tree the
    traversal runs on and ``query``/``stats``/``parallel`` pick the kernel.
    """

    build_key: str
    traversal: str | None = None
    query: str = "closest"
    stats: bool = False
    parallel: bool = False

    @property
    def name(self) -> str:
        """Return a short label, e.g. ``bvh2.stack closest+stats parallel``."""
        if self.traversal is None:
            return f"build {self.build_key}"
        kind = self.query + ("+stats" if self.stats else "")
        return f"{self.traversal} {kind} {'parallel' if self.parallel else 'serial'}"


def jobs(
    structures: Iterable[str] | None = None,
    *,
    parallel: bool = True,
    variant_filter: Callable[[str, str, bool], bool] | None = None,
) -> list[Job]:
    """Return the jobs that compile every build key and traversal kernel of ``structures``.

    Parameters
    ----------
    structures : iterable of str, optional
        Structure names (``bvh2``, ``kdtree``, ``grid``); every registered one by default.
    parallel : bool
        Include the parallel traversal kernels (those a batch of
        :data:`rayaccel.trace.run.PARALLEL_MIN_RAYS` rays or more runs).
    variant_filter : callable, optional
        ``variant_filter(traversal, query, stats) -> bool`` keeps a parallel kernel;
        serial kernels are always kept.

    Returns
    -------
    list of Job
        The builds of the structures' default trees, then serial kernels on those
        trees (each compiles its traversal's chunk worker, the slow part), then on the
        trees of builders that return another structure class
        (:func:`_other_layouts`), then the parallel ones (a ``prange`` around that
        worker), then the other builds.
    """
    names = list(structures) if structures is not None else registry.structures()
    unknown = sorted(set(names) - set(registry.structures()))
    if unknown:
        raise UnknownVariantError(
            f"unknown structure(s) {', '.join(unknown)} "
            f"(known: {', '.join(registry.structures())})"
        )
    serial: list[Job] = []
    other_trees: list[Job] = []
    parallel_jobs: list[Job] = []
    builds = [Job(key) for key in registry.build_keys()
              if registry.get_chain(key)[0].structure in names]  # fmt: skip
    # Query-major order: the closest and any-hit kernels of one statistics variant call
    # one chunk worker, so two processes never start on the same worker at once. Within
    # a query the structures take turns, so traversals of one structure that share a
    # compiled kernel (grid.dda and grid.skip; kd-restart, kd-backtrack and the short
    # stack) stand apart in the list: the later one loads what the earlier one compiled
    # instead of compiling it at the same time in another process.
    walks = {structure: registry.keys("traversal", structure) for structure in names}
    turns = [
        (structure, walks[structure][i])
        for i in range(max((len(w) for w in walks.values()), default=0))
        for structure in names
        if i < len(walks[structure])
    ]
    trees = {structure: registry.default_builder(structure) for structure in names}
    other_layouts = {structure: _other_layouts(structure) for structure in names}
    for query in QUERY_KINDS:
        for structure, traversal in turns:
            tree = trees[structure]
            others = other_layouts[structure]
            for stats in (False, True):
                serial.append(Job(tree, traversal, query, stats, parallel=False))
                # A builder of another structure class (the two-level grid) has
                # its own layout, so its kernels compile anew.
                other_trees += [Job(key, traversal, query, stats) for key in others]
                keep = variant_filter is None or variant_filter(traversal, query, stats)
                if parallel and keep:
                    parallel_jobs.append(Job(tree, traversal, query, stats, parallel=True))
    # The default trees' builds first, each on one process: every traversal job builds
    # its structure's default tree, and the build kernels would otherwise compile in
    # both processes at once when their first traversal jobs start together.
    defaults = set(trees.values())
    first = [job for job in builds if job.build_key in defaults]
    rest = [job for job in builds if job.build_key not in defaults]
    return first + serial + other_trees + parallel_jobs + rest


def common_parallel(traversal: str, query: str, stats: bool) -> bool:
    """Keep the parallel kernels that plain queries reach (a ``variant_filter`` for :func:`jobs`).

    Every parallel kernel of each structure's default (reference) and fastest traversals
    (for incoherent and coherent batches),
    and the plain closest-hit kernel of every other traversal; the statistics and any-hit
    parallel kernels of the other traversals compile on first use. ``make test`` warms
    this set: the default test tier runs no other parallel kernel.
    """
    structure = registry.get(traversal, "traversal").structure
    main = {
        registry.default_traversal(structure),
        registry.query_traversal(structure),
        registry.query_traversal(structure, coherence=1.0),
    }
    return traversal in main or (query == "closest" and not stats)


def _other_layouts(structure: str) -> list[str]:
    """Return one builder per structure class of ``structure`` besides the default builder's.

    Traversal kernels are compiled per layout type, which follows the class a builder
    returns (its return annotation): ``grid.two_level`` returns a ``TwoLevelGrid`` and
    needs its own kernels, while every ``bvh2`` builder returns a ``Bvh2``.
    """
    variants = registry.variants("builder", structure)
    default = registry.default_builder(structure)
    seen = {v.func.__annotations__.get("return") for v in variants if v.key == default}
    others = []
    for variant in variants:
        kind = variant.func.__annotations__.get("return")
        # An unannotated builder may return anything: its kernels are compiled too.
        if variant.key != default and (kind is None or kind not in seen):
            seen.add(kind)
            others.append(variant.key)
    return others


_MESH: list[Any] = []
_ACCELS: dict[str, api.Accel] = {}


def _accel(build_key: str) -> api.Accel:
    """Build (once per worker process) ``build_key``'s structure on the job mesh."""
    if not _MESH:
        _MESH.append(procedural.triangle_soup(MESH_TRIANGLES, seed=1))
    if build_key not in _ACCELS:
        _ACCELS[build_key] = api.build(_MESH[0], build_key)
    return _ACCELS[build_key]


def run_job(job: Job) -> tuple[Job, float]:
    """Run one job in this process; return it with its seconds."""
    start = time.perf_counter()
    accel = _accel(job.build_key)
    if job.traversal is None:
        accel.validate()
    else:
        n = PARALLEL_MIN_RAYS if job.parallel else SERIAL_RAYS
        rng = np.random.Generator(np.random.PCG64(3))
        origin = rng.uniform(-0.5, 1.5, (n, 3))
        target = rng.uniform(0.0, 1.0, (n, 3))
        accel.trace(RayBatch(origin, target - origin), query=job.query,
                    traversal=job.traversal, stats=job.stats)  # fmt: skip
    return job, time.perf_counter() - start


def precompile(
    job_list: list[Job],
    n_processes: int | None = None,
    on_done: Callable[[Job, float, int], None] | None = None,
) -> float:
    """Run ``job_list`` on ``n_processes`` worker processes; return the wall seconds.

    Each worker writes what it compiles into the on-disk cache, so the calling
    process (and every later one) loads those kernels instead of compiling them.
    Workers are spawned, not forked: a fork would copy numba's thread pools.
    ``on_done(job, seconds, n_done)`` is called as each job finishes.
    """
    n = n_processes or os.cpu_count() or 1
    if n < 1:
        raise ValueError(f"n_processes must be at least 1, got {n}")
    start = time.perf_counter()
    if n == 1 or len(job_list) <= 1:
        for k, job in enumerate(job_list, 1):
            _, seconds = run_job(job)
            if on_done is not None:
                on_done(job, seconds, k)
        return time.perf_counter() - start
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=n, mp_context=context) as pool:
        futures = [pool.submit(run_job, job) for job in job_list]
        for k, future in enumerate(as_completed(futures), 1):
            job, seconds = future.result()
            if on_done is not None:
                on_done(job, seconds, k)
    return time.perf_counter() - start
