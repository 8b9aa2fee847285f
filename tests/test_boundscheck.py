"""Kernels run with numba's bounds checks on (issue 20: bounds checking).

A subprocess runs :mod:`rayaccel.precompile` jobs (each builds its structure on a small
soup and validates it, or traces rays through one traversal kernel) with
``NUMBA_BOUNDSCHECK=1`` and a cache folder of its own (bounds-checked machine code must
not mix with the plain kernels' cache): an index out of range anywhere raises
``IndexError`` there instead of reading or writing past an array. By default every
structure's default builder and one traversal per structure (``bvh2.stack``,
``kdtree.ropes``, ``grid.dda``), with statistics (the variant holding the most code); with
``--full`` every build key and every serial traversal kernel (closest and any hit, with and
without statistics), on every structure class, then :func:`kernel_tour.tour` (build steps,
parallel kernels, all hits, geometry queries, refit, float64, bounce rays, path tracer,
heatmap); the run fails if any kernel the package declares did not run
(:func:`kernel_tour.kernels_not_run`).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import sys

    from rayaccel import precompile, registry

    full = sys.argv[1] == "full"
    sys.path.insert(0, sys.argv[2])
    if full:
        jobs = precompile.jobs(parallel=False)
    else:
        picks = {"bvh2": "bvh2.stack", "kdtree": "kdtree.ropes", "grid": "grid.dda"}
        jobs = []
        for structure, traversal in picks.items():
            tree = registry.default_builder(structure)
            jobs.append(precompile.Job(tree))
            jobs.append(precompile.Job(tree, traversal, "closest", True, parallel=False))
    for job in jobs:
        precompile.run_job(job)
        print("ran", job.name, flush=True)
    if full:
        import kernel_tour

        kernel_tour.tour()
        missing = kernel_tour.kernels_not_run()
        print("kernels not run:", len(missing), *missing)
    print("jobs", len(jobs))
    """
)


def test_kernels_run_with_bounds_checks(tmp_path, request):
    full = request.config.getoption("--full")
    env = {**os.environ, "NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    tests = os.path.dirname(__file__)
    command = [sys.executable, "-c", SCRIPT, "full" if full else "subset", tests]
    run = subprocess.run(command, env=env, capture_output=True, text=True,
                         timeout=5400 if full else 1200)  # fmt: skip
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-4000:]
    ran = [line for line in run.stdout.splitlines() if line.startswith("ran ")]
    assert len(ran) == int(run.stdout.split("jobs ")[-1]) > 0
    if full:
        assert "kernels not run: 0\n" in run.stdout, run.stdout[-2000:]
