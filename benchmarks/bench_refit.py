"""Refit against rebuild (same builder) on a deforming mesh: time, speed-up and SAH drift.

Each scene's vertices are displaced by a smooth travelling wave (amplitude a fraction of
the scene's extent), one frame per round. In every round ``accel.refit(frame)`` (new-vertex
validation, the bottom-up box refit and the SAH of the refitted tree) and
``rayaccel.build(mesh_of_frame, key)`` run back to back, so both see the same machine
load; the report is the median over rounds after one warm-up round that compiles, the
ratio rebuild / refit of those medians, and the refitted tree's SAH cost relative to its
build (the last frame's). One JSONL record per (scene, key); a Markdown table is printed.
The procedural teapot always runs; file scenes run when found on RAYACCEL_SCENE_PATH.

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=../shared/scenes python benchmarks/bench_refit.py \
        --scenes teapot:64 stanford-bunny sponza_dabrovic --keys bvh2.binned_sah bvh2.lbvh
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numba
import numpy as np

import rayaccel
from rayaccel.bench import report
from rayaccel.errors import SceneFileError, UnknownVariantError


def wave(vertices: np.ndarray, frame: int, amplitude: float = 0.02) -> np.ndarray:
    """``vertices`` moved by a smooth wave of ``amplitude`` × the scene's extent."""
    v = vertices.astype(np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    extent = float((hi - lo).max())
    u = (v - lo) / extent * 2.0 * np.pi
    phase = 0.5 * frame
    offset = np.stack(
        [np.sin(2 * u[:, 1] + phase), np.sin(3 * u[:, 2] - phase), np.cos(2 * u[:, 0] + phase)],
        axis=1,
    )
    return v + amplitude * extent * offset


def load(spec: str) -> rayaccel.TriangleMesh | None:
    """``teapot:64`` is the teapot at subdivision 64; other names are scenes (None if absent)."""
    name, _, param = spec.partition(":")
    try:
        if param:
            return rayaccel.scenes.get(name, subdivisions=int(param))
        return rayaccel.scenes.get(name)
    except (SceneFileError, UnknownVariantError) as exc:
        print(f"{spec}: skipped ({exc})", file=sys.stderr)
        return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["teapot:64", "stanford-bunny"])
    parser.add_argument("--keys", nargs="+", default=["bvh2.binned_sah", "bvh2.lbvh"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--json", default=None, help="JSONL output (default results/...)")
    args = parser.parse_args(argv)
    threads = numba.get_num_threads()
    records = []
    for spec in args.scenes:
        mesh = load(spec)
        if mesh is None:
            continue
        frames = [wave(mesh.vertices, f) for f in range(args.rounds + 1)]
        for key in args.keys:
            accel = rayaccel.build(mesh, key)
            refit_ms, rebuild_ms, kernel_ms = [], [], []
            last: dict = {}
            for i, vertices in enumerate(frames):
                start = time.perf_counter()
                last = accel.refit(vertices)
                refit_ms.append((time.perf_counter() - start) * 1e3)
                kernel_ms.append(last["refit_ms"])
                start = time.perf_counter()
                rayaccel.build(accel.mesh, key)
                rebuild_ms.append((time.perf_counter() - start) * 1e3)
                print(f"{spec} {key} round {i}: refit {refit_ms[-1]:.1f} ms, rebuild "
                      f"{rebuild_ms[-1]:.1f} ms", file=sys.stderr, flush=True)  # fmt: skip
            refit = statistics.median(refit_ms[1:])
            rebuild = statistics.median(rebuild_ms[1:])
            records.append({
                "scene": spec, "builder": key, "n_tris": mesh.n_triangles, "threads": threads,
                "rounds": args.rounds, "refit_ms": round(refit, 2),
                "refit_kernel_ms": round(statistics.median(kernel_ms[1:]), 2),
                "rebuild_ms": round(rebuild, 1), "x_rebuild": round(rebuild / refit, 1),
                "sah_ratio": round(last["ratio"], 3),
            })  # fmt: skip
    stamp = report.utc_stamp()
    output = Path(args.json or Path(__file__).parent / "results" / f"bench_refit-{stamp}.jsonl")
    writer = report.JsonlWriter(output)
    for record in records:
        writer.append(record)
    columns = ["scene", "builder", "n_tris", "refit_ms", "refit_kernel_ms", "rebuild_ms",
               "x_rebuild", "sah_ratio"]  # fmt: skip
    print(f"refit vs rebuild ({threads} threads, median of {args.rounds} rounds)\n")
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for record in records:
        print("| " + " | ".join(str(record[c]) for c in columns) + " |")
    print(f"\n{len(records)} records in {output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
