"""Stackless traversals against ``bvh2.stack``: node overvisit, backtracking, Mrays/s ratio.

For each scene and ray type (primary, diffuse, shadow from
``rayaccel.bench.raysets.standard_raysets``) every stackless traversal is traced
with counters (nodes per ray relative to ``bvh2.stack``, restarts, backtracks, hash
lookups, the histogram of backtracking targets) and timed without them,
interleaved with ``bvh2.stack`` in the same run (median of ``--repeats`` passes
after a warm-up; the machine is shared, so only ratios within a run are meaningful).
Every traversal is first checked to return ``bvh2.stack``'s hit distances bit for
bit. Prints a markdown table and writes one JSONL record per row to
``benchmarks/results/bench_stackless-<UTC time>.jsonl`` (atomically, after each).

    python benchmarks/bench_stackless.py
    python benchmarks/bench_stackless.py --scenes staircase --width 128 --height 128
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"
RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_SCENES = ("staircase", "living_room", "kitchen", "sponza_dabrovic", "salle_de_bain")
PROCEDURAL = ("sphereflake", "teapot-in-stadium")

#: (label, traversal key, options), bvh2.stack first.
VARIANTS = [
    ("stack", "bvh2.stack", {}),
    ("restart_trail", "bvh2.restart_trail", {}),
    ("restart_trail+ss3", "bvh2.restart_trail", {"short_stack": 3}),
    ("parent_link", "bvh2.parent_link", {}),
    ("bitstack", "bvh2.bitstack", {}),
    ("perfect_hash", "bvh2.perfect_hash", {}),
    ("ph-no_mask", "bvh2.perfect_hash", {"level_mask": False}),
    ("ph-no_register", "bvh2.perfect_hash", {"register": False}),
    ("ph-no_uncles", "bvh2.perfect_hash", {"uncle_refs": False}),
    ("ph-no_hash", "bvh2.perfect_hash", {"hash": False}),
    ("skip", "bvh2.skip", {}),
]
HISTOGRAM = ("backtrack_sibling", "backtrack_uncle", "backtrack_grand_uncle", "backtrack_further")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=None)
    parser.add_argument("--builder", default="bvh2.binned_sah")
    parser.add_argument("--rays", default="primary,diffuse,shadow")
    parser.add_argument("--variants", default="", help="comma-separated labels (default all)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--height", type=int, default=256)
    parser.add_argument("--output", type=Path, default=None, help="JSONL file to append to")
    args = parser.parse_args(argv)

    warnings.filterwarnings("ignore", message="The TBB threading layer requires")
    if SHARED_SCENES.is_dir() and not os.environ.get("RAYACCEL_SCENE_PATH"):
        os.environ["RAYACCEL_SCENE_PATH"] = str(SHARED_SCENES)

    import rayaccel
    from rayaccel.bench import report
    from rayaccel.bench.raysets import parse_kinds, standard_raysets
    from rayaccel.scene import catalog

    available = catalog.names()
    scenes = args.scenes or [s for s in DEFAULT_SCENES if s in available] or list(PROCEDURAL)
    wanted = {v for v in args.variants.split(",") if v}
    variants = [v for v in VARIANTS if not wanted or v[0] in wanted or v[0] == "stack"]
    stamp = report.utc_stamp()
    output = args.output or RESULTS / f"bench_stackless-{stamp}.jsonl"
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
        for kind, rayset in sets.items():
            rays, query = rayset.rays, rayset.query
            # Counters, and the identity check against bvh2.stack.
            stats: dict[str, dict[str, np.ndarray]] = {}
            ref = accel.trace(rays, query=query)
            for label, key, opts in variants:
                hits = accel.trace(rays, query=query, traversal=key, stats=True, **opts)
                same = hits.t.tobytes() == ref.t.tobytes()
                same_prim = bool(np.array_equal(hits.prim, ref.prim))
                if query == "any" and key == "bvh2.skip":
                    # Unordered: any-hit may report another hit; occlusion must agree.
                    same = same_prim = bool(np.array_equal(hits.hit, ref.hit))
                if not same or not (same_prim or key == "bvh2.skip"):
                    print(f"MISMATCH {scene}/{kind}/{label}", file=sys.stderr)
                stats[label] = dict(hits.stats, same_prim=np.array([same_prim]))
            # Timing: round-robin passes so every variant sees the same machine state.
            times: dict[str, list[float]] = {label: [] for label, _, _ in variants}
            for _label, key, opts in variants:
                accel.trace(rays, query=query, traversal=key, **opts)
            for _ in range(args.repeats):
                for label, key, opts in variants:
                    start = time.perf_counter()
                    accel.trace(rays, query=query, traversal=key, **opts)
                    times[label].append(time.perf_counter() - start)
            stack_nodes = float(stats["stack"]["nodes"].mean())
            stack_mrays = rays.n_rays / np.median(times["stack"]) / 1e6
            for label, key, opts in variants:
                s = stats[label]
                mrays = rays.n_rays / np.median(times[label]) / 1e6
                n_back = float(s["backtracks"].sum())
                jumps = sum(float(s[h].sum()) for h in HISTOGRAM)
                record = {
                    "bench": "stackless", "scene": scene, "n_prims": mesh.n_triangles,
                    "builder": args.builder, "rays": kind, "query": query,
                    "n_rays": rays.n_rays, "variant": label, "traversal": key,
                    "options": opts,
                    "nodes_per_ray": round(float(s["nodes"].mean()), 3),
                    "overvisit": round(float(s["nodes"].mean()) / stack_nodes, 4),
                    "box_tests_per_ray": round(float(s["box_tests"].mean()), 3),
                    "restarts_per_ray": round(float(s["restarts"].mean()), 4),
                    "backtracks_per_ray": round(n_back / rays.n_rays, 4),
                    "hash_lookups_per_ray": round(float(s["hash_lookups"].mean()), 4),
                    "backtrack_share": {
                        h.removeprefix("backtrack_"): round(float(s[h].sum()) / jumps, 4)
                        for h in HISTOGRAM
                    } if jumps else {},
                    "same_prim_as_stack": bool(s["same_prim"][0]),
                    "mrays": round(float(mrays), 3),
                    "ratio_to_stack": round(float(mrays / stack_mrays), 3),
                    "repeats": args.repeats, "numba_threads": _threads(),
                    "time": stamp,
                }  # fmt: skip
                rows.append(record)
                writer.append(record)
                print(
                    f"{scene:16s} {kind:8s} {label:18s} overvisit {record['overvisit']:.3f} "
                    f"x{record['ratio_to_stack']:.2f}",
                    file=sys.stderr,
                )
    print(_markdown(rows))
    print(f"\n{len(rows)} records in {output}", file=sys.stderr)
    return 0


def _threads() -> int:
    import numba

    return int(numba.get_num_threads())


def _markdown(rows: list[dict]) -> str:
    head = (
        "| scene | rays | traversal | nodes/ray | overvisit | restarts/ray | backtracks/ray "
        "| hash lookups/ray | sibling / uncle / grand-uncle / further | Mrays/s | × stack |"
    )
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        share = r["backtrack_share"]
        hist = (
            " / ".join(
                f"{100 * share[k]:.0f}%" for k in ("sibling", "uncle", "grand_uncle", "further")
            )
            if share
            else ""
        )
        lines.append(
            f"| {r['scene']} | {r['rays']} | {r['variant']} | {r['nodes_per_ray']:.1f} "
            f"| {r['overvisit']:.3f} | {r['restarts_per_ray']:.2f} "
            f"| {r['backtracks_per_ray']:.2f} | {r['hash_lookups_per_ray']:.2f} | {hist} "
            f"| {r['mrays']:.2f} | {r['ratio_to_stack']:.2f} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
