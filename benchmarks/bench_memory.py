"""Memory of a structure ready for queries: process RSS growth, rayaccel against Embree (Open3D).

Each system runs in a fresh process, which first makes the scene's standard ray sets
(256×256 primary rays, their diffuse and shadow rays) and loads its code by answering the
Cornell box's ray sets (rayaccel: every kernel the queries use), then reads its resident
set size, builds the structure over the scene and answers every ray set (rayaccel:
``Accel.trace`` with no traversal named, i.e. the default queries and the layouts they
derive, or the traversal given by ``--traversal``; Open3D: its peer in
:mod:`rayaccel.bench.peers`), drops garbage and returns freed heap pages to the system
(``malloc_trim``), and reads it again. The growth per triangle is issue 21's measure; for
rayaccel, ``Accel.info()``'s bytes (the canonical structure and each derived layout) are
listed beside it.

    RAYACCEL_SCENE_PATH=../shared/scenes python benchmarks/bench_memory.py kitchen
    RAYACCEL_SCENE_PATH=../shared/scenes python benchmarks/bench_memory.py kitchen \\
        --traversal bvh2.stack
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import json
import subprocess
import sys
from typing import Any

#: The ray-set size of every run.
SIZE = 256


def _trim() -> None:
    """Collect garbage and hand freed heap pages back to the system (glibc only)."""
    gc.collect()
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def _rss() -> int:
    import psutil

    return int(psutil.Process().memory_info().rss)


def _queries(raysets: dict[str, Any]) -> list[tuple[str, Any]]:
    """Return ``(query, rays)`` of every non-empty ray set."""
    return [(s.query, s.rays) for s in raysets.values() if s.rays.n_rays]


def measure(system: str, scene: str, key: str, traversal: str | None) -> dict[str, Any]:
    """Return one system's RSS growth on ``scene`` (run in a process of its own)."""
    import rayaccel
    from rayaccel.bench.raysets import standard_raysets

    mesh = rayaccel.scenes.get(scene)
    queries = _queries(standard_raysets(mesh, scene, width=SIZE, height=SIZE))
    small = rayaccel.scenes.get("cornell-box")
    small_queries = _queries(standard_raysets(small, "cornell-box", width=64, height=64))
    record: dict[str, Any] = {"system": system, "scene": scene, "n_tris": mesh.n_triangles}
    if system == "open3d":
        from rayaccel.bench.peers import get_peer

        peer = get_peer("open3d")

        def answer(sets: list[tuple[str, Any]]) -> None:
            for query, rays in sets:
                batch = peer.prepare(rays)
                peer.occluded(batch) if query == "any" else peer.intersect(batch)

        peer.build(small)
        answer(small_queries)
        _trim()
        before = _rss()
        peer.build(mesh)
        answer(queries)
    else:
        from rayaccel.registry import query_traversal

        warm = rayaccel.build(small, key)
        # every traversal a default query may pick (coherent or not), compiled on the small scene
        picks = {traversal} if traversal else {
            query_traversal(warm.structure_name, share) for share in (0.0, 1.0)
        }  # fmt: skip
        for query, rays in small_queries:
            for pick in picks:
                warm.trace(rays, query=query, traversal=pick)
        del warm
        _trim()
        before = _rss()
        built = rayaccel.build(mesh, key)
        for query, rays in queries:
            built.trace(rays, query=query, traversal=traversal)
    _trim()
    growth = _rss() - before
    if system != "open3d":
        # Read after the RSS: info() recomputes released boxes for the SAH it reports.
        info = built.info()
        record["info_bytes"] = info["bytes"]
        record["layouts"] = {name: entry["bytes"] for name, entry in info["layouts"].items()}
    record["rss_growth_mb"] = round(growth / 1e6, 1)
    record["bytes_per_tri"] = round(growth / mesh.n_triangles, 1)
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--key", default="bvh2.binned_sah", help="rayaccel builder")
    parser.add_argument("--traversal", default=None, help="default: the default queries")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.child, args.scene, args.key, args.traversal)))
        return 0
    for system in ("open3d", "rayaccel"):
        command = [sys.executable, __file__, args.scene, "--key", args.key, "--child", system]
        if args.traversal:
            command += ["--traversal", args.traversal]
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        if done.returncode:
            print(f"{system}: failed\n{done.stderr[-2000:]}", file=sys.stderr)
            continue
        record = json.loads(done.stdout.strip().splitlines()[-1])
        extra = ""
        if "layouts" in record:
            parts = ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in record["layouts"].items())
            extra = f"; info() {record['info_bytes'] / 1e6:.1f} MB (layouts: {parts})"
        print(f"{system}: RSS +{record['rss_growth_mb']} MB, "
              f"{record['bytes_per_tri']} bytes per triangle{extra}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
