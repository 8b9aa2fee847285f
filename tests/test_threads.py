"""Determinism across thread counts, concurrent Python threads, signature discipline."""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import os
import pkgutil
import subprocess
import sys
import textwrap

import numba
import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import registry
from rayaccel.rays.batch import RayBatch

BUILDERS = [pytest.param(k, id=k) for k in registry.keys("builder")]
PAIRS = reference.builder_traversal_pairs()
needs_two_threads = pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2,
                                       reason="needs at least 2 numba threads")


def _parallel_options(builder: str) -> dict:
    """Options that push a builder onto its parallel paths for a mid-size mesh."""
    fields = {f.name for f in dataclasses.fields(registry.get(builder).options)}
    return {"parallel_threshold": 256} if "parallel_threshold" in fields else {}


def _arrays(structure) -> dict[str, bytes]:
    return {f.name: getattr(structure, f.name).tobytes()
            for f in dataclasses.fields(structure) if isinstance(getattr(structure, f.name),
                                                                 np.ndarray)}


@needs_two_threads
@pytest.mark.parametrize("builder", BUILDERS)
@pytest.mark.parametrize("scene", ["sphereflake", "soup"])
def test_build_identical_for_1_and_2_threads(threads, builder, scene):
    mesh = rayaccel.scenes.get(scene)
    built = {}
    for n in (1, 2, 1):
        threads(n)
        for opts in ({}, _parallel_options(builder)):
            accel = rayaccel.build(mesh, builder, **opts)
            built.setdefault(tuple(opts), []).append(_arrays(accel.structure))
    for runs in built.values():
        assert runs[0] == runs[1] == runs[2]


@needs_two_threads
@pytest.mark.parametrize(("builder", "traversal"), PAIRS)
def test_trace_identical_for_1_and_2_threads(threads, scenes_cache, full, builder, traversal):
    accel = scenes_cache.accel(builder, "teapot")
    lo, hi = accel.mesh.bounds()
    rays = reference.concat(reference.rays_inside(lo, hi, 3000, seed=1),
                            reference.rays_outside(lo, hi, 3000, seed=2))
    results = []
    for n in (1, 2):
        threads(n)
        run = [accel.trace(rays, query=q, traversal=traversal, stats=s)
               for q, s in reference.parallel_variants(traversal, full)]
        results.append(run)
    for a, b in zip(*results, strict=True):
        reference.assert_hits_identical(a, b, "1 vs 2 threads")
        if a.stats is not None:
            for name in a.stats:
                assert a.stats[name].tobytes() == b.stats[name].tobytes(), name


CONCURRENT_SCRIPT = textwrap.dedent(
    """
    import dataclasses
    import threading
    from concurrent.futures import ThreadPoolExecutor

    import numba
    import numpy as np

    import rayaccel
    from rayaccel import registry
    from rayaccel.rays.batch import RayBatch

    mesh = rayaccel.scenes.get("sphereflake")
    lo, hi = mesh.bounds()
    rng = np.random.default_rng(0)
    batches = []
    for k in range(8):
        n = 3000 if k % 2 else 200  # both the parallel and the serial kernels
        o = lo + rng.random((n, 3)) * (hi - lo)
        d = rng.normal(size=(n, 3))
        batches.append(RayBatch(o, d))
    # The launch machinery is family-neutral: each structure's default tree, every traversal.
    for structure in registry.structures():
        builder = registry.default_builder(structure)
        accel = rayaccel.build(mesh, builder)
        for traversal in registry.keys("traversal", structure):
            expected = [accel.trace(b, traversal=traversal) for b in batches]
            blocked = [accel.occluded(b.origin, b.direction, traversal=traversal)
                       for b in batches]

            def job(i, accel=accel, traversal=traversal, expected=expected,
                    blocked=blocked):
                k = i % len(batches)
                b = batches[k]
                hits = accel.trace(b, traversal=traversal, stats=(i % 3 == 0))
                assert hits.t.tobytes() == expected[k].t.tobytes(), (builder, k)
                assert hits.prim.tobytes() == expected[k].prim.tobytes(), (builder, k)
                occ = accel.occluded(b.origin, b.direction, traversal=traversal)
                assert np.array_equal(occ, blocked[k])
                return True

            with ThreadPoolExecutor(4) as pool:
                assert all(pool.map(job, range(48)))
        # A fresh accel queried concurrently builds its derived layout under contention.
        fresh = rayaccel.build(mesh, builder)
        with ThreadPoolExecutor(4) as pool:
            outs = list(pool.map(lambda b: fresh.trace(b).prim, batches * 2))
        for k, prim in enumerate(outs):
            assert np.array_equal(prim, outs[k % len(batches)])
        # Builds from several threads at once.
        with ThreadPoolExecutor(4) as pool:
            trees = list(pool.map(lambda _: rayaccel.build(mesh, builder).structure, range(4)))
        for t in trees[1:]:
            for field in dataclasses.fields(t):
                value = getattr(t, field.name)
                if isinstance(value, np.ndarray):
                    assert np.array_equal(value, getattr(trees[0], field.name)), field.name
    # Refit (and a rebuild of another accel) while other threads query: every answer is
    # exactly the tree's before or after some refit, never a mix.
    accel = rayaccel.build(mesh, "bvh2.binned_sah")
    states = [mesh.vertices, mesh.vertices * np.float32(1.25) + np.float32(0.1)]
    probe = batches[1]
    answers = set()
    for vertices in states:
        accel.refit(vertices)
        for traversal in ("bvh2.stack", "bvh2.wide"):
            hits = accel.trace(probe, traversal=traversal)
            answers.add((hits.t.tobytes(), hits.prim.tobytes()))
    stop = threading.Event()

    def refitter():
        n = 0
        while not stop.is_set():
            accel.refit(states[n % 2], rebuild_if_worse=1e9 if n % 3 else None)
            n += 1
        return n

    def builder():
        n = 0
        while not stop.is_set():
            rayaccel.build(mesh, "bvh2.binned_sah")
            n += 1
        return n

    def query(i):
        hits = accel.trace(probe, traversal=("bvh2.stack", "bvh2.wide")[i % 2])
        return (hits.t.tobytes(), hits.prim.tobytes()) in answers

    with ThreadPoolExecutor(6) as pool:
        refits = pool.submit(refitter)
        builds = pool.submit(builder)
        results = list(pool.map(query, range(60)))
        stop.set()
        assert refits.result() >= 1 and builds.result() >= 1
    assert all(results), f"{results.count(False)} answers mixed two trees"
    print("OK", numba.threading_layer())
    """
)


@pytest.mark.parametrize("layer", ["default", "workqueue", "omp"])
def test_concurrent_python_threads_in_subprocess(tmp_path, layer):
    """One accel queried from 4 Python threads: right answers, and the process survives.

    Runs in a subprocess because numba's workqueue layer aborts the whole process when
    it is entered concurrently (the library must serialise launches on that layer).
    """
    env = dict(os.environ)
    if layer != "default":
        env["NUMBA_THREADING_LAYER"] = layer
    script = tmp_path / "query_from_threads.py"
    script.write_text(CONCURRENT_SCRIPT)
    proc = subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                          text=True, timeout=1500)
    output = proc.stdout + proc.stderr
    if layer == "omp" and "No threading layer could be loaded" in output:
        pytest.skip("the OpenMP threading layer is not available")
    assert proc.returncode == 0, f"exit {proc.returncode}:\n{output[-3000:]}"
    assert "OK" in proc.stdout
    if layer != "default":
        assert proc.stdout.strip().endswith(layer)


def _kernel_dispatchers():
    """Module-level numba dispatchers in rayaccel that are kernels (not inlined helpers)."""
    found = {}
    for info in pkgutil.walk_packages(rayaccel.__path__, "rayaccel."):
        if info.name.startswith(("rayaccel.cuda", "rayaccel.cli", "rayaccel.__main__")):
            continue
        try:
            module = importlib.import_module(info.name)
        except ImportError:
            continue
        for name, value in vars(module).items():
            if isinstance(value, numba.core.registry.CPUDispatcher):
                if value.targetoptions.get("inline", "never") == "always":
                    continue
                if getattr(value.py_func, "__module__", None) == info.name:
                    found[f"{info.name}.{name}"] = value
    return found


def _precision_of(signature) -> str:
    """``"float64"`` if a float64 array is among a kernel's arguments (or their tuples)."""
    pending = list(signature)
    while pending:
        arg = pending.pop()
        if isinstance(arg, numba.types.BaseTuple):
            pending.extend(arg.types)
        elif isinstance(arg, numba.types.Array) and arg.dtype == numba.types.float64:
            return "float64"
    return "float32"


def _too_many(signatures) -> bool:
    """More than one signature per precision (float64 meshes compile their own, by design)."""
    return len(signatures) > len({_precision_of(s) for s in signatures})


def test_signature_discipline(full):
    """Float64, int, Fortran and strided inputs are coerced: one signature per kernel.

    Per precision: float64 meshes (``precision="float64"``, ``test_float64.py``) compile
    a float64 specialisation of the kernels they run, so when both run in one session
    a kernel may hold one float32 and one float64 signature, never two of one precision.

    Inputs are coerced before any kernel, so the parallel batch size runs through each
    structure's default traversal (and every traversal with ``--full``).
    """
    from rayaccel.bvh.traverse.stack import trace_kernel
    from rayaccel.trace.run import PARALLEL_MIN_RAYS

    mesh64 = rayaccel.TriangleMesh(np.asfortranarray(reference.icosphere(2).vertices,
                                                     dtype=np.float64),
                                   reference.icosphere(2).faces.astype(np.int64))
    rng = np.random.default_rng(0)
    for builder in registry.keys("builder"):
        accel = rayaccel.build(mesh64, builder)
        accel.validate()
        accel.info()
        for n in (PARALLEL_MIN_RAYS // 2, 2 * PARALLEL_MIN_RAYS):
            o = rng.normal(size=(n, 3)) * 3
            d = -o + rng.normal(size=(n, 3))
            inputs = [(o, d, 0.0, np.inf), (np.asfortranarray(o), d.astype(np.float16), 0, 10),
                      (o[::1].tolist(), np.round(d).astype(np.int32), np.zeros(n), np.inf),
                      (np.repeat(o, 2, axis=0)[::2], d.astype(np.float32), 0.0, 1e30)]
            for origin, direction, tmin, tmax in inputs:
                for traversal in registry.keys("traversal", accel.structure_name):
                    if n >= PARALLEL_MIN_RAYS and not (
                            full or traversal == registry.default_traversal(accel.structure_name)):
                        continue
                    for query, stats in itertools.product(("closest", "any"), (False, True)):
                        accel.trace(RayBatch(origin, direction, tmin, tmax), query=query,
                                    traversal=traversal, stats=stats)
    for query, stats, parallel in itertools.product((0, 1), (False, True), (False, True)):
        kernel = trace_kernel(query, stats, parallel)
        assert len(kernel.signatures) >= 1, (query, stats, parallel)
        assert not _too_many(kernel.signatures), (query, stats, parallel, kernel.signatures)
    # Every other kernel in the package: at most one signature (after the whole session).
    kernels = _kernel_dispatchers()
    assert "rayaccel.bvh.layouts.bvh2._check_topology" in kernels
    many = {name: d.signatures for name, d in kernels.items() if _too_many(d.signatures)}
    assert not many, f"kernels compiled for several signatures: {many}"
