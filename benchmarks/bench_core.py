"""The core comparison: every registered builder and traversal against Embree and friends.

Runs the ``rayaccel bench`` harness (compile, validate against the oracle, warm up,
median and best of k timed passes) on the shared interior scenes with primary,
diffuse and shadow rays, with the peers (Open3D's Embree, embreex, trimesh) on the
same rays, then prints a markdown table (the form of ``docs/performance.md``) and
writes every record to ``benchmarks/results/bench_core-<UTC time>.jsonl``
(atomically, after each measurement, so an interrupted run keeps what it finished).

    python benchmarks/bench_core.py
    python benchmarks/bench_core.py --scenes staircase living_room kitchen --threads 2
    python benchmarks/bench_core.py --scenes cornell-box --width 128 --height 128 --repeats 3

``RAYACCEL_SCENE_PATH`` is pointed at ``../shared/scenes`` (relative to the
repository root) when that folder exists and the variable is not already set.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"
RESULTS = Path(__file__).resolve().parent / "results"
DEFAULT_SCENES = ("staircase", "living_room", "kitchen")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES))
    parser.add_argument("--accel", nargs="+", default=[], help="builder keys (default all)")
    parser.add_argument(
        "--traversals", nargs="+", default=[], help="traversal keys (default all)"
    )
    parser.add_argument("--threads", default="", help="e.g. 2 or 1,2 (default all cores)")
    parser.add_argument("--peers", default="all", help="embree,open3d,trimesh, all or none")
    parser.add_argument("--rays", default="primary,diffuse,shadow")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--validate", type=int, default=200)
    parser.add_argument("--output", type=Path, default=None, help="JSONL file to append to")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)

    warnings.filterwarnings("ignore", message="The TBB threading layer requires")
    if SHARED_SCENES.is_dir() and not os.environ.get("RAYACCEL_SCENE_PATH"):
        os.environ["RAYACCEL_SCENE_PATH"] = str(SHARED_SCENES)

    from rayaccel.bench import harness, report
    from rayaccel.bench.peers import parse_peers
    from rayaccel.bench.raysets import parse_kinds

    stamp = report.utc_stamp()
    output = args.output or RESULTS / f"bench_core-{stamp}.jsonl"
    threads = [int(n) for n in args.threads.split(",") if n.strip()]
    config = harness.BenchConfig(
        scenes=args.scenes,
        builders=args.accel,
        traversals=args.traversals,
        ray_kinds=parse_kinds(args.rays),
        threads=threads,
        peers=parse_peers(args.peers),
        repeats=args.repeats,
        width=args.width,
        height=args.height,
        validate=args.validate,
    )
    writer = report.JsonlWriter(output)
    records: list[dict] = []

    def sink(record: dict) -> None:
        records.append(record)
        writer.append(record)

    interrupted = False
    notes: list[str] = []
    try:
        result = harness.run_bench(config, on_record=sink, progress=not args.no_progress)
        notes = result.notes
    except KeyboardInterrupt:
        interrupted = True
    print(report.markdown_table(records))
    print()
    for line in (report.environment_line(records), report.compile_summary(records)):
        if line:
            print(f"- {line}")
    print(
        f"- {args.width}x{args.height} primary rays, median and best of {args.repeats} runs "
        f"after one warm-up; '× open3d' is Mrays/s divided by Open3D's on the same rays, "
        f"for rayaccel rows timed round-robin with Open3D's passes (and the stats variant's)"
    )
    for note in notes:
        print(f"- {note}")
    print(f"\n{len(records)} records in {output}", file=sys.stderr)
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
