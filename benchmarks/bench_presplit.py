"""Pre-splitting (``+presplit``): references, build time, SAH and primary-ray speed.

For every scene and builder, builds without pre-splitting and with each method
(``median``, ``evh``), all in one process so the ratios are comparable, and records
references per triangle, the presplit step's and the builder's time (median of
``--build-repeats`` after one untimed build), the SAH, and ``bvh2.stack`` closest-hit
throughput on primary rays (median and best of ``--repeats`` rounds after a warm-up,
the three trees of a builder interleaved in every round so load drifts hit them
alike). One JSONL record per (scene, builder, method); a Markdown table at the end.

    RAYACCEL_SCENE_PATH=/path/to/scenes python benchmarks/bench_presplit.py --scenes kitchen
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
from rayaccel.bench.raysets import standard_raysets

METHODS = ("none", "median", "evh")


def build(mesh, name, builder, method, args) -> tuple[dict, rayaccel.Accel]:
    key = builder if method == "none" else builder + "+presplit"
    kwargs = {} if method == "none" else {"presplit": {"method": method}}
    runs = [rayaccel.build(mesh, key, **kwargs) for _ in range(args.build_repeats + 1)]
    accel = runs[-1]
    info = accel.info()
    record = {
        "scene": name, "builder": builder, "presplit": method, "n_tris": mesh.n_triangles,
        "threads": numba.get_num_threads(), "n_refs": info["n_refs"],
        "refs_per_prim": round(info["refs_per_prim"], 4),
        "presplit_ms": round(statistics.median(
            r.step_ms.get("bvh2+presplit", 0.0) for r in runs[1:]), 1),
        "builder_ms": round(statistics.median(r.step_ms[builder] for r in runs[1:]), 1),
        "sah": round(info["sah"], 3),
    }  # fmt: skip
    return record, accel


def trace_rates(accels: list[rayaccel.Accel], rays, repeats: int) -> list[list[float]]:
    """Mrays/s of each accel, ``repeats`` rounds interleaved (load drifts hit all alike)."""
    for accel in accels:
        accel.trace(rays, traversal="bvh2.stack")
    rates: list[list[float]] = [[] for _ in accels]
    for _ in range(repeats):
        for i, accel in enumerate(accels):
            start = time.perf_counter()
            accel.trace(rays, traversal="bvh2.stack")
            rates[i].append(rays.n_rays / (time.perf_counter() - start) / 1e6)
    return rates


def table(records: list[dict]) -> str:
    cols = ["builder", "presplit", "refs_per_prim", "presplit_ms", "builder_ms", "sah",
            "mrays_primary", "mrays_primary_best"]  # fmt: skip
    out = []
    for scene in dict.fromkeys(r["scene"] for r in records):
        rows = [r for r in records if r["scene"] == scene]
        out.append(f"\n**{scene}** ({rows[0]['n_tris']:,} triangles, "
                   f"{rows[0]['threads']} threads)\n")  # fmt: skip
        out.append("| " + " | ".join(cols) + " |")
        out.append("|" + "---|" * len(cols))
        for r in rows:
            out.append("| " + " | ".join(str(r[c]) for c in cols) + " |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["kitchen"])
    parser.add_argument("--builders", nargs="+", default=["bvh2.lbvh", "bvh2.binned_sah"])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--build-repeats", type=int, default=2)
    parser.add_argument("--json", default=None, help="JSONL output (default results/...)")
    args = parser.parse_args(argv)
    stamp = report.utc_stamp()
    output = Path(args.json or Path(__file__).parent / "results" / f"bench_presplit-{stamp}.jsonl")
    writer = report.JsonlWriter(output)
    records = []
    for name in args.scenes:
        mesh = rayaccel.scenes.get(name)
        rays = standard_raysets(
            mesh, name, kinds=("primary",), width=args.width, height=args.height
        )["primary"].rays
        for builder in args.builders:
            built = [build(mesh, name, builder, method, args) for method in args.methods]
            rates = trace_rates([accel for _, accel in built], rays, args.repeats)
            for (record, _), rate in zip(built, rates, strict=True):
                record["mrays_primary"] = round(statistics.median(rate), 3)
                record["mrays_primary_best"] = round(max(rate), 3)
                records.append(record)
                writer.append(record)
                print(record, file=sys.stderr, flush=True)
    print(table(records))
    print(f"\n{len(records)} records in {output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
