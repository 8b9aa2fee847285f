"""Do other SAH constants make ``kdtree.stack`` faster? Ratios to ``bvh2.stack`` on the same rays.

For each scene, ``kdtree.sah`` is built with each option set below (the defaults first)
and traced with ``kdtree.stack`` on the standard primary, diffuse and shadow (any-hit)
rays of several views of the scene's camera; every row prints ``bvh2.stack``'s Mrays/s
and then, per option set, ``kdtree.stack``'s speed as a ratio to it (best of
``--repeats`` passes each). The trees' nodes, references per triangle and SAH cost are
printed as they are built.

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=../shared/scenes python \
        benchmarks/bench_kd_costs.py staircase living_room

``--sets 1`` compares the default tree alone (issue 16's ``kdtree.stack`` against
``bvh2.stack`` on several views).
"""

from __future__ import annotations

import argparse
import time

import numba

import rayaccel
from rayaccel.bench.raysets import standard_raysets

#: kdtree.sah option sets compared (the first is the defaults).
OPTION_SETS = (
    {},
    {"traversal_cost": 30.0},
    {"traversal_cost": 8.0},
    {"empty_bonus": 1.0},
    {"traversal_cost": 30.0, "empty_bonus": 1.0},
)


def best_seconds(run, repeats: int) -> float:
    """The fastest of ``repeats`` calls of ``run``."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--views", nargs="+", default=["preset", "yaw40", "orbit90"])
    parser.add_argument("--size", type=int, default=384, help="image width and height")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--sets", type=int, default=len(OPTION_SETS),
                        help="compare the first N option sets (1: the defaults alone)")
    args = parser.parse_args()
    numba.set_num_threads(args.threads)
    for scene in args.scenes:
        mesh = rayaccel.scenes.get(scene)
        bvh = rayaccel.build(mesh, "bvh2.binned_sah")
        trees = []
        for options in OPTION_SETS[: args.sets]:
            start = time.perf_counter()
            kd = rayaccel.build(mesh, "kdtree.sah", **options)
            info = kd.info()
            print(f"{scene} {options or 'defaults'}: build {time.perf_counter() - start:.1f} s, "
                  f"{info['n_nodes']} nodes, {info['refs_per_prim']:.2f} refs/prim, "
                  f"depth {info['depth']}, SAH {info['sah']:.1f}", flush=True)  # fmt: skip
            trees.append(kd)
        for view in args.views:
            sets = standard_raysets(mesh, scene, width=args.size, height=args.size, accel=bvh,
                                    view=None if view == "preset" else view)  # fmt: skip
            for kind, ray_set in sets.items():
                rays = ray_set.rays
                if rays.n_rays == 0:
                    print(f"{scene}@{view} {kind}: no rays")
                    continue
                query = "any" if kind == "shadow" else "closest"

                def trace(accel, traversal, rays=rays, query=query):
                    return lambda: accel.trace(rays, traversal=traversal, query=query)

                bvh_s = best_seconds(trace(bvh, "bvh2.stack"), args.repeats)
                ratios = []
                for kd in trees:
                    trace(kd, "kdtree.stack")()  # layouts and kernels first
                    ratios.append(bvh_s / best_seconds(trace(kd, "kdtree.stack"), args.repeats))
                print(f"{scene}@{view} {kind}: bvh2.stack {rays.n_rays / bvh_s / 1e6:.2f} Mrays/s;"
                      " kdtree.stack x bvh2.stack " + " ".join(f"{r:.2f}" for r in ratios),
                      flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
