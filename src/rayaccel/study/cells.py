"""A sweep's units of work (*cells*) and how one is run, on whatever process runs it.

Each (scene, builder) has a **build** cell per thread count (the median build time
of Table 5.4 and the structure's size); each (scene, builder, traversal, ray set)
has one **counters** cell (the instrumented kernel on one thread: counters per
ray, the ``bytes`` counter for the memory traffic, and a sample of rays checked
against the oracle) and a **timing** cell per thread count (the plain kernel,
``repeats`` passes round-robin with the peers on the same rays, as
:func:`rayaccel.bench.harness.timed_round_robin` does). Counters do not depend on
the thread count, so counter cells run single-threaded and fill the workers,
while build and timing cells run one at a time per machine
(:attr:`Cell.exclusive`).

A cell's ``key`` names it stably across runs: its kind, scene, builder,
traversal, ray set, threads and the digest of the ray parameters, so a resumed
sweep skips exactly the finished cells, and changing the rays makes new cells.

Structures are built once per (scene, builder) in the process that runs the cell
and kept there (:data:`_ACCELS`), as are the peers' structures, so the
cells of one structure reuse it. On Dask a counter cell may also receive its
structure from a build task (:func:`counter_structure`) run on another worker, so
moving a cell between workers copies the structure instead of building it again.
"""

from __future__ import annotations

import functools
import os
import socket
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from rayaccel import api
from rayaccel.bench.harness import (
    OWN_POOL,
    RTOL_OURS,
    count_mismatches,
    counter_summary,
    reference_hits,
    timed_round_robin,
)
from rayaccel.bench.peers import get_peer
from rayaccel.bench.raysets import RaySet
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.study.config import SweepConfig

Record = dict[str, Any]

#: Cell kinds, in the order a scene's cells are listed.
KINDS = ("build", "counters", "timing")

#: Structures and peers built in this process: (scene digest, key) -> object. Builders
#: give the same structure for every thread count, so one serves every cell.
_ACCELS: dict[tuple[str, str], api.Accel] = {}
_PEERS: dict[tuple[str, str], Any] = {}
#: Oracle answers on a ray set's validation sample, shared by its cells.
_REFERENCES: dict[tuple[str, str, int, int, int], Any] = {}


@dataclass(frozen=True, slots=True)
class Cell:
    """One unit of work of a sweep."""

    kind: str
    scene: str
    builder: str
    traversal: str | None
    rayset: str | None
    threads: int
    rays_digest: str

    @property
    def key(self) -> str:
        """Return the stable name of the cell (see the module docstring)."""
        return "|".join(
            [self.kind, self.scene, self.builder, self.traversal or "-", self.rayset or "-",
             f"t{self.threads}", self.rays_digest]
        )  # fmt: skip

    @property
    def exclusive(self) -> bool:
        """Whether the cell is timed, and so runs alone on its machine."""
        return self.kind != "counters"

    def fields(self) -> Record:
        """Return the cell's identity as record fields."""
        return {"key": self.key, "kind": self.kind, "scene": self.scene,
                "builder": self.builder, "traversal": self.traversal, "rayset": self.rayset,
                "threads": self.threads}  # fmt: skip


def balance(
    groups: dict[Any, int], n_bins: int, placed: dict[Any, int] | None = None
) -> dict[Any, int]:
    """Assign weighted groups to ``n_bins`` bins, heaviest first to the lightest bin (LPT).

    Groups already in ``placed`` keep their bin (modulo ``n_bins``) and count toward
    its load.
    """
    n = max(1, n_bins)
    placed = placed or {}
    load = [0] * n
    out = {}
    for group, weight in groups.items():
        if group in placed:
            out[group] = placed[group] % n
            load[out[group]] += weight
    for group, weight in sorted(groups.items(), key=lambda item: -item[1]):
        if group not in out:
            target = load.index(min(load))
            out[group] = target
            load[target] += weight
    return out


def homes(groups: dict[Any, int], n_bins: int, turn: int) -> dict[Any, int]:
    """Assign weighted groups to bins by :func:`balance`, then rotate by ``turn`` bins.

    The sweep gives each scene's structures homes with ``turn`` the scene's position:
    the cell counts do not show a build's cost (on one thread the staircase's kd-tree
    takes 33× its binned-SAH BVH's time, the living room's 61×), so without the turn
    the same builder of every scene would be built on the same worker.
    """
    n = max(1, n_bins)
    return {group: (target + turn) % n for group, target in balance(groups, n).items()}


def enumerate_cells(config: SweepConfig) -> list[Cell]:
    """Return every cell of ``config``: per scene, builds, then counters, then timings."""
    digest = config.rays.digest()
    cells: list[Cell] = []
    wanted = set(config.passes)
    for scene in config.scenes:
        for builder in config.builders:
            for threads in config.threads:
                cells.append(Cell("build", scene, builder, None, None, threads, digest))
        for builder in config.builders:
            for traversal in config.traversals[builder]:
                for rayset in config.rays.set_names():
                    cells.append(Cell("counters", scene, builder, traversal, rayset, 1, digest))
        for builder in config.builders:
            for traversal in config.traversals[builder]:
                for rayset in config.rays.set_names():
                    for threads in config.threads:
                        cells.append(
                            Cell("timing", scene, builder, traversal, rayset, threads, digest)
                        )
    return [cell for cell in cells if cell.kind in wanted]


class _Threads:
    """Set numba's thread count for a block, restoring it after."""

    def __init__(self, n: int) -> None:
        self.n = min(int(n), numba.config.NUMBA_NUM_THREADS)
        self.saved = numba.get_num_threads()

    def __enter__(self) -> _Threads:
        numba.set_num_threads(self.n)
        return self

    def __exit__(self, *exc: object) -> None:
        numba.set_num_threads(self.saved)


def structure(mesh: TriangleMesh, builder: str, threads: int, config: SweepConfig) -> api.Accel:
    """Return this process's structure of the builder labelled ``builder`` over ``mesh``.

    It is built on first use, with ``threads`` threads.
    """
    key = (mesh.digest(), builder)
    if key not in _ACCELS:
        with _Threads(threads):
            _ACCELS[key] = _build_once(mesh, builder, config)
    return _ACCELS[key]


def counter_structure(config: SweepConfig, mesh: TriangleMesh, builder: str) -> api.Accel:
    """Return the structure the counter cells of ``builder`` on ``mesh`` share (one thread).

    The Dask runner submits it as a task of its own and hands the result to those
    cells (:func:`run_cell`'s ``accel``).
    """
    return structure(mesh, builder, 1, config)


def counter_reference(config: SweepConfig, mesh: TriangleMesh, rayset: RaySet) -> Any:
    """Return the oracle's answers to ``rayset``'s sampled rays (one thread), kept here too.

    The Dask runner submits it once per ray set and hands the result to the ray set's
    counter cells (:func:`run_cell`'s ``reference``), so no two workers compute it.
    """
    with _Threads(1):
        return _reference(config, mesh, rayset)


def _reference(config: SweepConfig, mesh: TriangleMesh, rayset: RaySet) -> Any:
    """Return this process's oracle answers to ``rayset`` (computed on first use)."""
    key = _reference_key(config, mesh, rayset)
    if key not in _REFERENCES:
        _REFERENCES[key] = reference_hits(mesh, rayset, config.validate, config.rays.seed)
    return _REFERENCES[key]


def _reference_key(config: SweepConfig, mesh: TriangleMesh, rayset: RaySet) -> tuple[Any, ...]:
    return (mesh.digest(), rayset.kind, rayset.n_rays, config.validate, config.rays.seed)


def _build_once(mesh: TriangleMesh, builder: str, config: SweepConfig) -> api.Accel:
    key, options = config.variant(builder)
    return api.build(mesh, key, **options)


def _trace(accel: api.Accel, cell: Cell, config: SweepConfig, rays: Any, query: str,
           stats: bool = False) -> Any:  # fmt: skip
    key, options = config.variant(str(cell.traversal))
    return accel.trace(rays, query=query, traversal=key, stats=stats, **options)


def _peer(name: str, mesh: TriangleMesh) -> Any:
    key = (mesh.digest(), name)
    if key not in _PEERS:
        peer = get_peer(name)
        if peer.available() and peer.skip_reason(mesh) is None:
            peer.build(mesh)
        _PEERS[key] = peer
    return _PEERS[key]


def _build(cell: Cell, config: SweepConfig, mesh: TriangleMesh) -> Record:
    with _Threads(cell.threads):
        _build_once(mesh, cell.builder, config)  # compiles on a process's first build
        times = []
        accel = None
        for _ in range(config.build_repeats):
            start = time.perf_counter()
            accel = _build_once(mesh, cell.builder, config)
            times.append(time.perf_counter() - start)
    assert accel is not None
    _ACCELS[(mesh.digest(), cell.builder)] = accel
    info = accel.info()
    return {
        "build_ms_median": round(float(np.median(times)) * 1e3, 4),
        "build_ms_best": round(float(np.min(times)) * 1e3, 4),
        "structure": accel.structure_name,
        "bytes": info.get("bytes"),
        "info": {k: v for k, v in info.items() if isinstance(v, (int, float, str))},
    }


def _counters(cell: Cell, config: SweepConfig, mesh: TriangleMesh, rayset: RaySet) -> Record:
    # Everything on one thread, the structure's build and the oracle included, so
    # counter cells on several workers of one machine do not compete for its cores.
    with _Threads(1):
        accel = structure(mesh, cell.builder, 1, config)
        hits = _trace(accel, cell, config, rayset.rays, rayset.query, stats=True)
        ref = _reference(config, mesh, rayset)
    record = counter_summary(hits.stats)
    record["n_rays"] = rayset.n_rays
    record["hit_rate"] = round(float(np.mean(hits.hit)), 6) if rayset.n_rays else 0.0
    means = record.get("counters_mean", {})
    record["bytes_per_ray"] = means.get("bytes")
    if ref is not None:
        t = None if rayset.query == "any" else hits.t[ref.index]
        record["validated"] = int(ref.index.size)
        record["mismatches"] = count_mismatches(ref, rayset.query, t, hits.prim[ref.index],
                                                RTOL_OURS)  # fmt: skip
    return record


def _timing(cell: Cell, config: SweepConfig, mesh: TriangleMesh, rayset: RaySet) -> Record:
    accel = structure(mesh, cell.builder, cell.threads, config)
    rays, query = rayset.rays, rayset.query
    fns: list[Callable[[], Any]] = [lambda: _trace(accel, cell, config, rays, query)]
    peers: list[str] = []
    notes: list[str] = []
    for name in config.peers:
        peer = _peer(name, mesh)
        reason = peer.unavailable_reason() or peer.skip_reason(mesh)
        if reason is None and peer.limit(rays).n_rays != rays.n_rays:
            reason = "runs on part of the rays only"
        if reason is not None:
            notes.append(f"{name}: {reason}")
            continue
        peer.set_threads(cell.threads)
        try:
            prepared = peer.prepare(rays)
        except Exception as exc:  # a peer refusing these rays (e.g. Open3D's tmax rule)
            notes.append(f"{name}: {exc}")
            continue
        call = peer.occluded if query == "any" else peer.intersect
        fns.append(functools.partial(call, prepared))
        peers.append(name)
    with _Threads(cell.threads):
        seconds, _ = timed_round_robin(fns, config.repeats, [OWN_POOL, *peers])
    ours = float(np.median(seconds[0]))
    record: Record = {
        "n_rays": rays.n_rays,
        "repeats": config.repeats,
        "ms_median": round(ours * 1e3, 4),
        "ms_best": round(float(np.min(seconds[0])) * 1e3, 4),
        "mrays_median": round(rays.n_rays / ours / 1e6, 4) if ours > 0 else None,
        "mrays_best": round(rays.n_rays / float(np.min(seconds[0])) / 1e6, 4),
        "peers": {},
    }
    for name, peer_seconds in zip(peers, seconds[1:], strict=True):
        median = float(np.median(peer_seconds))
        record["peers"][name] = {
            "mrays_median": round(rays.n_rays / median / 1e6, 4) if median > 0 else None,
            "ratio": round(median / ours, 4) if ours > 0 else None,
        }
    if notes:
        record["notes"] = notes
    return record


def run_cell(
    cell: Cell,
    config: SweepConfig,
    mesh: TriangleMesh,
    rayset: RaySet | None,
    accel: api.Accel | None = None,
    reference: Any = None,
) -> Record:
    """Run one cell; return its record (``status`` "ok", or "failed" with the error).

    ``accel``, the cell's structure built elsewhere (:func:`counter_structure`), and
    ``reference``, its ray set's oracle answers computed elsewhere
    (:func:`counter_reference`), are kept for the cells that follow in this process.
    The record carries ``seconds``, the cell's own wall-clock time, and when
    (``started``, Unix time) and where (``host``, ``pid``) it ran.
    """
    if accel is not None:
        _ACCELS.setdefault((mesh.digest(), cell.builder), accel)
    if reference is not None and rayset is not None:
        _REFERENCES.setdefault(_reference_key(config, mesh, rayset), reference)
    start = time.perf_counter()
    record: Record = cell.fields()
    record.update(started=time.time(), host=socket.gethostname(), pid=os.getpid())
    try:
        if cell.kind == "build":
            record.update(_build(cell, config, mesh))
        elif rayset is None:
            raise ValueError(f"{cell.key}: no ray set")
        elif cell.kind == "counters":
            record.update(_counters(cell, config, mesh, rayset))
        else:
            record.update(_timing(cell, config, mesh, rayset))
        record["status"] = "ok"
    except Exception as exc:  # recorded, so the sweep goes on (the sweep retries it)
        record["status"] = "failed"
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc(limit=8)
    record["seconds"] = round(time.perf_counter() - start, 4)
    return record


def cells_by_scene(cells: list[Cell]) -> Iterator[tuple[str, list[Cell]]]:
    """Yield ``(scene, cells)`` groups in the order the scenes first appear."""
    order: dict[str, list[Cell]] = {}
    for cell in cells:
        order.setdefault(cell.scene, []).append(cell)
    yield from order.items()
