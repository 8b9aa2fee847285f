"""Ahead-of-time compilation: the job list, worker processes, and a cache later processes load."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from rayaccel import precompile, registry
from rayaccel.errors import UnknownVariantError


def test_jobs_cover_every_kernel_variant():
    todo = precompile.jobs()
    kernels = {(j.traversal, j.query, j.stats, j.parallel) for j in todo if j.traversal}
    for structure in registry.structures():
        for traversal in registry.keys("traversal", structure):
            for query in ("closest", "any"):
                for stats in (False, True):
                    for parallel in (False, True):
                        assert (traversal, query, stats, parallel) in kernels
    assert {j.build_key for j in todo if j.traversal is None} == set(registry.build_keys())
    # The two-level grid has its own layout: its serial kernels are compiled too.
    serial = {(j.build_key, j.traversal, j.query, j.stats) for j in todo if not j.parallel}
    for traversal in registry.keys("traversal", "grid"):
        for query in ("closest", "any"):
            for stats in (False, True):
                assert ("grid.two_level", traversal, query, stats) in serial
    assert not any(j.build_key == "bvh2.sbvh" for j in todo if j.traversal)
    # The default trees' builds come first, then the serial jobs (which compile the
    # chunk workers), then the parallel ones.
    defaults = {registry.default_builder(structure) for structure in registry.structures()}
    first = todo[: len(defaults)]
    assert {j.build_key for j in first} == defaults
    assert not any(j.traversal for j in first)
    first_parallel = next(i for i, j in enumerate(todo) if j.parallel)
    assert all(j.traversal and not j.parallel for j in todo[len(defaults) : first_parallel])
    # Traversals of one structure that share a kernel are not next to each other.
    plain = [j.traversal for j in todo[:first_parallel]
             if j.traversal and j.query == "closest" and not j.stats and j.build_key in defaults]
    assert abs(plain.index("grid.dda") - plain.index("grid.skip")) > 1
    assert abs(plain.index("kdtree.restart") - plain.index("kdtree.backtrack")) > 1


def test_jobs_filters():
    grid = precompile.jobs(["grid"], parallel=False)
    assert grid
    assert all(registry.get_chain(j.build_key)[0].structure == "grid" for j in grid)
    assert not any(j.parallel for j in grid)
    only_closest = precompile.jobs(["kdtree"], variant_filter=lambda t, q, s: q == "closest")
    assert {j.query for j in only_closest if j.parallel} == {"closest"}
    with pytest.raises(UnknownVariantError, match="octree"):
        precompile.jobs(["octree"])


def test_common_parallel_keeps_what_plain_queries_reach():
    todo = precompile.jobs(variant_filter=precompile.common_parallel)
    parallel = {(j.traversal, j.query, j.stats) for j in todo if j.parallel}
    for query in ("closest", "any"):
        for stats in (False, True):
            for traversal in ("bvh2.stack", "bvh2.wide", "kdtree.stack", "grid.dda"):
                assert (traversal, query, stats) in parallel
            plain = query == "closest" and not stats
            assert (("kdtree.ropes", query, stats) in parallel) == plain
    assert len(parallel) < len({(j.traversal, j.query, j.stats) for j in precompile.jobs()
                                if j.parallel})  # fmt: skip
    serial = precompile.jobs(parallel=False)
    assert [j for j in todo if not j.parallel] == serial


LOAD_SCRIPT = textwrap.dedent(
    """
    import numba.core.event as events
    from rayaccel import precompile

    compiled = []

    class Listener(events.Listener):
        def on_start(self, event):
            compiled.append(event.data["dispatcher"].py_func.__qualname__)

        def on_end(self, event):
            pass

    events.register("numba:compile", Listener())
    for job in precompile.jobs(["grid"], variant_filter=lambda t, q, s: not s)[:{n}]:
        precompile.run_job(job)
    print("compiled:", compiled)
    """
)


def test_a_process_after_precompile_compiles_nothing():
    """Kernels compiled by two worker processes load, uncompiled, in a third process."""
    todo = precompile.jobs(["grid"], variant_filter=lambda t, q, s: not s)[:6]
    done = []
    precompile.precompile(todo, 2, on_done=lambda job, s, k: done.append(job))
    assert sorted(done, key=repr) == sorted(todo, key=repr)
    proc = subprocess.run([sys.executable, "-c", LOAD_SCRIPT.replace("{n}", "6")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "compiled: []" in proc.stdout, proc.stdout
