"""The sweep's own cost and its scaling on Dask (issue 18's two performance targets).

1. Overhead: a sweep in one process, its wall-clock time against the sum of its
   cells' own times and the ray sets' (``SweepSummary.overhead``).
2. Scaling: the counter passes alone (``passes = ["counters"]``) with ``--workers 1``
   and ``--workers 2``, each from an empty results file, after one untimed run that
   fills numba's cache for the worker processes. The ray sets are recorded once
   beforehand and shared, so both runs do the same work. What a second worker cannot
   shorten (the cluster's start, imports, kernel loads, one-thread builds) weighs less
   as the ray sets grow: issue 18's 0.6 is read at 640×480 (docs/performance.md).

    RAYACCEL_SCENE_PATH=../shared/scenes python benchmarks/bench_sweep.py \
        --scenes staircase living_room --size 640 480 --skip-whole
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from rayaccel.study.config import parse_config
from rayaccel.study.sweep import sweep

CONFIG = """\
scenes = {scenes}
builders = ["bvh2.binned_sah", "kdtree.sah", "grid.uniform"]
traversals = "all"
threads = [2]
repeats = 3
build_repeats = 1
validate = 50
passes = {passes}

[rays]
kinds = ["primary", "diffuse", "shadow", "path"]
width = {width}
height = {height}

[rays.path]
spp = 1
max_depth = 2
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "teapot"])
    parser.add_argument("--size", nargs=2, type=int, default=[128, 96])
    parser.add_argument("--skip-whole", action="store_true", help="only the Dask scaling part")
    args = parser.parse_args(argv)
    scenes = "[" + ", ".join(f'"{s}"' for s in args.scenes) + "]"

    def config(passes: str):
        return parse_config(CONFIG.format(scenes=scenes, passes=passes, width=args.size[0],
                                          height=args.size[1]))  # fmt: skip

    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        rays = root / "rays"
        if not args.skip_whole:
            full = sweep(config('["build", "counters", "timing"]'), root / "all.jsonl",
                         rays_folder=rays)  # fmt: skip
            print(f"whole sweep in one process: {full.ran} cells, wall {full.wall_seconds:.1f} s, "
                  f"cells {full.cell_seconds:.1f} s, ray sets {full.rays_seconds:.1f} s, "
                  f"overhead {100 * full.overhead:.2f}%")  # fmt: skip
        counters = config('["counters"]')
        sweep(counters, root / "warm.jsonl", workers=1, rays_folder=rays)
        times = {}
        for workers in (1, 2, 1, 2):
            start = time.perf_counter()
            summary = sweep(counters, root / f"w{workers}-{time.time_ns()}.jsonl",
                            workers=workers, rays_folder=rays)  # fmt: skip
            elapsed = time.perf_counter() - start
            times.setdefault(workers, []).append(elapsed)
            print(f"counters, --workers {workers}: {summary.ran} cells in {elapsed:.1f} s "
                  f"(cells {summary.cell_seconds:.1f} s, ray sets {summary.rays_seconds:.1f} s)")
        ratio = min(times[2]) / min(times[1])
        print(f"--workers 2 / --workers 1 (best of two each): {ratio:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
