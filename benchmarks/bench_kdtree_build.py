"""kd-tree build time against N log N: ``kdtree.sah`` on nested subsets of one scene.

The subsets are the first N/8, N/4, N/2 and all triangles of the scene in file
order (spatially coherent parts of the same model). For each size the best of
``--rounds`` builds is reported with ``time / (N log2 N)``: a flat column is the
O(N log N) of Wald & Havran 2006 (an O(N log² N) build would grow by log N). A
warm-up build compiles first. Options pass through (``--option perfect_splits=False``).

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=../shared/scenes python \
        benchmarks/bench_kdtree_build.py kitchen --rounds 2
"""

from __future__ import annotations

import argparse
import math
import time

import numba

import rayaccel


def _value(text: str) -> object:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"True": True, "False": False}.get(text, text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--key", default="kdtree.sah")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--option", action="append", default=[], metavar="K=V")
    args = parser.parse_args(argv)
    options = {k: _value(v) for k, v in (o.split("=", 1) for o in args.option)}
    mesh = rayaccel.scenes.get(args.scene)
    rayaccel.build(rayaccel.scenes.get("teapot"), args.key, **options)  # compile
    n_all = mesh.n_triangles
    print(f"{args.key} on {args.scene} ({n_all} triangles), {numba.get_num_threads()} threads")
    print("| triangles | build s | ns per N·log2 N | nodes | leaves | empty | refs/prim | depth |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for share in (8, 4, 2, 1):
        n = n_all // share
        part = rayaccel.TriangleMesh(mesh.vertices, mesh.faces[:n], name=f"{args.scene}/{share}")
        best = math.inf
        for _ in range(args.rounds):
            t0 = time.perf_counter()
            accel = rayaccel.build(part, args.key, **options)
            best = min(best, time.perf_counter() - t0)
        info = accel.info()
        per = best / (n * math.log2(n)) * 1e9
        print(
            f"| {n} | {best:.2f} | {per:.1f} | {info['n_nodes']} | {info['n_leaves']} | "
            f"{info['n_empty_leaves']} | {info['refs_per_prim']:.2f} | {info['depth']} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
