"""Run a sweep: every cell of a configuration, resumable, in this process or on Dask.

:func:`sweep` reads the results file first (:mod:`rayaccel.study.results`) and runs
only the cells it does not hold, so an interrupted sweep (Ctrl-C, SIGKILL, a
crash) resumes where it stopped and repeats no finished cell. Scenes are taken one
at a time: the client loads the mesh and makes its ray sets
(:mod:`rayaccel.study.raysets`), then runs its cells (:mod:`rayaccel.study.cells`)
and appends each record as it arrives (on Dask, a scene of counter cells only
overlaps the loading of the next scene). A cell that raises is tried again, up to
:data:`MAX_ATTEMPTS` times, then recorded as failed with its error.

With ``workers`` or ``scheduler`` the cells run on a ``dask.distributed`` cluster
(a ``LocalCluster`` of ``workers`` single-threaded processes, or the cluster at
``scheduler``). The mesh and ray sets of a scene are scattered to every worker once
(``broadcast``); each worker builds the structures it needs and keeps them for
its next cells. Build and timing cells run one at a time per machine: the client
keeps at most one of them in flight per host, restricted to that host, so two
timings never share a machine; counter cells fill the workers. Each structure of
a scene's counter cells is built once, by a task of its own (one thread) on its
home worker (structures spread over the workers by their cell counts, turned by one
worker from scene to scene so that one builder's structures are not all built on
one worker), and each ray set's oracle answers are computed once, by a task of their
own. A counter cell prefers its traversal's worker, the same for the whole sweep (so
each worker loads only its own traversals' kernels), and takes the structure and the
answers from those tasks wherever it runs rather than building or answering again. A
worker that dies has its cell re-run by Dask (up to its ``allowed-failures``), and
then by the sweep, up to :data:`MAX_ATTEMPTS` times in all; a mesh or ray set that
died with it (scattered data cannot be recomputed) is scattered again first. The
single writer is this process.
"""

from __future__ import annotations

import os
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rayaccel.bench.harness import environment
from rayaccel.scene import catalog
from rayaccel.study.cells import (
    Cell,
    Record,
    balance,
    cells_by_scene,
    counter_reference,
    counter_structure,
    enumerate_cells,
    homes,
    run_cell,
)
from rayaccel.study.config import SweepConfig, load_config
from rayaccel.study.raysets import scene_raysets
from rayaccel.study.results import ResultsFile

#: Tries of a cell before it is recorded as failed for good.
MAX_ATTEMPTS = 3

Progress = Callable[[int, int, str], Any]


@dataclass(frozen=True, slots=True)
class SweepSummary:
    """What one call of :func:`sweep` did.

    Attributes
    ----------
    cells : int
        Cells of the configuration.
    skipped : int
        Cells already finished in the results file.
    ran : int
        Cells run now (including failed ones).
    failed : int
        Cells recorded as failed now.
    wall_seconds : float
        Wall-clock time of the whole call.
    cell_seconds : float
        Sum of the cells' own times (what the work itself took).
    rays_seconds : float
        Time spent making the scenes' ray sets (path tracing included).

    On Dask, the structures of counter cells are built by tasks of their own, whose
    time is in ``wall_seconds`` but not in ``cell_seconds``.
    """

    cells: int
    skipped: int
    ran: int
    failed: int
    wall_seconds: float
    cell_seconds: float
    rays_seconds: float

    @property
    def overhead(self) -> float:
        """Return the sweep's own share of the time, beyond its cells and ray sets."""
        work = self.cell_seconds + self.rays_seconds
        return (self.wall_seconds - work) / work if work > 0 else 0.0


def sweep(
    config: SweepConfig | str | os.PathLike[str],
    results: str | os.PathLike[str],
    *,
    workers: int = 0,
    scheduler: str | None = None,
    rays_folder: str | os.PathLike[str] | None = None,
    progress: Progress | None = None,
) -> SweepSummary:
    """Run the cells of ``config`` not yet in ``results``; append their records.

    Parameters
    ----------
    config : SweepConfig or path-like
        The configuration, or its TOML file (:func:`rayaccel.study.config.load_config`).
    results : path-like
        The JSON-lines results file, created or resumed.
    workers : int
        Run on a local Dask cluster of this many processes (0: in this process).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:port``) to run on.
    rays_folder : path-like, optional
        Where recorded ray sets go; default ``<results>.rays`` beside the results.
    progress : callable, optional
        Called as ``progress(done, total, label)`` after each cell.

    Returns
    -------
    SweepSummary
    """
    start = time.perf_counter()
    cfg = config if isinstance(config, SweepConfig) else load_config(config)
    results_path = Path(results)
    rays_dir = Path(rays_folder) if rays_folder else results_path.with_suffix(".rays")
    env = environment()
    out = ResultsFile(results_path, {"rayaccel": env["rayaccel_version"],
                                     "config": cfg.as_record(), "environment": env})  # fmt: skip
    cells = enumerate_cells(cfg)
    finished = out.finished_keys(MAX_ATTEMPTS)
    todo = [cell for cell in cells if cell.key not in finished]
    state = _State(out, len(todo), progress)
    rays_seconds = 0.0
    runner: _Runner = (
        _DaskRunner(workers, scheduler) if workers > 0 or scheduler else _LocalRunner()
    )
    try:
        for scene, scene_cells in cells_by_scene(todo):
            t0 = time.perf_counter()
            mesh = catalog.get(scene)
            needs_rays = any(cell.kind != "build" for cell in scene_cells)
            raysets = scene_raysets(mesh, scene, cfg.rays, rays_dir) if needs_rays else {}
            rays_seconds += time.perf_counter() - t0
            runner.run(scene_cells, cfg, mesh, raysets, state)
        runner.drain(state)
    finally:
        runner.close()
    return SweepSummary(
        cells=len(cells),
        skipped=len(cells) - len(todo),
        ran=state.ran,
        failed=state.failed,
        wall_seconds=time.perf_counter() - start,
        cell_seconds=state.cell_seconds,
        rays_seconds=rays_seconds,
    )


class _State:
    """The writer's bookkeeping: records appended, failures, progress."""

    def __init__(self, out: ResultsFile, total: int, progress: Progress | None) -> None:
        self.out = out
        self.total = total
        self.progress = progress
        self.ran = 0
        self.failed = 0
        self.cell_seconds = 0.0

    def finish(self, record: Record, attempts: int) -> None:
        record["attempts"] = attempts
        self.out.append(record)
        self.ran += 1
        self.failed += record["status"] != "ok"
        self.cell_seconds += float(record.get("seconds", 0.0))
        if self.progress is not None:
            self.progress(self.ran, self.total, record["key"])


class _Runner:
    def run(self, cells: list[Cell], config: SweepConfig, mesh: Any, raysets: dict[str, Any],
            state: _State) -> None:  # fmt: skip
        raise NotImplementedError

    def drain(self, state: _State) -> None:
        """Wait for the cells still in flight and record them (none by default)."""

    def close(self) -> None:
        """Release what the runner holds."""


class _LocalRunner(_Runner):
    """Cells one after the other in this process."""

    def run(self, cells: list[Cell], config: SweepConfig, mesh: Any, raysets: dict[str, Any],
            state: _State) -> None:  # fmt: skip
        for cell in cells:
            rayset = raysets.get(cell.rayset) if cell.rayset else None
            for attempt in range(1, MAX_ATTEMPTS + 1):
                record = run_cell(cell, config, mesh, rayset)
                if record["status"] == "ok" or attempt == MAX_ATTEMPTS:
                    state.finish(record, attempt)
                    break


def _killed_record(cell: Cell, exc: BaseException) -> Record:
    record = cell.fields()
    record.update(status="failed", error=f"{type(exc).__name__}: {exc}", seconds=0.0)
    return record


class _SceneInputs:
    """A scene's mesh, ray sets and counter structures on the cluster, made again when lost.

    Scattered data cannot be recomputed: when the worker holding its only copy dies (the
    scheduler's active memory manager drops replicas it sees no use for), every task that
    needs it is cancelled for "lost dependencies". So each cell takes its inputs from here
    when it is submitted, and a lost mesh or ray set is scattered again and a lost
    structure build submitted again. The client keeps the scene's mesh and ray sets until
    its cells are done.
    """

    def __init__(self, client: Any, config: SweepConfig, mesh: Any, raysets: dict[str, Any],
                 home: dict[str, str], cell_home: dict[tuple[str, str], str]) -> None:  # fmt: skip
        self.client = client
        self.config = config
        self.mesh = mesh
        self.raysets = raysets
        self.home = home
        self.cell_home = cell_home
        self.futures: dict[str, Any] = {}
        #: How often the inputs were made again (a cell's failure renews only the
        #: inputs it was submitted with, not ones already made again after it).
        self.generation = 0

    def _live(self, name: str, make: Callable[[], Any]) -> Any:
        future = self.futures.get(name)
        if future is None or future.status in ("lost", "cancelled", "error"):
            future = self.futures[name] = make()
        return future

    def renew(self, generation: int) -> None:
        """Make every input again for the next cells, unless done since ``generation``."""
        if generation == self.generation:
            self.generation += 1
            self.futures.clear()

    def _scatter(self, data: Any) -> Any:
        """Scatter ``data`` to every worker under a new key.

        A key derived from the data (Dask's default) would name the lost copy again,
        and cells given it were cancelled again ("lost dependencies") until they ran
        out of attempts.
        """
        return self.client.scatter(data, broadcast=True, hash=False)

    def mesh_future(self) -> Any:
        """Return the scattered mesh (on every worker)."""
        return self._live("mesh", lambda: self._scatter(self.mesh))

    def rayset_future(self, name: str | None) -> Any:
        """Return the scattered ray set ``name`` (None for a cell without one)."""
        if not name:
            return None
        rays = self.raysets[name]
        return self._live(f"rays:{name}", lambda: self._scatter(rays))

    def structure_future(self, builder: str) -> Any:
        """Return the build task of ``builder``'s counter structure (on its home worker)."""
        return self._live(
            f"structure:{builder}",
            lambda: self.client.submit(
                counter_structure, self.config, self.mesh_future(), builder,
                workers=[self.home[builder]], allow_other_workers=True, pure=False, priority=1,
            ),
        )  # fmt: skip

    def reference_future(self, name: str | None) -> Any:
        """Return the task answering ray set ``name``'s sampled rays with the oracle (once)."""
        if not name:
            return None
        return self._live(
            f"reference:{name}",
            lambda: self.client.submit(
                counter_reference, self.config, self.mesh_future(), self.rayset_future(name),
                pure=False, priority=1,
            ),
        )  # fmt: skip


class _DaskRunner(_Runner):
    """Cells on a ``dask.distributed`` cluster (see the module docstring).

    A scene of counter cells only does not wait for its cells: :meth:`run` returns
    once they are submitted, so the client loads the next scene while the workers
    compute, and no worker idles at the end of a scene while another finishes it.
    A scene with build or timing cells first waits for every cell in flight, then
    for its own, so nothing the client does overlaps a timing.
    """

    def __init__(self, workers: int, scheduler: str | None) -> None:
        from dask.distributed import Client, LocalCluster, as_completed

        self.cluster = None
        if scheduler:
            self.client = Client(scheduler)
        else:
            self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                        dashboard_address=None)  # fmt: skip
            self.client = Client(self.cluster)
        self.attempts: dict[str, int] = {}
        # In-flight futures: their cell, the host of an exclusive cell, the scene's inputs
        # and their generation when the cell was submitted
        self.futures: dict[Any, tuple[Cell, str | None, _SceneInputs, int]] = {}
        self.exclusive: deque[tuple[Cell, _SceneInputs]] = deque()
        self.busy: dict[str, bool] = {}
        self.done = as_completed()
        #: Scenes run so far, which turns the structures' homes (:func:`homes`).
        self.turn = 0
        #: The worker (by position) of each (builder, traversal)'s counter cells, kept
        #: for the whole sweep (:meth:`_cell_homes`).
        self.cell_bins: dict[tuple[str, str], int] = {}

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()

    def _hosts(self) -> dict[str, list[str]]:
        """Return the workers of each host."""
        hosts: dict[str, list[str]] = {}
        for address, info in self.client.scheduler_info()["workers"].items():
            hosts.setdefault(info.get("host", address), []).append(address)
        return {host: sorted(addresses) for host, addresses in hosts.items()}

    def _submit(self, cell: Cell, host: str | None, inputs: _SceneInputs) -> None:
        self.attempts[cell.key] = self.attempts.get(cell.key, 0) + 1
        config, mesh_f = inputs.config, inputs.mesh_future()
        rayset = inputs.rayset_future(cell.rayset)
        # A host, not a worker address, for timed cells: a worker that dies is
        # replaced under another address, and the cell must be able to run there.
        # Counter cells prefer their structure's worker but may run on any.
        if host is not None:
            future = self.client.submit(run_cell, cell, config, mesh_f, rayset, workers=[host],
                                        pure=False)  # fmt: skip
        else:
            home = inputs.cell_home[cell.builder, str(cell.traversal)]
            future = self.client.submit(run_cell, cell, config, mesh_f, rayset,
                                        inputs.structure_future(cell.builder),
                                        inputs.reference_future(cell.rayset), workers=[home],
                                        allow_other_workers=True, pure=False)  # fmt: skip
        self.futures[future] = (cell, host, inputs, inputs.generation)
        self.done.add(future)

    def _feed_exclusive(self) -> None:
        for host, busy in self.busy.items():
            if not busy and self.exclusive:
                self.busy[host] = True
                cell, inputs = self.exclusive.popleft()
                self._submit(cell, host, inputs)

    def _collect(self, future: Any, state: _State) -> None:
        """Record a finished future's cell, or submit it again."""
        cell, host, inputs, generation = self.futures.pop(future)
        try:
            record = future.result()
        except Exception as exc:  # the worker died more often than Dask allows, or lost inputs
            record = _killed_record(cell, exc)
            inputs.renew(generation)
        if host is not None:
            self.busy[host] = False
        if record["status"] != "ok" and self.attempts[cell.key] < MAX_ATTEMPTS:
            if host is not None:
                self.exclusive.appendleft((cell, inputs))
            else:
                self._submit(cell, None, inputs)
        else:
            state.finish(record, self.attempts[cell.key])
        self._feed_exclusive()

    def _cell_homes(self, cells: list[Cell], addresses: list[str]) -> dict[tuple[str, str], str]:
        """Return the worker of each (builder, traversal)'s counter cells.

        A traversal's cells stay on one worker for the whole sweep, every scene
        included, so each worker loads the kernels of its own traversals only (a
        kernel's first call in a process loads it, 50–150 ms). Groups are placed by
        :func:`rayaccel.study.cells.balance` when first seen.
        """
        groups = Counter((c.builder, str(c.traversal)) for c in cells if not c.exclusive)
        bins = balance(groups, len(addresses), self.cell_bins)
        self.cell_bins.update(bins)
        return {group: addresses[i] for group, i in bins.items()}

    def drain(self, state: _State) -> None:
        """Wait for every cell in flight and record it."""
        while self.futures:
            self._collect(next(self.done), state)

    def run(self, cells: list[Cell], config: SweepConfig, mesh: Any, raysets: dict[str, Any],
            state: _State) -> None:  # fmt: skip
        client = self.client
        pipelined = not any(cell.exclusive for cell in cells)
        if pipelined:  # record what has finished meanwhile, without waiting
            while self.done.has_ready():
                self._collect(next(self.done), state)
        else:
            self.drain(state)
        by_host = self._hosts()
        for host in by_host:
            self.busy.setdefault(host, False)
        # Each structure of the counter cells is built once, by a task on its home worker
        # (structures spread over the workers by their cell counts, turned by one worker
        # from scene to scene), ahead of the cells already waiting there (priority); the
        # cells go preferably to their traversal's worker (:meth:`_cell_homes`), and take
        # the structure from the build wherever they run.
        addresses = [a for host in by_host for a in by_host[host]]
        groups = Counter(cell.builder for cell in cells if not cell.exclusive)
        turn, self.turn = self.turn, self.turn + 1
        home = {b: addresses[i] for b, i in homes(groups, len(addresses), turn).items()}
        inputs = _SceneInputs(client, config, mesh, raysets, home,
                              self._cell_homes(cells, addresses))  # fmt: skip
        inputs.mesh_future()
        for name in raysets:
            inputs.rayset_future(name)
        for builder in home:
            inputs.structure_future(builder)
        for cell in cells:
            if cell.exclusive:
                self.exclusive.append((cell, inputs))
            else:
                self._submit(cell, None, inputs)
        self._feed_exclusive()
        if not pipelined:
            self.drain(state)
