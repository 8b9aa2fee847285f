"""Cost of one ``bvh2.stack`` node step, on distinct rays and on a few rays repeated.

For each scene and ray type (``rayaccel.bench.raysets.standard_raysets``) the batch
is traced as it is ("distinct") and as a batch of the same length made of eight of
its chunks of ``RAY_CHUNK`` rays (the traversal's work item), tiled ("repeated"):
the same per-chunk work, but every ray is traced thousands of times, so its nodes and
triangles stay in cache. Both are timed interleaved (median of ``--repeats`` passes
after a warm-up pass of each) and reported as nanoseconds per node visit per thread
(time × threads / node visits).

A repeated ray also repeats its branch outcomes, which the CPU's predictor can
learn, so the gap between the two columns is memory *and* mispredicted branches,
not memory alone. Prints a markdown table and writes one JSONL record per row to
``benchmarks/results/step_cost-<UTC time>.jsonl`` (atomically, after each).

    python benchmarks/step_cost.py --scenes staircase kitchen
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"
RESULTS = Path(__file__).resolve().parent / "results"
N_CHUNKS = 8
TRAVERSAL = "bvh2.stack"


def repeated_batch(rays, seed: int):
    """Return a batch of ``rays.n_rays`` rays made of ``N_CHUNKS`` chunks of ``rays``, tiled."""
    from rayaccel.rays.batch import RayBatch
    from rayaccel.trace.skeleton import RAY_CHUNK

    n = rays.n_rays
    rng = np.random.Generator(np.random.PCG64(seed))
    starts = RAY_CHUNK * rng.integers(0, max(n // RAY_CHUNK, 1), N_CHUNKS)
    few = (starts[:, None] + np.arange(RAY_CHUNK)).ravel() % n
    pick = np.resize(few, n)
    return RayBatch(rays.origin[pick], rays.direction[pick], rays.tmin[pick], rays.tmax[pick])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["staircase", "living_room", "kitchen"])
    parser.add_argument("--builder", default="bvh2.binned_sah")
    parser.add_argument("--rays", default="primary,diffuse,shadow")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--output", type=Path, default=None, help="JSONL file to append to")
    args = parser.parse_args(argv)
    if SHARED_SCENES.is_dir() and not os.environ.get("RAYACCEL_SCENE_PATH"):
        os.environ["RAYACCEL_SCENE_PATH"] = str(SHARED_SCENES)

    import numba

    import rayaccel
    from rayaccel.bench import report
    from rayaccel.bench.harness import timed_round_robin
    from rayaccel.bench.raysets import parse_kinds, standard_raysets

    threads = int(numba.get_num_threads())
    stamp = report.utc_stamp()
    output = args.output or RESULTS / f"step_cost-{stamp}.jsonl"
    writer = report.JsonlWriter(output)
    lines = [
        "| scene | rays | nodes/ray distinct / repeated | ns per node visit per thread: "
        "distinct | repeated | repeated / distinct |",
        "|---|---|---|---:|---:|---:|",
    ]
    for scene in args.scenes:
        mesh = rayaccel.scenes.get(scene)
        accel = rayaccel.build(mesh, args.builder)
        sets = standard_raysets(mesh, scene, kinds=parse_kinds(args.rays), accel=accel)
        for kind, rayset in sets.items():
            batches = {"distinct": rayset.rays, "repeated": repeated_batch(rayset.rays, 0)}
            query = rayset.query
            counted = {
                label: accel.trace(b, query=query, traversal=TRAVERSAL, stats=True)
                for label, b in batches.items()
            }
            nodes = {label: float(hits.stats["nodes"].sum()) for label, hits in counted.items()}
            passes = [
                lambda b=b, a=accel, q=query: a.trace(b, query=q, traversal=TRAVERSAL)
                for b in batches.values()
            ]
            seconds, _ = timed_round_robin(passes, args.repeats)
            ns = {
                label: float(np.median(s)) * threads / nodes[label] * 1e9
                for label, s in zip(batches, seconds, strict=True)
            }
            n = rayset.n_rays
            record = {
                "bench": "step_cost", "scene": scene, "builder": args.builder, "rays": kind,
                "query": rayset.query, "n_rays": n, "threads": threads,
                "nodes_per_ray": {k: round(v / n, 3) for k, v in nodes.items()},
                "ns_per_node_visit": {k: round(v, 3) for k, v in ns.items()},
                "repeats": args.repeats, "time": stamp,
            }  # fmt: skip
            writer.append(record)
            lines.append(
                f"| {scene} | {kind} | {nodes['distinct'] / n:.1f} / {nodes['repeated'] / n:.1f} "
                f"| {ns['distinct']:.2f} | {ns['repeated']:.2f} "
                f"| {ns['repeated'] / ns['distinct']:.2f} |"
            )
            print(lines[-1], file=sys.stderr)
    print("\n".join(lines))
    print(f"\n{len(writer)} records in {output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
