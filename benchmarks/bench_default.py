"""The default query traversal against Embree (Open3D), on several cameras per scene.

Issue 21's protocol: for each scene and camera (the catalog preset and turned views,
:mod:`rayaccel.rays.views`), primary, diffuse and shadow (any-hit) rays of the bench
(:func:`rayaccel.bench.raysets.standard_raysets`), traced by ``accel.trace(rays)``
with no traversal named (the default: ``bvh2.packet`` for coherent batches,
``bvh2.wide`` otherwise, :func:`rayaccel.registry.query_traversal`), by
``bvh2.wide`` and ``bvh2.packet`` named, and by Open3D's ``RaycastingScene`` with the
same threads, in interleaved rounds (:func:`rayaccel.bench.harness.timed_round_robin`);
``--peers open3d mitsuba`` adds Mitsuba 3 (``llvm_ad_rgb``, ``ray_intersect_preliminary``
and ``ray_test``) to the rounds. Every result is checked against ``bvh2.stack``'s (same
hit mask; same ``t`` for closest hits, within 1e-6 of the scene for the peers' own
arithmetic). Prints a markdown table: Mrays/s (medians) and the ratio to Open3D, and the
default's ratio to each further peer.

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=$SCENES python benchmarks/bench_default.py \\
        --scenes staircase living_room kitchen --views preset yaw40 orbit90 --peers open3d mitsuba
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

import rayaccel
from rayaccel.bench.harness import OWN_POOL, timed_round_robin
from rayaccel.bench.peers import get_peer
from rayaccel.bench.raysets import standard_raysets
from rayaccel.rays.batch import HitBatch, RayBatch

#: The rayaccel systems, before the peers.
OWN = ("default", "bvh2.wide", "bvh2.packet")


def _check(reference: HitBatch, hits: HitBatch, query: str, label: str) -> None:
    """Raise when ``hits`` disagree with ``bvh2.stack``'s (hit mask; ``t`` of closest hits)."""
    same = (reference.prim >= 0) == (hits.prim >= 0)
    if query == "closest":
        same &= (reference.t == hits.t) | ((reference.prim < 0) & (hits.prim < 0))
    if not same.all():
        raise AssertionError(f"{label}: {int((~same).sum())} rays differ from bvh2.stack")


def _check_peer(reference: HitBatch, answer: Any, query: str, label: str, scale: float) -> None:
    """Raise when a peer's answer differs from ``bvh2.stack``'s on more than 0.1% of the rays.

    Peers use their own arithmetic (Embree's triangle test is not watertight), so rays
    grazing an edge may differ; a wrong adapter differs on many.
    """
    if query == "any":
        differ = np.asarray(answer) != (reference.prim >= 0)
    else:
        t, prim = answer
        hit = prim >= 0
        differ = hit != (reference.prim >= 0)
        both = hit & (reference.prim >= 0)
        differ[both] = np.abs(t[both] - reference.t[both]) > 1e-6 * scale
    if differ.mean() > 1e-3:
        raise AssertionError(f"{label}: {int(differ.sum())} rays differ from bvh2.stack")


def _systems(accel: Any, peers: list[Any], prepared: list[Any], rays: RayBatch,
             query: str) -> list[Callable[[], Any]]:  # fmt: skip
    """Return one traced pass of each rayaccel system and each peer on ``rays``."""
    own: list[Callable[[], Any]] = [
        lambda: accel.trace(rays, query=query),
        lambda: accel.trace(rays, query=query, traversal="bvh2.wide"),
        lambda: accel.trace(rays, query=query, traversal="bvh2.packet"),
    ]
    for peer, batch in zip(peers, prepared, strict=True):
        own.append(
            (lambda p, b: lambda: p.occluded(b) if query == "any" else p.intersect(b))(peer, batch)
        )
    return own


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["staircase", "living_room", "kitchen"])
    parser.add_argument("--views", nargs="+", default=["preset", "yaw40", "orbit90"])
    parser.add_argument("--size", nargs=2, type=int, default=[512, 512])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--peers", nargs="+", default=["open3d"],
                        help="peers timed in the same rounds; the first is the ratios' base")
    args = parser.parse_args(argv)
    threads = numba.get_num_threads()
    systems = [*OWN, *args.peers]
    extra = [f"default / {name}" for name in args.peers[1:]]
    print(f"threads {threads}; Mrays/s (median of {args.repeats}) and × {args.peers[0]}\n")
    print("| scene | view | rays | default | " + " | ".join(systems[1:] + extra) + " |")
    print("|---|---|---|" + "---:|" * (len(systems) + len(extra)))
    for scene in args.scenes:
        mesh = rayaccel.scenes.get(scene)
        accel = rayaccel.build(mesh)
        scale = float(np.abs(mesh.vertices).max())
        peers = [get_peer(name) for name in args.peers]
        for peer in peers:
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
                prepared = [peer.prepare(rays) for peer in peers]
                fns = _systems(accel, peers, prepared, rays, query)
                for name, fn in zip(systems, fns, strict=True):
                    label = f"{scene} {view} {kind} {name}"
                    if name in OWN:
                        _check(reference, fn(), query, label)
                    else:
                        _check_peer(reference, fn(), query, label, scale)
                pools = [OWN_POOL] * len(OWN) + args.peers
                seconds, _ = timed_round_robin(fns, args.repeats, pools)
                rates = [rays.n_rays / np.median(s) / 1e6 for s in seconds]
                base = rates[len(OWN)]
                chosen = accel.query_traversal(rays)
                cells = [f"{r:.2f} ({r / base:.2f}×)" for r in rates]
                cells += [f"{rates[0] / r:.2f}×" for r in rates[len(OWN) + 1 :]]
                print(f"| {scene} | {view} | {kind} | {cells[0]} `{chosen}` | "
                      + " | ".join(cells[1:]) + " |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
