"""Thread scaling: rayaccel traversals and Embree (Open3D, embreex) on 1 and N threads.

For each scene and ray type (``rayaccel.bench.raysets.standard_raysets``) every system
is timed in interleaved rounds on the same rays: Open3D's ``RaycastingScene`` with 1
and N threads, embreex (always one thread), and each rayaccel traversal with numba
set to 1 and to N threads. Every timed pass follows an untimed pass of the same system
(warm caches; ``rayaccel.bench.harness.timed_round_robin``, as in ``bench_core``).
Reports median milliseconds, each system's
speed-up from 1 to N threads, and rayaccel's one-thread time against embreex's: the
per-thread gap and the scaling gap, which ``× open3d`` in ``bench_core`` mixes.
Prints a markdown table and writes one JSONL record per row to
``benchmarks/results/bench_threads-<UTC time>.jsonl`` (atomically, after each).

    python benchmarks/bench_threads.py --scenes staircase kitchen --threads 2
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"
RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_SCENES = ("staircase", "kitchen")
PROCEDURAL = ("sphereflake",)


def _trace_on(accel, rays, key: str, query: str, threads: int, restore: int) -> object:
    """Trace with numba limited to ``threads`` threads, then restore ``restore``."""
    import numba

    numba.set_num_threads(threads)
    try:
        return accel.trace(rays, traversal=key, query=query)
    finally:
        numba.set_num_threads(restore)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=None)
    parser.add_argument("--builder", default="bvh2.binned_sah")
    parser.add_argument("--traversals", nargs="+", default=["bvh2.stack"])
    parser.add_argument("--rays", default="primary,diffuse,shadow")
    parser.add_argument("--threads", type=int, default=2, help="the N of 1 against N threads")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--output", type=Path, default=None, help="JSONL file to append to")
    args = parser.parse_args(argv)

    warnings.filterwarnings("ignore", message="The TBB threading layer requires")
    if SHARED_SCENES.is_dir() and not os.environ.get("RAYACCEL_SCENE_PATH"):
        os.environ["RAYACCEL_SCENE_PATH"] = str(SHARED_SCENES)

    import numba

    import rayaccel
    from rayaccel.bench import report
    from rayaccel.bench.harness import timed_round_robin
    from rayaccel.bench.peers import get_peer
    from rayaccel.bench.raysets import parse_kinds, standard_raysets
    from rayaccel.scene import catalog

    n = args.threads
    if not 1 < n <= numba.config.NUMBA_NUM_THREADS:
        parser.error(f"--threads: expected 2..{numba.config.NUMBA_NUM_THREADS}, got {n}")
    available = catalog.names()
    scenes = args.scenes or [s for s in DEFAULT_SCENES if s in available] or list(PROCEDURAL)
    stamp = report.utc_stamp()
    output = args.output or RESULTS / f"bench_threads-{stamp}.jsonl"
    writer = report.JsonlWriter(output)
    rows: list[dict] = []
    for scene in scenes:
        mesh = rayaccel.scenes.get(scene)
        accel = rayaccel.build(mesh, args.builder)
        sets = standard_raysets(
            mesh,
            scene,
            kinds=parse_kinds(args.rays),
            width=args.width,
            height=args.height,
            accel=accel,
        )
        # Peers that run here: Open3D on 1 and n threads, embreex on its one thread.
        peers: dict[str, object] = {}
        for label, name, threads in (
            ("open3d-1", "open3d", 1),
            (f"open3d-{n}", "open3d", n),
            ("embreex-1", "embree", 1),
        ):
            peer = get_peer(name)
            if peer.available() and peer.skip_reason(mesh) is None:
                peer.set_threads(threads)
                peer.build(mesh)
                peers[label] = peer
        for kind, rayset in sets.items():
            rays, query = rayset.rays, rayset.query
            systems: dict[str, Callable[[], object]] = {}
            for label, peer in peers.items():
                prepared = peer.prepare(peer.limit(rays))
                run = peer.occluded if query == "any" else peer.intersect
                systems[label] = lambda run=run, prepared=prepared: run(prepared)
            for key in args.traversals:
                for threads in (1, n):
                    systems[f"{key}-{threads}"] = functools.partial(
                        _trace_on, accel, rays, key, query, threads, n
                    )
            seconds, _ = timed_round_robin(list(systems.values()), args.repeats)
            ms = {
                label: float(np.median(t) * 1e3)
                for label, t in zip(systems, seconds, strict=True)
            }
            embreex = ms.get("embreex-1")
            for base in [*(k for k in args.traversals), "open3d"]:
                one, many = ms.get(f"{base}-1"), ms.get(f"{base}-{n}")
                if one is None or many is None:
                    continue
                record = {
                    "bench": "threads", "scene": scene, "n_prims": mesh.n_triangles,
                    "rays": kind, "query": query, "n_rays": rays.n_rays, "system": base,
                    "threads": n, "ms_1": round(one, 3), "ms_n": round(many, 3),
                    "speedup": round(one / many, 3),
                    "one_thread_vs_embreex": round(one / embreex, 3) if embreex else None,
                    "embreex_ms": round(embreex, 3) if embreex else None,
                    "repeats": args.repeats, "builder": args.builder, "time": stamp,
                }  # fmt: skip
                rows.append(record)
                writer.append(record)
                print(f"{scene:12s} {kind:8s} {base:12s} speed-up x{record['speedup']:.2f}",
                      file=sys.stderr)  # fmt: skip
    print(_markdown(rows, n))
    print(f"\n{len(rows)} records in {output}", file=sys.stderr)
    return 0


def _markdown(rows: list[dict], n: int) -> str:
    lines = [
        f"| scene | rays | system | ms, 1 thread | ms, {n} threads | speed-up "
        "| 1-thread time / embreex's |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        vs = "–" if r["one_thread_vs_embreex"] is None else f"{r['one_thread_vs_embreex']:.2f}"
        lines.append(
            f"| {r['scene']} | {r['rays']} | {r['system']} | {r['ms_1']:.1f} | {r['ms_n']:.1f} "
            f"| {r['speedup']:.2f} | {vs} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
