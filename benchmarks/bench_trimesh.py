"""rayaccel's trimesh drop-in against trimesh with Embree (embreex), on the same rays.

For every scene (the procedural teapot always, then each scene file found through
``RAYACCEL_SCENE_PATH``; absent ones are skipped), one ``trimesh.Trimesh`` gets two
intersectors: :class:`rayaccel.trimesh.RayMeshIntersector` (``bvh2.binned_sah``, numba
threads) and ``trimesh.ray.ray_pyembree.RayMeshIntersector`` (embreex: one thread, as
trimesh uses it). Both answer ``intersects_location(multiple_hits=True)`` and
``intersects_first`` on two ray sets: the scene's camera rays (its catalog preset, or
the framed bounding box; :func:`rayaccel.bench.raysets.scene_camera`) and random rays
(origins uniform in the bounding box, directions uniform on the sphere, fixed seed).

Each measurement calls both once untimed (compiles, commits Embree's scene), then runs
``--repeats`` interleaved rounds, so load drifts on a shared machine hit both alike;
the ratio is Embree's median time over the drop-in's, from the same run. Each record
also says how many hits each found and how often their first hits agree. One JSONL
record per (scene, rays, query); a Markdown table at the end.

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=$SCENES python benchmarks/bench_trimesh.py \
        --scenes teapot living_room kitchen --repeats 5
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
import numpy as np
import trimesh

import rayaccel
from rayaccel.bench import report
from rayaccel.bench.harness import environment
from rayaccel.bench.raysets import scene_camera
from rayaccel.trimesh import RayMeshIntersector

#: Scenes tried by default (file scenes only when found on the search path).
DEFAULT_SCENES = ("teapot", "stanford-bunny", "CornellBox-Original", "living_room",
                  "staircase", "salle_de_bain", "sponza_dabrovic", "kitchen")  # fmt: skip
QUERIES = ("location_all", "first")


def ray_sets(mesh: rayaccel.TriangleMesh, name: str, n_side: int, seed: int) -> dict[str, Any]:
    """Return ``{"camera": (o, d), "random": (o, d)}``, float64 ``(n_side², 3)`` arrays."""
    camera, _ = scene_camera(mesh, name, width=n_side, height=n_side)
    rays = camera.rays()
    lo, hi = (np.asarray(b, dtype=np.float64) for b in mesh.bounds())
    rng = np.random.default_rng(seed)
    n = n_side * n_side
    origins = rng.uniform(lo, hi, size=(n, 3))
    directions = rng.normal(size=(n, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return {
        "camera": (rays.origin.astype(np.float64), rays.direction.astype(np.float64)),
        "random": (origins, directions),
    }


def timed(calls: dict[str, Callable[[], Any]], repeats: int) -> dict[str, list[float]]:
    """Seconds of each call over ``repeats`` interleaved rounds (after one untimed round)."""
    for call in calls.values():
        call()
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    return times


def measure(name: str, args: argparse.Namespace, writer: report.JsonlWriter) -> list[dict]:
    mesh = rayaccel.scenes.get(name)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
    start = time.perf_counter()
    ours = RayMeshIntersector(tm)
    build_ms = (time.perf_counter() - start) * 1e3
    embree = trimesh.ray.ray_pyembree.RayMeshIntersector(tm)
    start = time.perf_counter()
    embree.intersects_first(np.zeros((1, 3)), np.ones((1, 3)))  # commits Embree's scene
    embree_build_ms = (time.perf_counter() - start) * 1e3
    records = []
    for rays, (origins, directions) in ray_sets(mesh, name, args.side, args.seed).items():
        for query in args.queries:
            method = "intersects_location" if query == "location_all" else "intersects_first"
            calls = {
                label: functools.partial(getattr(system, method), origins, directions)
                for label, system in (("rayaccel", ours), ("embree", embree))
            }
            times = timed(calls, args.repeats)
            ours_s, embree_s = (statistics.median(times[k]) for k in ("rayaccel", "embree"))
            record = {
                "scene": name, "n_tris": mesh.n_triangles, "rays": rays,
                "n_rays": len(origins), "query": query, "threads": numba.get_num_threads(),
                "repeats": args.repeats, "build_ms": round(build_ms, 1),
                "embree_build_ms": round(embree_build_ms, 1),
                "rayaccel_ms": round(ours_s * 1e3, 2), "embree_ms": round(embree_s * 1e3, 2),
                "rayaccel_best_ms": round(min(times["rayaccel"]) * 1e3, 2),
                "embree_best_ms": round(min(times["embree"]) * 1e3, 2),
                "x_embree": round(embree_s / ours_s, 2),
            }  # fmt: skip
            if query == "location_all":
                _, ray_ours, _ = ours.intersects_location(origins, directions)
                _, ray_embree, _ = embree.intersects_location(origins, directions)
                record["hits"] = len(ray_ours)
                record["embree_hits"] = len(ray_embree)
            else:
                first_ours = ours.intersects_first(origins, directions)
                first_embree = embree.intersects_first(origins, directions)
                record["hits"] = int((first_ours >= 0).sum())
                record["embree_hits"] = int((first_embree >= 0).sum())
                record["same_first"] = round(float(np.mean(first_ours == first_embree)), 4)
            record.update(environment())
            records.append(record)
            writer.append(record)
            print({k: record[k] for k in ("scene", "rays", "query", "rayaccel_ms", "embree_ms",
                                         "x_embree")}, file=sys.stderr, flush=True)  # fmt: skip
    return records


def table(records: list[dict]) -> str:
    cols = ["scene", "n_tris", "rays", "query", "rayaccel_ms", "embree_ms", "x_embree", "hits",
            "embree_hits", "same_first"]  # fmt: skip
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in records:
        out.append("| " + " | ".join(str(r.get(c, "–")) for c in cols) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES))
    parser.add_argument("--queries", nargs="+", default=list(QUERIES), choices=QUERIES)
    parser.add_argument("--side", type=int, default=256, help="rays per set: side × side")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=19)
    parser.add_argument("--json", default=None, help="JSONL output (default results/...)")
    args = parser.parse_args(argv)
    available = set(rayaccel.scenes.names())
    stamp = report.utc_stamp()
    output = Path(args.json or Path(__file__).parent / "results" / f"bench_trimesh-{stamp}.jsonl")
    writer = report.JsonlWriter(output)
    records = []
    for name in args.scenes:
        if name not in available:
            print(f"{name}: not found on RAYACCEL_SCENE_PATH, skipped", file=sys.stderr)
            continue
        records += measure(name, args, writer)
    print(f"{numba.get_num_threads()} numba threads for rayaccel; embreex traces on one "
          f"thread; median of {args.repeats} interleaved rounds\n")  # fmt: skip
    print(table(records))
    print(f"\n{len(records)} records in {output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
