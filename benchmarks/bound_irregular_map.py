"""How fast the irregular grid's walk could be if it knew every ray's cells in advance.

Each step of ``grid.irregular``'s walk depends on the one before: the exit from the
current cell's expanded box gives the next voxel, the voxel map (three dependent loads:
top cell, leaf, cell) gives its cell, and that cell's range and box are loaded before
the next exit can be computed. This script bounds what any change to that chain (a
faster or smaller map, links between cells, a cheaper exit) could gain: it records
every ray's cells in a first pass, then times the same walk
(:func:`rayaccel.grid.traverse.irregular.walk_body`, the traversal's own body) with
the map replaced by a read of the recorded cell, a streaming load that depends on no
earlier step, so that the processor can run ahead across cells. It times that walk,
the walk with the map and ``bvh2.stack`` on the same rays (median of ``--repeats``
interleaved passes, after checking that both walks return the traversal's hits). The
cell tests, the exits and the triangle tests stay as they are, so the recorded walk
still does all the work the irregular grid's cells ask for. Rays entering more than
``--max-cells`` cells look the rest up in the map.

    python benchmarks/bound_irregular_map.py --scenes living_room kitchen --views preset yaw40
"""

from __future__ import annotations

import argparse
import os
import sys
from collections import namedtuple
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED_SCENES = ROOT.parent / "shared" / "scenes"
RESULTS = Path(__file__).resolve().parent / "results"


def replay_kernels(max_cells: int):
    """Return the walks recording and replaying cells, and their layouts' types.

    The recording walk writes ray ``r``'s cells into row ``r`` of ``cells`` (``-1``
    past its last); the replaying one reads them back from ``flat[offsets[r]:offsets[r +
    1]]``, each ray's cells side by side in the order the rays are traced, so that
    the reads stream through memory.
    """
    from rayaccel._jit import cpu_inline
    from rayaccel.grid.layouts.irregular import IrregularTrace
    from rayaccel.grid.traverse.irregular import map_cell, walk_body
    from rayaccel.grid.traverse.walk import make_mailbox
    from rayaccel.trace.run import body_kernels

    def record_cell_py(grid, shift, r, step, cx, cy, cz):
        cell = map_cell(grid, shift, r, step, cx, cy, cz)
        if step < max_cells:
            grid.cells[r, step] = cell
        return cell

    def replay_cell_py(grid, shift, r, step, cx, cy, cz):
        at = grid.offsets[np.uint64(r)] + step
        if at < grid.offsets[np.uint64(r + 1)]:
            return np.int64(grid.flat[np.uint64(at)])
        return np.int64(map_cell(grid, shift, r, step, cx, cy, cz))

    record = body_kernels(make_mailbox, walk_body(cpu_inline(record_cell_py)))
    replay = body_kernels(make_mailbox, walk_body(cpu_inline(replay_cell_py)))
    fields = IrregularTrace._fields
    recording = namedtuple("RecordingCells", [*fields, "cells"])
    recorded = namedtuple("RecordedCells", [*fields, "offsets", "flat"])
    return record, replay, recording, recorded


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["staircase", "living_room", "kitchen"])
    parser.add_argument("--views", nargs="+", default=["preset"])
    parser.add_argument("--rays", default="primary,diffuse")
    parser.add_argument("--size", type=int, default=384, help="rays per side of the image")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--max-cells", type=int, default=64)
    parser.add_argument("--output", type=Path, default=None, help="JSONL file to append to")
    args = parser.parse_args(argv)
    if SHARED_SCENES.is_dir() and not os.environ.get("RAYACCEL_SCENE_PATH"):
        os.environ["RAYACCEL_SCENE_PATH"] = str(SHARED_SCENES)

    import numba

    import rayaccel
    from rayaccel.bench import report
    from rayaccel.bench.harness import timed_round_robin
    from rayaccel.bench.raysets import parse_kinds, standard_raysets
    from rayaccel.cuda.report import kernel_plan
    from rayaccel.trace.run import body_kernels, run_trace

    record, replay, recording, recorded = replay_kernels(args.max_cells)
    threads = int(numba.get_num_threads())
    stamp = report.utc_stamp()
    output = args.output or RESULTS / f"bound_irregular_map-{stamp}.jsonl"
    writer = report.JsonlWriter(output)
    lines = [
        "| scene, view | rays | cells/ray | walk × `bvh2.stack` | cells known × `bvh2.stack` "
        "| known / walk |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for scene in args.scenes:
        mesh = rayaccel.scenes.get(scene)
        grid = rayaccel.build(mesh, "grid.irregular")
        bvh = rayaccel.build(mesh)
        make_scratch, walk_rays, arrays = kernel_plan(grid, "grid.dda")
        walk = body_kernels(make_scratch, walk_rays)
        for view in args.views:
            sets = standard_raysets(
                mesh, scene, width=args.size, height=args.size, kinds=parse_kinds(args.rays),
                accel=bvh, view=None if view == "preset" else view,
            )  # fmt: skip
            for kind, rayset in sets.items():
                rays, query = rayset.rays, rayset.query
                cells = np.full((rays.n_rays, args.max_cells), -1, np.int32)
                reference = grid.trace(rays, query=query, traversal="grid.dda", stats=True)
                run_trace(record, recording(*arrays, cells), rays, query, False)
                taken = cells >= 0
                offsets = np.concatenate([[0], np.cumsum(taken.sum(axis=1))]).astype(np.int64)
                layout = recorded(*arrays, offsets, cells[taken])
                del cells, taken
                for kernel, lay in ((walk, arrays), (replay, layout)):
                    hits = run_trace(kernel, lay, rays, query, False)
                    if not (
                        np.array_equal(hits.prim >= 0, reference.prim >= 0)
                        and np.array_equal(hits.t, reference.t)
                    ):
                        raise AssertionError(f"{scene} {view} {kind}: the hits differ")
                passes = [
                    lambda r=rays, q=query, lay=arrays, w=walk: run_trace(w, lay, r, q, False),
                    lambda r=rays, q=query, lay=layout: run_trace(replay, lay, r, q, False),
                    lambda r=rays, q=query, b=bvh: b.trace(r, query=q, traversal="bvh2.stack"),
                ]
                seconds, _ = timed_round_robin(passes, args.repeats)
                walk_s, known_s, bvh_s = (float(np.median(s)) for s in seconds)
                per_ray = float(reference.stats["cells"].mean())
                writer.append({
                    "bench": "bound_irregular_map", "scene": scene, "view": view, "rays": kind,
                    "query": query, "n_rays": rays.n_rays, "threads": threads,
                    "cells_per_ray": round(per_ray, 3), "seconds": {
                        "map_walk": walk_s, "known_cells_walk": known_s, "bvh2.stack": bvh_s},
                    "repeats": args.repeats, "max_cells": args.max_cells, "time": stamp,
                })  # fmt: skip
                lines.append(
                    f"| {scene}, {view} | {kind} | {per_ray:.1f} | {bvh_s / walk_s:.2f} "
                    f"| {bvh_s / known_s:.2f} | {walk_s / known_s:.2f} |"
                )
                print(lines[-1], file=sys.stderr)
    print("\n".join(lines))
    print(f"\n{len(writer)} records in {output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
