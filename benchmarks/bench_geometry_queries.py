"""Open3D's query set: rayaccel's Accel against Open3D's RaycastingScene, in one run.

For each scene, both systems answer the same queries on the same inputs:
``compute_closest_points`` (and ``compute_distance``) on random points in and around
the bounding box (10% margin), ``count_intersections`` and ``list_intersections`` on
the rays of a pinhole camera framing the scene. Each round runs every query once per
system in turn (interleaved, so the noise of a shared machine hits both alike); the
report is the median over rounds after one warm-up round (numba compilation, Open3D's
lazy build) with rayaccel's speed-up over Open3D in the same run (``ratio`` > 1:
rayaccel is faster). Answers are checked against each other before timing (same
counts; closest distances within 1e-5 of the scene size). Both use every thread numba
has (``NUMBA_NUM_THREADS``; Open3D's ``nthreads`` is set to the same).

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=../shared/scenes \\
        python benchmarks/bench_geometry_queries.py teapot stanford-bunny --rounds 5

Scenes default to the procedural teapot and sphereflake plus the bundled
``stanford-bunny`` and ``sponza_dabrovic`` when ``RAYACCEL_SCENE_PATH`` finds them.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import numba
import numpy as np

import rayaccel
from rayaccel.errors import SceneFileError
from rayaccel.rays.camera import frame_bounds

DEFAULT_SCENES = ("teapot", "sphereflake", "stanford-bunny", "sponza_dabrovic")


def _timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return (time.perf_counter() - start) * 1e3


def run_scene(name: str, args: argparse.Namespace) -> list[dict[str, object]]:
    import open3d as o3d

    try:
        mesh = rayaccel.scenes.get(name)
    except (SceneFileError, KeyError, rayaccel.InvalidInputError) as exc:
        print(f"{name}: skipped ({exc})", file=sys.stderr)
        return []
    threads = numba.get_num_threads()
    accel = rayaccel.build(mesh, args.key)
    scene = o3d.t.geometry.RaycastingScene(nthreads=threads)
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices), o3d.core.Tensor(mesh.faces.astype(np.uint32))
    )
    lo, hi = (b.astype(np.float64) for b in mesh.bounds())
    span = hi - lo
    rng = np.random.default_rng(0)
    points = rng.uniform(lo - 0.1 * span, hi + 0.1 * span, size=(args.points, 3))
    points = points.astype(np.float32)
    camera = frame_bounds(lo, hi, width=args.width, height=args.width)
    rays = camera.rays()
    o3d_points = o3d.core.Tensor(points)
    o3d_rays = o3d.core.Tensor(np.hstack([rays.origin, rays.direction]))

    # Check the answers agree before timing anything.
    ours = accel.compute_closest_points(points)
    theirs = scene.compute_closest_points(o3d_points)
    their_d = np.linalg.norm(theirs["points"].numpy() - points, axis=1)
    scale = float(np.abs(span).max())
    worst = float(np.abs(ours.distance - their_d).max())
    counts = accel.count_intersections(rays.origin, rays.direction)
    their_counts = scene.count_intersections(o3d_rays).numpy()
    count_mismatch = int((counts != their_counts).sum())
    if worst > 1e-5 * scale or count_mismatch > rays.n_rays // 10000:
        print(
            f"{name}: answers differ (closest distance {worst:.3g}, {count_mismatch} counts)",
            file=sys.stderr,
        )

    queries: dict[str, tuple[Callable[[], object], Callable[[], object]]] = {
        "closest_points": (
            lambda: accel.compute_closest_points(points),
            lambda: scene.compute_closest_points(o3d_points, nthreads=threads),
        ),
        "distance": (
            lambda: accel.compute_distance(points),
            lambda: scene.compute_distance(o3d_points, nthreads=threads),
        ),
        "count_intersections": (
            lambda: accel.count_intersections(rays.origin, rays.direction),
            lambda: scene.count_intersections(o3d_rays, nthreads=threads),
        ),
        "list_intersections": (
            lambda: accel.list_intersections(rays.origin, rays.direction),
            lambda: scene.list_intersections(o3d_rays, nthreads=threads),
        ),
    }
    times: dict[tuple[str, str], list[float]] = {}
    for round_index in range(args.rounds + 1):
        for query, (mine, peer) in queries.items():
            times.setdefault((query, "rayaccel"), []).append(_timed(mine))
            times.setdefault((query, "open3d"), []).append(_timed(peer))
        if round_index == 0:
            times = {k: [] for k in times}  # warm-up round: compile and lazy builds
    records = []
    for query in queries:
        ours_ms = statistics.median(times[(query, "rayaccel")])
        theirs_ms = statistics.median(times[(query, "open3d")])
        n = args.points if query in ("closest_points", "distance") else rays.n_rays
        records.append({
            "scene": name, "n_tris": mesh.n_triangles, "query": query, "n": n,
            "threads": threads, "key": args.key, "rayaccel_ms": round(ours_ms, 2),
            "open3d_ms": round(theirs_ms, 2), "ratio": round(theirs_ms / ours_ms, 2),
            "closest_max_diff": worst, "count_mismatches": count_mismatch,
        })  # fmt: skip
    return records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="*", default=list(DEFAULT_SCENES))
    parser.add_argument("--key", default="bvh2.binned_sah", help="rayaccel build key")
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--width", type=int, default=256, help="camera rays: width x width")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    try:
        import open3d  # noqa: F401
    except ImportError:
        print("open3d is not installed (pip install open3d)", file=sys.stderr)
        return 1
    print("| scene | tris | query | n | rayaccel ms | Open3D ms | speed-up |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for name in args.scenes:
        for r in run_scene(name, args):
            print(
                f"| {r['scene']} | {r['n_tris']} | {r['query']} | {r['n']} | "
                f"{r['rayaccel_ms']} | {r['open3d_ms']} | {r['ratio']}x |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
