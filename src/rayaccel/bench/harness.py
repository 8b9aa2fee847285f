"""The benchmark harness behind ``rayaccel bench`` (STYLE §11, tinybvh's speed-test protocol).

For every scene, thread count and system (each registered builder × each traversal
of its structure, plus the available peers of :mod:`rayaccel.bench.peers`):

1. **Compile first.** Before any scene, every builder and every traversal variant
   (closest/any × plain/stats × the serial and parallel kernels the run will call)
   runs once on a small procedural mesh large enough to reach the parallel code
   paths (``warmup_triangles``). The first call's time is recorded as a
   ``compile`` record, labelled ``jit`` when numba wrote new cache files during it
   and ``cache`` when it only loaded them, so compilation never pollutes a timing.
2. **Validate** each system on each ray set against an oracle before timing it: a
   deterministic sample of ``validate`` rays (default 200) is traced by
   :func:`rayaccel.kernels.brute_force.brute_force_trace` (O(rays × triangles);
   for scenes where that exceeds :data:`BRUTE_FORCE_BUDGET` triangle tests the
   sample shrinks, or Embree answers if available). rayaccel systems must match
   exactly (same hit or miss, ``t`` within 1e-5 relative; a different triangle
   only at equal ``t``); peers, whose triangle tests differ, may disagree on up to
   2% of the sample (edge-grazing rays). A failing system is reported in an
   ``invalid`` record and not timed.
3. **Warm up** with one untimed pass, then time ``repeats`` passes and keep the
   **median** and the **minimum** (reported as Mrays/s median and best).
4. For rayaccel systems, trace again with ``stats=True`` (warm-up plus
   ``repeats`` passes) for the mean nodes and primitives per ray and the stats
   overhead ``median(stats) / median(plain) - 1``.

Builds are timed the same way: one untimed build (which compiles the parallel
builder paths on first use), then the median of ``build_repeats`` builds.

The ray sets (:mod:`rayaccel.bench.raysets`) are generated once per scene and the
same objects go to every system. Each measurement becomes one JSON record
(:func:`environment` fields included) handed to ``on_record`` as soon as it is
finished, so a JSONL sink (:class:`rayaccel.bench.report.JsonlWriter`) keeps every
finished result if the run is interrupted.
"""

from __future__ import annotations

import datetime
import functools
import importlib.metadata
import os
import platform
import subprocess
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from rayaccel import api, registry
from rayaccel.bench import peers as peers_mod
from rayaccel.bench.raysets import RAY_KINDS, RaySet, parse_kinds, standard_raysets
from rayaccel.counters import COUNTER_NAMES
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.brute_force import brute_force_trace
from rayaccel.queries import QUERY_ANY, QUERY_CLOSEST
from rayaccel.rays.batch import RayBatch
from rayaccel.rays.views import VIEW_SEPARATOR, split_view
from rayaccel.scene import catalog, procedural
from rayaccel.scene.io import scene_stem
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.run import PARALLEL_MIN_RAYS

#: Most ray/triangle tests the brute-force validation may spend per ray set.
BRUTE_FORCE_BUDGET = 400_000_000
#: Relative ``t`` tolerance of rayaccel systems and of peers against the oracle.
RTOL_OURS = 1e-5
RTOL_PEER = 1e-3
#: Share of the validation sample a peer may get wrong (different triangle tests).
PEER_MISMATCH_FRACTION = 0.02
#: Most rays of the compile warm-up (above every traversal's parallel threshold).
WARMUP_RAYS = 2048

Record = dict[str, Any]


#: A measurement's cell: scene label, system, thread count, ray set.
CellKey = tuple[str, str, int, str]


def cell_key(record: Mapping[str, Any]) -> CellKey:
    """Return the cell a ``trace`` or ``invalid`` record measured."""
    return (str(record.get("scene")), str(record.get("system")), int(record.get("threads") or 0),
            str(record.get("ray_type")))  # fmt: skip


def completed_cells(records: Iterable[Mapping[str, Any]]) -> dict[CellKey, Record]:
    """Return the finished cells of earlier records (``trace`` or ``invalid``), by cell.

    ``rayaccel bench --resume`` passes them as :attr:`BenchConfig.done`, so a run that was
    interrupted (SIGINT, SIGKILL: the results file only ever holds whole records, see
    :class:`rayaccel.bench.report.JsonlWriter`) completes its set without repeating work.
    """
    return {cell_key(r): dict(r) for r in records if r.get("record") in ("trace", "invalid")}


#: Seconds :func:`timed_round_robin` waits when the thread pool changes.
SETTLE_SECONDS = 0.05
#: The pool name of rayaccel's own passes (numba's threads) for :func:`timed_round_robin`.
OWN_POOL = "rayaccel"


@dataclass(frozen=True)
class BenchConfig:
    """What to measure.

    Attributes
    ----------
    scenes : sequence of str
        Catalog names or scene file paths.
    builders : sequence of str
        Builder keys; empty means every registered builder.
    traversals : sequence of str
        Traversal keys; empty means every traversal of each builder's structure.
    builder_options : mapping
        Options passed to every builder (unknown names raise).
    ray_kinds : sequence of str
        Subset of ``primary``, ``diffuse``, ``shadow``.
    threads : sequence of int
        Thread counts to run with; empty means numba's default (all cores).
    peers : sequence of str
        Peer names (:data:`rayaccel.bench.peers.PEERS`); unavailable ones are noted
        and skipped.
    repeats : int
        Timed passes per measurement (after one untimed warm-up).
    build_repeats : int
        Timed builds per system (after one untimed build).
    width, height : int
        Primary-ray resolution.
    validate : int
        Rays checked against the oracle per system and ray set; 0 disables.
    seed : int
        Seed of the ray sets and of the validation sample.
    warmup_triangles : int
        Size of the compile warm-up mesh.
    settle_ms : float
        Pause before a pass whose thread pool differs from the pass before it, so the
        other system's spinning threads are idle (:func:`timed_round_robin`).
    done : mapping
        Records of an earlier, interrupted run of the same command, by :func:`cell_key`
        (:func:`completed_cells`): their cells are not measured again, and the
        reference peer's earlier rates serve the ratios of the cells still to measure.
    """

    scenes: Sequence[str]
    builders: Sequence[str] = ()
    traversals: Sequence[str] = ()
    builder_options: Mapping[str, Any] = field(default_factory=dict)
    ray_kinds: Sequence[str] = tuple(RAY_KINDS)
    threads: Sequence[int] = ()
    peers: Sequence[str] = ()
    repeats: int = 5
    build_repeats: int = 3
    width: int = 512
    height: int = 512
    validate: int = 200
    seed: int = 0
    warmup_triangles: int = 40_000
    settle_ms: float = SETTLE_SECONDS * 1e3
    done: Mapping[CellKey, Record] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.scenes:
            raise InvalidInputError("scenes: expected at least one scene")
        for name in ("repeats", "build_repeats", "width", "height", "warmup_triangles"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InvalidInputError(f"{name}: expected an int >= 1, got {value!r}")
        if not isinstance(self.validate, int) or self.validate < 0:
            raise InvalidInputError(f"validate: expected an int >= 0, got {self.validate!r}")
        settle = self.settle_ms
        if isinstance(settle, bool) or not isinstance(settle, (int, float)) or not (
            0.0 <= settle <= 10_000.0
        ):
            raise InvalidInputError(f"settle_ms: expected 0..10000, got {settle!r}")
        parse_kinds(list(self.ray_kinds))
        for key in self.builders:
            registry.get_chain(key)
        for key in self.traversals:
            registry.get(key, "traversal")
        for name in self.peers:
            peers_mod.get_peer(name)
        max_threads = int(numba.config.NUMBA_NUM_THREADS)
        for n in self.threads:
            if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= max_threads:
                raise InvalidInputError(
                    f"threads: expected 1..{max_threads} (NUMBA_NUM_THREADS), got {n!r}"
                )

    def builder_keys(self) -> list[str]:
        """Return the build keys to measure (every builder and configuration if none named)."""
        return list(self.builders) or registry.build_keys()

    def traversal_keys(self, builder: str) -> list[str]:
        """Return the traversals to measure with ``builder``'s structure."""
        structure = registry.get_chain(builder)[0].structure
        available = registry.keys("traversal", structure)
        if not self.traversals:
            return available
        return [key for key in self.traversals if key in available]

    def thread_counts(self) -> list[int]:
        """Return the thread counts (numba's default if none was named)."""
        return list(self.threads) or [int(numba.config.NUMBA_NUM_THREADS)]


@dataclass
class BenchResult:
    """Everything a run produced.

    Attributes
    ----------
    records : list of dict
        Every record, in the order they were made.
    notes : list of str
        Things a reader of the table must know (skipped peers, thread control).
    """

    records: list[Record] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


# -- environment -------------------------------------------------------------------------------


def cpu_model() -> str:
    """Return the CPU model from ``/proc/cpuinfo`` (or :func:`platform.processor`)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as handle:
            for line in handle:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_sha() -> str | None:
    """Return the git commit of the rayaccel checkout (``+dirty`` if modified), or None."""
    root = Path(__file__).resolve().parents[3]

    def git(*args: str) -> str:
        run = subprocess.run(
            ["git", *args], cwd=root, capture_output=True, text=True, timeout=5, check=True
        )
        return run.stdout.strip()

    try:
        sha = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None
    return f"{sha}+dirty" if dirty else sha or None


def threading_layer() -> str:
    """Return numba's active threading layer, or ``"unset"`` before any parallel kernel."""
    try:
        return str(numba.threading_layer())
    except ValueError:
        return "unset"


def environment() -> Record:
    """Return the fields every record carries: versions, machine, git sha."""
    try:
        version = importlib.metadata.version("rayaccel")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    return {
        "rayaccel_version": version,
        "numba_version": numba.__version__,
        "numpy_version": np.__version__,
        "python_version": platform.python_version(),
        "platform": platform.platform(),
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "numba_max_threads": int(numba.config.NUMBA_NUM_THREADS),
        "git_sha": git_sha(),
    }


def numba_cache_dirs() -> list[Path]:
    """Return the folders numba caches rayaccel's kernels in.

    ``NUMBA_CACHE_DIR`` when set; otherwise every ``__pycache__`` folder inside the
    rayaccel package (numba writes its cache beside the source when it can).
    """
    if numba.config.CACHE_DIR:
        return [Path(numba.config.CACHE_DIR)]
    package = Path(__file__).resolve().parents[1]
    return sorted(p for p in package.rglob("__pycache__") if p.is_dir())


def numba_cache_files() -> list[Path]:
    """Return every numba cache file (``*.nbi`` index, ``*.nbc`` code) of rayaccel."""
    files: list[Path] = []
    for folder in numba_cache_dirs():
        files.extend(p for p in folder.rglob("*") if p.suffix in (".nbi", ".nbc"))
    return sorted(files)


def _cache_snapshot() -> dict[Path, int]:
    snapshot = {}
    for path in numba_cache_files():
        try:
            snapshot[path] = path.stat().st_mtime_ns
        except OSError:
            continue
    return snapshot


# -- helpers -----------------------------------------------------------------------------------


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _timed(fn: Callable[[], Any], repeats: int) -> tuple[np.ndarray, Any]:
    """Run ``fn`` once untimed, then ``repeats`` timed; return seconds and the last result."""
    result = fn()
    seconds = np.empty(repeats)
    for i in range(repeats):
        start = time.perf_counter()
        result = fn()
        seconds[i] = time.perf_counter() - start
    return seconds, result


def timed_round_robin(
    fns: Sequence[Callable[[], Any]],
    repeats: int,
    pools: Sequence[str] | None = None,
    settle: float = SETTLE_SECONDS,
) -> tuple[list[np.ndarray], list[Any]]:
    """Time each of ``fns`` once per round for ``repeats`` rounds, each right after an untimed run.

    The untimed run warms the caches with the function's own data, as a block of
    repeated passes would, so no pass pays for the previous function's; the rounds
    spread every function over the same stretch of time, so a noisy phase of the
    machine falls on every function alike (``docs/performance.md``, "Tracing against
    Embree", records what the other orders gave). Before the untimed run of a function
    whose thread pool differs from the one run before it, the round waits ``settle``
    seconds: worker threads (numba's OpenMP, Embree's TBB, Dr.Jit's pool)
    spin a while after their work and would otherwise take cores from the other
    system's timed pass.

    Parameters
    ----------
    fns : sequence of callable
        The functions to time, called with no arguments.
    repeats : int
        Timed rounds.
    pools : sequence of str, optional
        The thread pool each function runs on (:data:`OWN_POOL` for rayaccel's passes,
        a peer's name for its); None: no waiting.
    settle : float
        The wait, in seconds (:data:`SETTLE_SECONDS` by default).

    Returns
    -------
    seconds : list of (repeats,) float64 ndarray
        The time of each function in each round.
    results : list
        The last result of each function.
    """
    results: list[Any] = [None] * len(fns)
    seconds = [np.empty(repeats) for _ in fns]
    previous = None
    for i in range(repeats):
        for k, fn in enumerate(fns):
            if pools is not None and pools[k] != previous:
                time.sleep(settle)
                previous = pools[k]
            fn()
            start = time.perf_counter()
            results[k] = fn()
            seconds[k][i] = time.perf_counter() - start
    return seconds, results


def sample_index(n: int, k: int, seed: int) -> np.ndarray:
    """Return ``min(k, n)`` sorted distinct ray indices drawn with ``seed``."""
    if k >= n:
        return np.arange(n)
    rng = np.random.Generator(np.random.PCG64(seed))
    return np.sort(rng.choice(n, size=k, replace=False))


def scene_label(spec: str) -> str:
    """Return the name a scene is reported under (a file path gives its stem).

    A view after the scene (``living_room@yaw120``, :mod:`rayaccel.rays.views`) stays
    in the label: each view is a scene of its own in the tables.
    """
    scene, view = split_view(spec)
    stem = scene_stem(scene) if os.sep in scene or Path(scene).suffix else scene
    return stem if view is None else f"{stem}{VIEW_SEPARATOR}{view}"


@dataclass(frozen=True)
class _Cells:
    """One scene at one thread count: what every system measures, and the reference's rates."""

    mesh: TriangleMesh
    raysets: Mapping[str, RaySet]
    references: Mapping[str, _Reference | None]
    #: ``scene``, ``n_tris`` and ``threads``: the fields every record of these cells has.
    base: Record
    #: Mrays/s of the reference peer per ray kind, for the ``ratio_vs_open3d`` fields.
    rates: dict[str, float] = field(default_factory=dict)


@dataclass
class _Reference:
    """Oracle answers on a sample of one ray set."""

    index: np.ndarray
    rays: RayBatch
    t: np.ndarray
    prim: np.ndarray
    source: str


def reference_hits(
    mesh: TriangleMesh, rayset: RaySet, k: int, seed: int, notes: list[str] | None = None
) -> _Reference | None:
    """Answer ``k`` sampled rays of ``rayset`` with the brute-force oracle (or Embree).

    Returns None when ``k`` is 0 or no oracle fits the budget.
    """
    if k <= 0 or rayset.n_rays == 0:
        return None
    n_tris = mesh.n_triangles
    k = min(k, rayset.n_rays)
    source = "brute_force"
    if k * n_tris > BRUTE_FORCE_BUDGET:
        embree = peers_mod.EmbreePeer()
        if embree.available():
            source = "embree"
        else:
            k = max(16, BRUTE_FORCE_BUDGET // n_tris)
            if notes is not None:
                notes.append(f"{mesh.name}: validation sample cut to {k} rays (brute force budget)")
    index = sample_index(rayset.n_rays, k, seed)
    rays = rayset.rays.subset(index)
    query = QUERY_ANY if rayset.query == "any" else QUERY_CLOSEST
    if source == "embree":
        embree.build(mesh)
        if query == QUERY_ANY:
            occluded = embree.occluded(rays)
            return _Reference(index, rays, np.zeros(k), np.where(occluded, 0, -1), source)
        t, prim = embree.intersect(rays)
        return _Reference(index, rays, t, prim, source)
    tri = mesh.hit_rows()
    t, prim, _, _ = brute_force_trace(tri, rays.origin, rays.direction, rays.tmin, rays.tmax, query)
    return _Reference(index, rays, t, prim, source)


def count_mismatches(
    ref: _Reference, query: str, t: np.ndarray | None, prim: np.ndarray, rtol: float
) -> int:
    """Count sampled rays whose answer disagrees with the oracle.

    Closest hit: hit/miss differs, or ``|t - t_ref| > rtol·max(1, |t_ref|)`` (a
    different triangle at an equal ``t`` is a tie, not an error). Any hit: the
    occluded flag differs.
    """
    hit = np.asarray(prim) >= 0
    ref_hit = ref.prim >= 0
    bad = hit != ref_hit
    if query == "closest" and t is not None:
        both = hit & ref_hit
        tol = rtol * np.maximum(1.0, np.abs(ref.t.astype(np.float64)))
        with np.errstate(invalid="ignore"):
            far = np.abs(np.asarray(t, dtype=np.float64) - ref.t) > tol
        bad |= both & far
    return int(bad.sum())


class _Progress:
    """A rich progress bar on stderr, or nothing."""

    def __init__(self, enabled: bool, total: int) -> None:
        self._progress: Any = None
        if enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )

            self._progress = Progress(
                TextColumn("[bold]bench[/]"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("{task.description}"),
                console=Console(stderr=True),
                transient=True,
            )
            self._task = self._progress.add_task("starting", total=total)

    def __enter__(self) -> _Progress:
        if self._progress is not None:
            self._progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.stop()

    def describe(self, text: str) -> None:
        if self._progress is not None:
            self._progress.update(self._task, description=text)

    def advance(self, steps: int = 1) -> None:
        if self._progress is not None:
            self._progress.advance(self._task, steps)


# -- the run -----------------------------------------------------------------------------------


class _Run:
    """State of one benchmark run (records, notes, sink)."""

    def __init__(
        self, config: BenchConfig, on_record: Callable[[Record], None] | None, progress: bool
    ) -> None:
        self.config = config
        self.on_record = on_record
        self.result = BenchResult()
        self.env = environment()
        self.run_id = uuid.uuid4().hex[:12]
        self.show_progress = progress
        self.ui = _Progress(False, 0)
        # The reference peer's query per ray type, re-timed alongside each of ours.
        self.reference_queries: dict[str, Callable[[], Any]] = {}

    def emit(self, record: Record) -> Record:
        full: Record = {
            "record": record.pop("record"),
            "run_id": self.run_id,
            "timestamp": _now(),
            **record,
            "threading_layer": threading_layer(),
            **self.env,
        }
        self.result.records.append(full)
        if self.on_record is not None:
            self.on_record(full)
        return full

    def note(self, text: str) -> None:
        if text not in self.result.notes:
            self.result.notes.append(text)

    # -- compile phase ---------------------------------------------------------------------

    def compile_all(self) -> None:
        """Run every builder and traversal variant once on a small mesh; record the first call.

        Each traversal is called with a batch below :data:`rayaccel.trace.run.PARALLEL_MIN_RAYS`
        (the serial kernels the oracle check runs) and, when the measured sets reach it,
        with one above (the parallel kernels the timings run), each query with and
        without stats: every kernel a measurement calls is compiled or loaded here,
        before any timing, with the progress line naming it.
        """
        mesh = procedural.triangle_soup(self.config.warmup_triangles, seed=1)
        rng = np.random.Generator(np.random.PCG64(2))
        sizes = [min(WARMUP_RAYS, PARALLEL_MIN_RAYS - 1)]
        if self.config.width * self.config.height >= PARALLEL_MIN_RAYS:
            sizes.append(PARALLEL_MIN_RAYS)
        batches = []
        for n_rays in sizes:
            origin = rng.uniform(-0.5, 1.5, (n_rays, 3))
            target = rng.uniform(0.0, 1.0, (n_rays, 3))
            batches.append(RayBatch(origin, target - origin, 0.0, np.inf))
        builders = self.config.builder_keys()
        n_kernels = sum(1 + 4 * len(batches) * len(self.config.traversal_keys(b)) for b in builders)
        done = 0
        for builder in builders:
            self.ui.describe(f"compiling {builder} ({done + 1}/{n_kernels})")
            accel, first_ms, status = self._first_call(
                functools.partial(api.build, mesh, builder, **self.config.builder_options)
            )
            done += 1
            self.emit_compile(builder, None, "build", first_ms, status, mesh)
            for traversal in self.config.traversal_keys(builder):
                for rays in batches:
                    mode = "parallel" if rays.n_rays >= PARALLEL_MIN_RAYS else "serial"
                    for query in ("closest", "any"):
                        for stats in (False, True):
                            variant = f"{query}{'+stats' if stats else ''}"
                            self.ui.describe(
                                f"compiling {traversal} {variant} {mode} ({done + 1}/{n_kernels})"
                            )
                            _, first_ms, status = self._first_call(
                                functools.partial(
                                    accel.trace, rays, query=query, traversal=traversal, stats=stats
                                )
                            )
                            done += 1
                            self.emit_compile(
                                builder, traversal, f"{variant} {mode}", first_ms, status, mesh
                            )

    def _first_call(self, fn: Callable[[], Any]) -> tuple[Any, float, str]:
        before = _cache_snapshot()
        start = time.perf_counter()
        value = fn()
        first = time.perf_counter() - start
        after = _cache_snapshot()
        compiled = any(before.get(path) != mtime for path, mtime in after.items())
        # The steady-state cost of the same call, to isolate compile/cache-load time
        start = time.perf_counter()
        fn()
        steady = time.perf_counter() - start
        return value, max(first - steady, 0.0) * 1e3, "jit" if compiled else "cache"

    def emit_compile(
        self,
        builder: str,
        traversal: str | None,
        variant: str,
        ms: float,
        status: str,
        mesh: TriangleMesh,
    ) -> None:
        self.emit({
            "record": "compile",
            "system": builder if traversal is None else f"{builder}+{traversal}",
            "builder": builder,
            "traversal": traversal,
            "variant": variant,
            "compile_ms": round(ms, 3),
            "compile_kind": status,
            "warmup_triangles": mesh.n_triangles,
        })  # fmt: skip

    # -- per scene -------------------------------------------------------------------------

    def run(self) -> BenchResult:
        config = self.config
        peer_objects = [peers_mod.get_peer(name) for name in config.peers]
        usable: list[peers_mod.Peer] = []
        for peer in peer_objects:
            reason = peer.unavailable_reason()
            if reason is None:
                usable.append(peer)
            else:
                self.note(f"{peer.name} not measured: {reason}")
        builders = config.builder_keys()
        n_systems = len(usable) + sum(len(config.traversal_keys(b)) for b in builders)
        total = len(config.scenes) * len(config.thread_counts()) * n_systems * len(config.ray_kinds)
        self.ui = _Progress(self.show_progress, total)
        initial_threads = numba.get_num_threads()
        try:
            with self.ui:
                self.ui.describe("compiling kernels")
                self.compile_all()
                for spec in config.scenes:
                    self.scene(spec, usable)
        finally:
            numba.set_num_threads(initial_threads)
            # The timed queries close over the peers: drop them, so the peers' native
            # scenes (Embree, Open3D, Mitsuba) are freed here by reference counting, not
            # later by the cyclic garbage collector in whatever the process runs next.
            self.reference_queries.clear()
        return self.result

    def scene(self, spec: str, peers: list[peers_mod.Peer]) -> None:
        config = self.config
        label = scene_label(spec)
        scene_spec, view = split_view(spec)
        self.ui.describe(f"{label}: loading")
        mesh = catalog.get(scene_spec)
        self.ui.describe(f"{label}: generating rays")
        kinds = parse_kinds(list(config.ray_kinds))
        raysets = standard_raysets(
            mesh, scene_spec, kinds=kinds, width=config.width, height=config.height,
            seed=config.seed, view=view,
        )  # fmt: skip
        self.ui.describe(f"{label}: oracle")
        references = {
            kind: reference_hits(mesh, rs, config.validate, config.seed, self.result.notes)
            for kind, rs in raysets.items()
        }
        for threads in config.thread_counts():
            numba.set_num_threads(threads)
            base = {"scene": label, "n_tris": mesh.n_triangles, "threads": threads}
            cells = _Cells(mesh, raysets, references, base)
            for peer in peers:
                if self.skip_done(label, peer.name, threads, raysets, cells.rates):
                    self.ui.advance(len(raysets))
                    continue
                self.peer(peer, cells)
            for builder in config.builder_keys():
                systems = [f"{builder}+{t}" for t in config.traversal_keys(builder)]
                if all(self.skip_done(label, s, threads, raysets, {}) for s in systems):
                    self.ui.advance(len(systems) * len(raysets))
                    continue
                self.ours(builder, cells)

    def is_done(self, scene: str, system: str, threads: int, kind: str) -> bool:
        """Whether an earlier run finished this cell (:attr:`BenchConfig.done`)."""
        return (scene, system, threads, kind) in self.config.done

    def skip_done(
        self, scene: str, system: str, threads: int, raysets: Mapping[str, RaySet],
        rates: dict[str, float],
    ) -> bool:  # fmt: skip
        """Return whether every ray set of a system is done; take the reference's rates.

        The reference peer's earlier rates fill ``rates``, so the cells still to measure
        get their ratios.
        """
        done = self.config.done
        for kind in raysets:
            earlier = done.get((scene, system, threads, kind)) or {}
            if system == peers_mod.REFERENCE_PEER and earlier.get("mrays_median"):
                rates[kind] = float(earlier["mrays_median"])
        return all(self.is_done(scene, system, threads, kind) for kind in raysets)

    def pending(self, cells: _Cells, system: str) -> Iterator[tuple[str, RaySet]]:
        """Yield the ray sets of ``system`` an earlier run did not finish, as ``(kind, rayset)``.

        Each cell counts as one progress step: a finished one at once, a yielded one
        when the caller's loop moves on from it.
        """
        scene = cells.base["scene"]
        for kind, rayset in cells.raysets.items():
            if not self.is_done(scene, system, cells.base["threads"], kind):
                self.ui.describe(f"{scene}: {system} {kind}")
                yield kind, rayset
            self.ui.advance()

    def _validation(self, ref: _Reference | None, mismatches: int | None) -> Record | None:
        if ref is None or mismatches is None:
            return None
        return {"reference": ref.source, "checked": len(ref.index), "mismatches": mismatches}

    def _ratio(self, rates: Mapping[str, float], kind: str, mrays: float) -> float | None:
        reference = rates.get(kind)
        return round(mrays / reference, 4) if reference else None

    def peer(self, peer: peers_mod.Peer, cells: _Cells) -> None:
        config, mesh, base = self.config, cells.mesh, cells.base
        peer.set_threads(base["threads"])
        note = peer.threads_note.format(n=base["threads"])
        if note:
            self.note(note)
        skip = peer.skip_reason(mesh)
        if skip is not None:
            self.note(f"{base['scene']}: {skip}")
            self.ui.advance(len(cells.raysets))
            return
        self.ui.describe(f"{base['scene']}: {peer.name} build")
        peer.build(mesh)  # untimed: first build may load libraries
        build_ms = float(np.median([peer.build(mesh) for _ in range(config.build_repeats)]))
        system = {"system": peer.name, "kind": "peer", "peer": peer.name, "builder": None,
                  "traversal": None, "peer_label": peer.label}  # fmt: skip
        for kind, rayset in self.pending(cells, peer.name):
            rays = peer.limit(rayset.rays)
            prepared = peer.prepare(rays)
            if rayset.query == "any":

                def query(p: Any = prepared) -> Any:
                    return peer.occluded(p)
            else:

                def query(p: Any = prepared) -> Any:
                    return peer.intersect(p)

            ref = cells.references.get(kind)
            mismatches = None
            if ref is not None:
                sub = peer.prepare(ref.rays)
                if rayset.query == "any":
                    mismatches = count_mismatches(
                        ref, "any", None, np.where(peer.occluded(sub), 0, -1), RTOL_PEER
                    )
                else:
                    t, prim = peer.intersect(sub)
                    mismatches = count_mismatches(ref, "closest", t, prim, RTOL_PEER)
            record = {**base, **system, "ray_type": kind, "query": rayset.query,
                      "n_rays": rays.n_rays, "build_ms": round(build_ms, 3),
                      "validation": self._validation(ref, mismatches)}  # fmt: skip
            if rays.n_rays < rayset.n_rays:
                record["note"] = f"first {rays.n_rays} of {rayset.n_rays} rays"
            allowed = PEER_MISMATCH_FRACTION * (len(ref.index) if ref is not None else 0)
            if ref is not None and mismatches is not None and mismatches > allowed:
                self.emit({"record": "invalid", **record})
                self.note(f"{base['scene']}: {peer.name} {kind}: {mismatches} rays differ "
                          f"from the {ref.source} oracle; not timed")  # fmt: skip
                continue
            repeats = min(config.repeats, peer.max_repeats or config.repeats)
            seconds, _ = _timed(query, repeats)
            timing = _timing_fields(rays.n_rays, seconds)
            if peer.name == peers_mod.REFERENCE_PEER:
                cells.rates[kind] = timing["mrays_median"]
                self.reference_queries[kind] = query
            record.update(timing)
            record["ratio_vs_open3d"] = self._ratio(cells.rates, kind, timing["mrays_median"])
            self.emit({"record": "trace", **record})

    def ours(self, builder: str, cells: _Cells) -> None:
        config, mesh, base = self.config, cells.mesh, cells.base
        self.ui.describe(f"{base['scene']}: {builder} build")
        options = dict(config.builder_options)
        api.build(mesh, builder, **options)  # untimed: compiles parallel builder paths
        build_times = []
        accel = None
        for _ in range(config.build_repeats):
            accel = api.build(mesh, builder, **options)
            build_times.append(accel.build_ms)
        assert accel is not None
        info = accel.info()
        structure = {key: info.get(key) for key in ("n_nodes", "n_leaves", "depth", "sah", "bytes")}
        build_ms = round(float(np.median(build_times)), 3)
        for traversal in config.traversal_keys(builder):
            name = f"{builder}+{traversal}"
            system = {"system": name, "kind": "rayaccel", "builder": builder,
                      "traversal": traversal, "peer": None, "build_ms": build_ms,
                      **structure}  # fmt: skip
            for kind, rayset in self.pending(cells, name):
                self.measure_ours(accel, traversal, kind, rayset, cells.references.get(kind),
                                  {**base, **system}, cells.rates)  # fmt: skip

    def measure_ours(
        self,
        accel: api.Accel,
        traversal: str,
        kind: str,
        rayset: RaySet,
        ref: _Reference | None,
        base: Record,
        rates: Mapping[str, float],
    ) -> None:
        config = self.config
        rays, query = rayset.rays, rayset.query
        record = {**base, "ray_type": kind, "query": query, "n_rays": rays.n_rays}
        mismatches = None
        if ref is not None:
            hits = accel.trace(ref.rays, query=query, traversal=traversal)
            mismatches = count_mismatches(ref, query, hits.t, hits.prim, RTOL_OURS)
        record["validation"] = self._validation(ref, mismatches)
        if mismatches:
            self.emit({"record": "invalid", **record})
            self.note(f"{base['scene']}: {base['system']} {kind}: {mismatches} of "
                      f"{len(ref.index)} rays differ from the {ref.source} oracle; not timed")  # type: ignore[union-attr]  # fmt: skip
            return
        # Plain, instrumented and (when present) the reference peer's pass, round-robin:
        # a noisy phase of the shared machine then slows all three, not one of them.
        passes = [
            lambda: accel.trace(rays, query=query, traversal=traversal),
            lambda: accel.trace(rays, query=query, traversal=traversal, stats=True),
        ]
        reference = self.reference_queries.get(kind) if kind in rates else None
        if reference is not None:
            passes.append(reference)
        pools = [OWN_POOL, OWN_POOL, "reference"][: len(passes)]
        timings, results = timed_round_robin(
            passes, config.repeats, pools, config.settle_ms / 1e3
        )
        seconds, stats_seconds, hits = timings[0], timings[1], results[1]
        timing = _timing_fields(rays.n_rays, seconds)
        record.update(timing)
        if reference is not None:
            # The ratio to the reference passes timed in the same rounds.
            record["reference_ms_median"] = round(float(np.median(timings[2])) * 1e3, 4)
            record["ratio_vs_open3d"] = round(float(np.median(timings[2]) / np.median(seconds)), 4)
        else:
            record["ratio_vs_open3d"] = self._ratio(rates, kind, timing["mrays_median"])
        record["stats_ms_median"] = round(float(np.median(stats_seconds)) * 1e3, 4)
        record["stats_overhead"] = round(
            float(np.median(stats_seconds)) / float(np.median(seconds)) - 1.0, 4
        )
        record.update(counter_summary(hits.stats))
        self.emit({"record": "trace", **record})


def _timing_fields(n_rays: int, seconds: np.ndarray) -> Record:
    median = float(np.median(seconds))
    best = float(np.min(seconds))
    return {
        "repeats": len(seconds),
        "ms_median": round(median * 1e3, 4),
        "ms_best": round(best * 1e3, 4),
        "mrays_median": round(n_rays / median / 1e6, 4) if median > 0 else None,
        "mrays_best": round(n_rays / best / 1e6, 4) if best > 0 else None,
    }


def counter_summary(stats: Mapping[str, np.ndarray] | None) -> Record:
    """Return mean nodes and primitives per ray, nodes p95, and every counter's mean."""
    if not stats:
        return {}
    means = {name: round(float(np.mean(stats[name])), 4) for name in COUNTER_NAMES if name in stats}
    nodes = np.asarray(stats.get("nodes", np.zeros(0)))
    return {
        "nodes_per_ray": means.get("nodes"),
        "prims_per_ray": means.get("prim_tests"),
        "nodes_p95": float(np.percentile(nodes, 95)) if nodes.size else None,
        "counters_mean": means,
    }


def run_bench(
    config: BenchConfig,
    *,
    on_record: Callable[[Record], None] | None = None,
    progress: bool = False,
) -> BenchResult:
    """Run the benchmark described by ``config``.

    Parameters
    ----------
    config : BenchConfig
        Scenes, ray sets, builders, traversals, peers, thread counts and repeats.
    on_record : callable, optional
        Called with every record as soon as it is finished (e.g.
        :meth:`rayaccel.bench.report.JsonlWriter.append`).
    progress : bool
        Show a rich progress bar on stderr.

    Returns
    -------
    BenchResult
        The records and the notes. An interrupt (``KeyboardInterrupt``) propagates;
        everything already passed to ``on_record`` is complete.

    Raises
    ------
    InvalidInputError, UnknownVariantError, SceneFileError
        Bad configuration or scene.
    """
    return _Run(config, on_record, progress).run()


def iter_trace_records(records: Sequence[Record]) -> Iterator[Record]:
    """Yield the ``trace`` and ``invalid`` records (the ones tables show)."""
    for record in records:
        if record.get("record") in ("trace", "invalid"):
            yield record
