"""The default query traversal against Embree (Open3D), on several cameras per scene.

Issue 21's protocol: for each scene and camera (the catalog preset and turned views,
:mod:`rayaccel.rays.views`), primary, diffuse and shadow (any-hit) rays of the bench
(:func:`rayaccel.bench.raysets.standard_raysets`), traced by ``accel.trace(rays)``
with no traversal named (the default: ``bvh2.packet`` for coherent batches,
``bvh2.wide`` otherwise, :func:`rayaccel.registry.query_traversal`), by
``bvh2.wide`` and ``bvh2.packet`` named, and by Open3D's ``RaycastingScene`` with the
same threads, in interleaved rounds (:func:`rayaccel.bench.harness.timed_round_robin`).
Every rayaccel result is checked against ``bvh2.stack``'s (same hit mask; same ``t``
for closest hits). Prints a markdown table: Mrays/s (medians) and the ratio to Open3D.

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=$SCENES python benchmarks/bench_default.py \\
        --scenes staircase living_room kitchen --views preset yaw40 orbit90
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

import rayaccel
from rayaccel.bench.harness import timed_round_robin
from rayaccel.bench.peers import get_peer
from rayaccel.bench.raysets import standard_raysets
from rayaccel.rays.batch import HitBatch, RayBatch

SYSTEMS = ("default", "bvh2.wide", "bvh2.packet", "open3d")


def _check(reference: HitBatch, hits: HitBatch, query: str, label: str) -> None:
    """Raise when ``hits`` disagree with ``bvh2.stack``'s (hit mask; ``t`` of closest hits)."""
    same = (reference.prim >= 0) == (hits.prim >= 0)
    if query == "closest":
        same &= (reference.t == hits.t) | ((reference.prim < 0) & (hits.prim < 0))
    if not same.all():
        raise AssertionError(f"{label}: {int((~same).sum())} rays differ from bvh2.stack")


def _systems(accel: Any, peer: Any, rays: RayBatch, query: str) -> list[Callable[[], Any]]:
    """Return one traced pass of each of :data:`SYSTEMS` on ``rays``."""
    prepared = peer.prepare(rays)
    return [
        lambda: accel.trace(rays, query=query),
        lambda: accel.trace(rays, query=query, traversal="bvh2.wide"),
        lambda: accel.trace(rays, query=query, traversal="bvh2.packet"),
        lambda: peer.occluded(prepared) if query == "any" else peer.intersect(prepared),
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["staircase", "living_room", "kitchen"])
    parser.add_argument("--views", nargs="+", default=["preset", "yaw40", "orbit90"])
    parser.add_argument("--size", nargs=2, type=int, default=[512, 512])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    threads = numba.get_num_threads()
    print(f"threads {threads}; Mrays/s (median of {args.repeats}) and × open3d\n")
    print("| scene | view | rays | default | " + " | ".join(SYSTEMS[1:]) + " |")
    print("|---|---|---|" + "---:|" * len(SYSTEMS))
    for scene in args.scenes:
        mesh = rayaccel.scenes.get(scene)
        accel = rayaccel.build(mesh)
        peer = get_peer("open3d")
        peer.set_threads(threads)
        peer.build(mesh)
        for view in args.views:
            turned = None if view == "preset" else view
            sets = standard_raysets(mesh, scene, width=args.size[0], height=args.size[1],
                                    accel=accel, view=turned)  # fmt: skip
            for kind, ray_set in sets.items():
                query = ray_set.query
                rays = ray_set.rays
                reference = accel.trace(rays, query=query, traversal="bvh2.stack")
                fns = _systems(accel, peer, rays, query)
                for name, fn in zip(SYSTEMS[:3], fns[:3], strict=True):
                    _check(reference, fn(), query, f"{scene} {view} {kind} {name}")
                seconds, _ = timed_round_robin(fns, args.repeats)
                rates = [rays.n_rays / np.median(s) / 1e6 for s in seconds]
                chosen = accel.query_traversal(rays)
                cells = [f"{r:.2f} ({r / rates[-1]:.2f}×)" for r in rates]
                print(f"| {scene} | {view} | {kind} | {cells[0]} `{chosen}` | "
                      + " | ".join(cells[1:]) + " |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
