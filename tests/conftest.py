"""Shared fixtures: scene search path, cached meshes, accels, ray sets and oracle hits.

Built structures and oracle results are cached for the whole session (building the
kitchen or brute-forcing its rays takes seconds), keyed by builder and scene.
File scenes live in ``<repo>/../shared/scenes``; tests that need them are marked
``scenes`` and skip when the folder (or the file) is absent.

``--full`` runs the ``slow`` tests at full size (more rays, more examples); without
it they still run, on small inputs.
"""

from __future__ import annotations

import os
from pathlib import Path

# The CUDA traversals' tests (tests/gpu) run under numba's CUDA simulator unless a GPU is
# asked for; numba reads the switch once, when numba.cuda is first imported.
if os.environ.get("RAYACCEL_CUDA_TESTS") != "gpu":
    os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, settings

REPO = Path(__file__).resolve().parents[1]
SHARED_SCENES = REPO.parent / "shared" / "scenes"
if SHARED_SCENES.is_dir() and not os.environ.get("RAYACCEL_SCENE_PATH"):
    os.environ["RAYACCEL_SCENE_PATH"] = str(SHARED_SCENES)

settings.register_profile(
    "default", deadline=None, max_examples=40, derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "full", deadline=None, max_examples=400,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.load_profile("default")

#: Procedural scenes (always available).
PROCEDURAL_SCENES = ("cornell-box", "soup", "sphereflake", "teapot", "teapot-in-stadium")
#: The shared benchmark files (skipped when absent).
FILE_SCENES = ("CornellBox-Original", "stanford-bunny", "sponza_dabrovic", "living_room",
               "staircase", "salle_de_bain", "kitchen")
#: Oracle budget per scene: rays × triangles (about 1.5 s on two cores).
ORACLE_BUDGET = 3.0e8
MAX_RAYS = 1800
MIN_RAYS = 300


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--full", action="store_true",
                     help="run slow tests at full size (more rays and examples)")


def pytest_configure(config: pytest.Config) -> None:
    if config.getoption("--full"):
        settings.load_profile("full")


#: The files that take longest (seconds of a default-tier run on 2 cores, most first). They
#: run first: ``pytest -n auto --dist loadfile`` hands whole files to the workers in
#: collection order, so a long file collected last would run alone at the end while the
#: other worker idles (longest first keeps the two workers' ends close).
LONGEST_FILES = (
    "test_boundscheck.py",  # one subprocess compiling bounds-checked kernels
    "test_float64_kd_grid.py",  # float64 grid and kd kernels compile here
    "test_conformance.py",
    "test_properties.py",
    "gpu/test_cuda_traversals.py",
    "test_threads.py",
    "test_embree_crosscheck.py",
    "test_float64.py",
    "bench/test_harness.py",
    "bvh/test_wide.py",
    "test_watertight.py",
)

assert all((Path(__file__).parent / name).is_file() for name in LONGEST_FILES), LONGEST_FILES


def _run_order(item: pytest.Item) -> int:
    """The item's place among :data:`LONGEST_FILES` (the rest after them, as collected)."""
    path = item.path.as_posix()
    for rank, name in enumerate(LONGEST_FILES):
        if path.endswith("/tests/" + name):
            return rank
    return len(LONGEST_FILES)


def pytest_collection_modifyitems(config: pytest.Config, items: list) -> None:
    """Run the longest files first; without ``--full``, deselect the ``cross`` cases.

    ``cross`` cases: see ``test_conformance.py``. The sort is stable, so tests keep their
    order within a file.
    """
    items.sort(key=_run_order)
    if config.getoption("--full"):
        return
    cross = [item for item in items if item.get_closest_marker("cross")]
    if cross:
        config.hook.pytest_deselected(items=cross)
        items[:] = [item for item in items if not item.get_closest_marker("cross")]
        config.stash[CROSS_DESELECTED] = len(cross)


CROSS_DESELECTED = pytest.StashKey[int]()


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    n = config.stash.get(CROSS_DESELECTED, 0)
    if n:
        terminalreporter.write_line(
            f"{n} builder x traversal cases beyond the core pairs deselected; "
            "run with --full for the whole cross product"
        )


@pytest.fixture(scope="session")
def full(request: pytest.FixtureRequest) -> bool:
    """Whether ``--full`` was given."""
    return bool(request.config.getoption("--full"))


def scene_params(marks_slow_files: bool = False) -> list:
    """``pytest.param`` per scene: procedural ones, then file ones marked ``scenes``."""
    params = [pytest.param(name, id=name) for name in PROCEDURAL_SCENES]
    for name in FILE_SCENES:
        marks = [pytest.mark.scenes]
        if marks_slow_files and name == "kitchen":
            marks.append(pytest.mark.slow)
        params.append(pytest.param(name, id=name, marks=marks))
    return params


def scene_file(name: str) -> Path | None:
    """Return the file of a shared scene, or None when it is not on the search path."""
    from rayaccel.scene import catalog

    return catalog.file_scenes().get(name)


class SceneCache:
    """Session-wide memo of meshes, accels, ray sets and oracle hits."""

    def __init__(self) -> None:
        self.meshes: dict[str, object] = {}
        self.accels: dict[tuple[str, str], object] = {}
        self.rays: dict[str, object] = {}
        self.oracles: dict[str, object] = {}

    def mesh(self, name: str):
        if name not in self.meshes:
            import rayaccel

            if name not in PROCEDURAL_SCENES and scene_file(name) is None:
                pytest.skip(f"scene {name!r} not found (RAYACCEL_SCENE_PATH / ../shared/scenes)")
            self.meshes[name] = rayaccel.scenes.get(name)
        return self.meshes[name]

    def accel(self, builder: str, name: str):
        key = (builder, name)
        if key not in self.accels:
            import rayaccel

            self.accels[key] = rayaccel.build(self.mesh(name), builder)
        return self.accels[key]

    def ray_set(self, name: str):
        """Camera, inside, outside, interval and diffuse rays, subsampled for big scenes."""
        if name not in self.rays:
            self.rays[name] = _make_ray_set(self, name)
        return self.rays[name]

    def oracle(self, name: str):
        """Closest-hit oracle of :meth:`ray_set`."""
        if name not in self.oracles:
            import reference

            self.oracles[name] = reference.oracle(self.mesh(name), self.ray_set(name))
        return self.oracles[name]


def _make_ray_set(cache: SceneCache, name: str):
    import reference
    from rayaccel.rays.bounce import diffuse_rays, shadow_rays
    from rayaccel.rays.camera import frame_bounds, from_preset
    from rayaccel.scene.catalog import camera_preset

    mesh = cache.mesh(name)
    lo, hi = mesh.bounds()
    n_total = int(np.clip(ORACLE_BUDGET / mesh.n_triangles, MIN_RAYS, MAX_RAYS))
    preset = camera_preset(name)
    if preset is not None:
        camera = from_preset(preset, 24, 24)
    else:
        camera = frame_bounds(lo, hi, width=24, height=24)
    primary = camera.rays()
    # Secondary rays need the primary hits: brute-force them on a subsample.
    n_seed = max(n_total // 4, 16)
    seed_rays = reference.subsample(primary, n_seed, seed=1)
    seed_hits = reference.oracle(mesh, seed_rays)
    diffuse, _ = diffuse_rays(seed_rays, seed_hits, mesh.normals(), seed=2)
    light = (lo + hi) / 2 + np.array([0, 0, 0.45]) * (hi - lo)
    shadow, _ = shadow_rays(seed_rays, seed_hits, mesh.normals(), light, seed=3)
    sets = [
        primary,
        reference.rays_inside(lo, hi, 256, seed=4),
        reference.rays_outside(lo, hi, 256, seed=5),
        reference.rays_intervals(lo, hi, 128, seed=6),
        diffuse,
        shadow,
    ]
    share = n_total / sum(s.n_rays for s in sets)
    parts = [reference.subsample(s, max(int(s.n_rays * share), 8), seed=i)
             for i, s in enumerate(sets)]
    return reference.concat(*parts)


@pytest.fixture(scope="session")
def scenes_cache() -> SceneCache:
    """The session-wide :class:`SceneCache`."""
    return SceneCache()


@pytest.fixture
def threads():
    """Set numba's thread count for a block (call the fixture); restore it afterwards."""
    before = numba.get_num_threads()
    yield numba.set_num_threads
    numba.set_num_threads(before)


class _CompileLog:
    """Seconds numba spends compiling, per kernel and per test (``RAYACCEL_COMPILE_LOG``).

    Set ``RAYACCEL_COMPILE_LOG=FILE`` to write, at the end of the session, a JSON file of
    the outermost compilations: seconds per kernel and per test. CI time is mostly
    compilation on a cold cache; this says which kernels and which tests pay for it.
    Under pytest-xdist each worker writes its own file, ``FILE.<worker>``.
    """

    def __init__(self, path: str) -> None:
        import numba.core.event as events

        self.path = path
        self.depth = 0
        self.started = 0.0
        self.test = "(collection)"
        self.kernels: dict[str, float] = {}
        self.tests: dict[str, float] = {}
        log = self

        class Listener(events.Listener):
            def on_start(self, event) -> None:
                if log.depth == 0:
                    import time

                    log.started = time.perf_counter()
                log.depth += 1

            def on_end(self, event) -> None:
                import time

                log.depth -= 1
                if log.depth == 0:
                    seconds = time.perf_counter() - log.started
                    func = event.data["dispatcher"].py_func
                    name = f"{func.__module__}.{func.__qualname__}"
                    log.kernels[name] = log.kernels.get(name, 0.0) + seconds
                    log.tests[log.test] = log.tests.get(log.test, 0.0) + seconds

        events.register("numba:compile", Listener())

    def write(self) -> None:
        import json

        def top(d: dict[str, float]) -> dict[str, float]:
            return {k: round(v, 2) for k, v in sorted(d.items(), key=lambda kv: -kv[1])}

        Path(self.path).write_text(json.dumps(
            {"total": round(sum(self.kernels.values()), 1), "kernels": top(self.kernels),
             "tests": top(self.tests)}, indent=1))


_COMPILE_LOG = (
    _CompileLog(os.environ["RAYACCEL_COMPILE_LOG"]
                + (f".{os.environ['PYTEST_XDIST_WORKER']}"
                   if os.environ.get("PYTEST_XDIST_WORKER") else ""))
    if os.environ.get("RAYACCEL_COMPILE_LOG") else None
)


def pytest_runtest_logstart(nodeid: str, location: tuple) -> None:
    if _COMPILE_LOG is not None:
        _COMPILE_LOG.test = nodeid


def pytest_sessionfinish(session: pytest.Session) -> None:
    if _COMPILE_LOG is not None:
        _COMPILE_LOG.write()
