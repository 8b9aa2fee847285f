"""BVH builder comparison: the thesis's eight configurations on the shared scenes.

For every scene and build key (default: ``registry.configurations()``) this measures
the build time (median of ``--build-repeats`` on the current numba thread count),
triangles per second, SAH, EPO (``--no-epo`` skips it), references per triangle, and
``bvh2.stack`` throughput for primary and diffuse closest-hit rays and shadow any-hit
rays (median of ``--repeats`` after a warm-up) with the mean nodes entered and triangles
tested per ray (independent of the machine's load). One JSONL record per (scene, key),
written atomically after each; a Markdown table per scene is printed at the end.

    NUMBA_NUM_THREADS=2 python benchmarks/bench_builders.py --scenes staircase kitchen
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numba

import rayaccel
from rayaccel import registry
from rayaccel.bench import report
from rayaccel.bench.raysets import standard_raysets
from rayaccel.bvh.metrics import epo

SCENES = ("staircase", "living_room", "salle_de_bain", "kitchen", "sponza_dabrovic")


def measure(mesh, name, key, rays, args) -> dict:
    times = []
    accel = None
    for _ in range(args.build_repeats + 1):
        accel = rayaccel.build(mesh, key)
        times.append(accel.build_ms)
    build_ms = statistics.median(times[1:])  # the first run may compile
    info = accel.info()
    record = {
        "scene": name, "key": key, "n_tris": mesh.n_triangles,
        "threads": numba.get_num_threads(), "build_ms": round(build_ms, 2),
        "mtris_per_s": round(mesh.n_triangles / build_ms / 1e3, 3),
        "step_ms": {k: round(v, 1) for k, v in accel.step_ms.items()},
        "sah": round(info["sah"], 3), "refs_per_prim": round(info["refs_per_prim"], 3),
        "depth": info["depth"], "n_nodes": info["n_nodes"],
        "mean_leaf_size": round(info["mean_leaf_size"], 3),
    }  # fmt: skip
    if args.epo:
        start = time.perf_counter()
        record["epo"] = round(epo(accel.structure, mesh.triangles()), 4)
        record["epo_s"] = round(time.perf_counter() - start, 2)
    for kind, rayset in rays.items():
        accel.trace(rayset.rays, query=rayset.query)
        rates = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            accel.trace(rayset.rays, query=rayset.query, traversal="bvh2.stack")
            rates.append(rayset.n_rays / (time.perf_counter() - start) / 1e6)
        record[f"mrays_{kind}"] = round(statistics.median(rates), 3)
        # Work per ray (machine-independent): nodes entered and triangles tested.
        counted = accel.trace(rayset.rays, query=rayset.query, stats=True).stats
        record[f"nodes_{kind}"] = round(float(counted["nodes"].mean()), 2)
        record[f"prims_{kind}"] = round(float(counted["prim_tests"].mean()), 2)
    return record


def table(records: list[dict]) -> str:
    cols = ["key", "build_ms", "mtris_per_s", "sah", "epo", "refs_per_prim",
            "mrays_primary", "mrays_diffuse", "mrays_shadow",
            "nodes_primary", "prims_primary", "nodes_diffuse", "prims_diffuse"]  # fmt: skip
    out = []
    for scene in dict.fromkeys(r["scene"] for r in records):
        rows = [r for r in records if r["scene"] == scene]
        out.append(f"\n**{scene}** ({rows[0]['n_tris']:,} triangles, "
                   f"{rows[0]['threads']} threads)\n")  # fmt: skip
        out.append("| " + " | ".join(cols) + " |")
        out.append("|" + "---|" * len(cols))
        for r in rows:
            out.append("| " + " | ".join(str(r.get(c, "-")) for c in cols) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--keys", nargs="+", default=None)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--height", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--build-repeats", type=int, default=3)
    parser.add_argument("--no-epo", dest="epo", action="store_false")
    parser.add_argument("--json", default=None, help="JSONL output (default results/...)")
    args = parser.parse_args(argv)
    keys = args.keys or registry.configurations()
    stamp = report.utc_stamp()
    output = Path(args.json or Path(__file__).parent / "results" / f"bench_builders-{stamp}.jsonl")
    writer = report.JsonlWriter(output)
    records = []
    for name in args.scenes:
        mesh = rayaccel.scenes.get(name)
        rays = standard_raysets(mesh, name, width=args.width, height=args.height)
        for key in keys:
            record = measure(mesh, name, key, rays, args)
            records.append(record)
            writer.append(record)
            print(record, file=sys.stderr, flush=True)
    print(table(records))
    print(f"\n{len(records)} records in {output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
