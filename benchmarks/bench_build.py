"""Build time of rayaccel's builders against Embree's, interleaved on the same mesh.

The machine is shared and noisy, so each round builds every rayaccel key and every
peer once, in turn, and the report is the median over rounds (after one warm-up
round that also compiles) with each build's ratio to Open3D's Embree build in the
same run. Open3D builds lazily; its time covers ``add_triangles`` and the committing
first cast (:mod:`rayaccel.bench.peers`). With ``--ready`` a rayaccel build's time also
covers the layouts its default queries derive on first use (``Accel.query_traversal`` of
the scene's standard primary, diffuse and shadow rays: for a BVH the pairs rows of
``bvh2.packet`` and the 8-wide rows of ``bvh2.wide``), so both sides are timed until they
can answer. One JSONL record per system, written atomically after the last round; a
Markdown table is printed.

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=../shared/scenes python benchmarks/bench_build.py \
        kitchen --keys bvh2.lbvh bvh2.binned_sah bvh2.ploc bvh2.sbvh --rounds 7
    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=../shared/scenes python benchmarks/bench_build.py \
        kitchen --ready --rounds 7
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numba

import rayaccel
from rayaccel.bench import report
from rayaccel.bench.peers import get_peer
from rayaccel.bench.raysets import standard_raysets
from rayaccel.rays.batch import RayBatch


def default_queries(mesh: rayaccel.TriangleMesh, scene: str, key: str) -> list[tuple[str, str]]:
    """Return the ``(traversal, query)`` pairs a ``key`` accel's default queries use.

    Chosen by :meth:`rayaccel.Accel.query_traversal` on the scene's standard ray sets
    (128×128 primary rays): closest hits for primary and diffuse rays, any hit for
    shadow rays.
    """
    accel = rayaccel.build(mesh, key)
    pairs = set()
    for ray_set in standard_raysets(mesh, scene, width=128, height=128).values():
        if ray_set.rays.n_rays:
            pairs.add((accel.query_traversal(ray_set.rays), ray_set.query))
    return sorted(pairs)


def ready_ms(mesh: rayaccel.TriangleMesh, key: str, queries: list[tuple[str, str]],
             probe: RayBatch) -> float:  # fmt: skip
    """Build ``key`` and answer ``probe`` with each of ``queries``; return the milliseconds.

    The default's own choice (``Accel.query_traversal``, which measures the scene once) is
    timed too.
    """
    start = time.perf_counter()
    accel = rayaccel.build(mesh, key)
    accel.query_traversal(probe)
    for traversal, query in queries:
        accel.trace(probe, traversal=traversal, query=query)
    return (time.perf_counter() - start) * 1e3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--keys", nargs="+", default=["bvh2.binned_sah"])
    parser.add_argument("--peers", nargs="*", default=["open3d", "embree"])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--json", default=None, help="JSONL output (default results/...)")
    parser.add_argument(
        "--ready",
        action="store_true",
        help="time rayaccel until its default queries can answer (their layouts)",
    )
    args = parser.parse_args(argv)
    mesh = rayaccel.scenes.get(args.scene)
    queries = (
        {key: default_queries(mesh, args.scene, key) for key in args.keys} if args.ready else {}
    )
    probe = RayBatch(mesh.vertices[:16] * 0.5, [0.0, 0.0, 1.0])
    for key, pairs in queries.items():
        print(
            f"{key}: ready when {', '.join(f'{t} ({q})' for t, q in pairs)} can answer",
            file=sys.stderr,
        )
    threads = numba.get_num_threads()
    peers = {}
    for name in args.peers:
        peer = get_peer(name)
        if peer.available():
            peer.set_threads(threads)
            peers[name] = peer
        else:
            print(f"{name}: {peer.unavailable_reason()}", file=sys.stderr)
    times: dict[str, list[float]] = {key: [] for key in [*args.keys, *peers]}
    for round_index in range(args.rounds + 1):
        for key in args.keys:
            if args.ready:
                times[key].append(ready_ms(mesh, key, queries[key], probe))
            else:
                times[key].append(rayaccel.build(mesh, key).build_ms)
        for name, peer in peers.items():
            times[name].append(peer.build(mesh))
        print(f"round {round_index}: " + ", ".join(f"{k} {v[-1]:.0f}" for k, v in times.items()),
              file=sys.stderr, flush=True)  # fmt: skip
    median = {key: statistics.median(values[1:]) for key, values in times.items()}
    reference = median.get("open3d")
    records = []
    for key, ms in median.items():
        records.append({
            "scene": args.scene, "system": key, "n_tris": mesh.n_triangles, "threads": threads,
            "rounds": args.rounds, "build_ms": round(ms, 1),
            "ready": bool(args.ready and key in queries),
            "best_ms": round(min(times[key][1:]), 1),
            "mtris_per_s": round(mesh.n_triangles / ms / 1e3, 3),
            "x_open3d_speed": round(reference / ms, 3) if reference else None,
        })  # fmt: skip
    stamp = report.utc_stamp()
    output = Path(args.json or Path(__file__).parent / "results" / f"bench_build-{stamp}.jsonl")
    writer = report.JsonlWriter(output)
    for record in records:
        writer.append(record)
    columns = ["system", "build_ms", "best_ms", "mtris_per_s", "x_open3d_speed"]
    print(f"**{args.scene}** ({mesh.n_triangles:,} triangles, {threads} threads, "
          f"median of {args.rounds} rounds)\n")  # fmt: skip
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for record in records:
        print("| " + " | ".join(str(record[c]) for c in columns) + " |")
    print(f"\n{len(records)} records in {output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
