"""Time a new process's ``import``, ``build()`` and first ``intersect()``, cold and warm.

Cold: an empty numba cache folder, so every kernel the call needs is compiled. Warm: the
same folder again, so the kernels load from the cache. Each phase runs in a fresh
Python process, as a user's script would::

    python benchmarks/first_call.py --scene teapot --accel bvh2.binned_sah --runs 3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

CHILD = """
import json, time
t0 = time.perf_counter()
import numpy as np
import rayaccel as ra
t1 = time.perf_counter()
mesh = ra.scenes.get({scene!r})
accel = ra.build(mesh, {accel!r})
t2 = time.perf_counter()
lo, hi = mesh.bounds()
rng = np.random.default_rng(0)
origins = rng.uniform(lo, hi, ({n_rays}, 3))
hits = accel.intersect(origins, rng.normal(size=({n_rays}, 3)))
t3 = time.perf_counter()
print(json.dumps({{"import_s": t1 - t0, "build_s": t2 - t1, "intersect_s": t3 - t2}}))
"""


def run_child(code: str, cache: str) -> dict[str, float]:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="teapot")
    parser.add_argument("--accel", default="bvh2.binned_sah")
    parser.add_argument("--rays", type=int, default=10_000,
                        help="rays of the first intersect (>= 4096 uses the parallel kernel)")
    parser.add_argument("--runs", type=int, default=3, help="cold/warm pairs")
    args = parser.parse_args()
    code = CHILD.format(scene=args.scene, accel=args.accel, n_rays=args.rays)
    print(f"{args.scene}, {args.accel}, first intersect of {args.rays} rays; seconds")
    print(f"{'run':<6}{'cache':<7}{'import':>8}{'build':>8}{'intersect':>11}{'total':>8}")
    for run in range(args.runs):
        with tempfile.TemporaryDirectory() as cache:
            for label in ("cold", "warm"):
                t = run_child(code, cache)
                total = sum(t.values())
                print(f"{run:<6}{label:<7}{t['import_s']:>8.2f}{t['build_s']:>8.2f}"
                      f"{t['intersect_s']:>11.2f}{total:>8.2f}", flush=True)


if __name__ == "__main__":
    main()
