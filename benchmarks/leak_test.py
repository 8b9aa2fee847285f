"""Leak test (issue 20): over a million rays aimed exactly at shared edges and vertices.

Every structure and traversal, closest and any hit, on closed meshes: procedural ones
(icospheres, a UV sphere, a cube, a torus, a jittered and a far-off-centre sphere, the
sphereflake's spheres) and the closed parts of the benchmark scenes found on
``RAYACCEL_SCENE_PATH`` (living room, staircase, bathroom, kitchen; skipped when
absent). The rays come from ``tests/leak_rays.py``: from certainly interior points
through points on the edges and at the vertices, and from outside back through them;
where float32 allows, the point lies exactly on the edge and the ray passes exactly
through it. Every ray must hit. The cases are those of ``tests/test_leaks.py`` (every
traversal on its structure's default builder, every builder with its structure's
default traversal), each tracing the whole ray set::

    nice -n 19 python benchmarks/leak_test.py

Prints the meshes (triangles, rays, exact share, origins outside, a brute-force check
of a subsample) and a table of misses per (builder, traversal, query); ``--json``
writes both. The exit status is 1 when any ray missed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
# Like the tests: the shared scene folder beside the repository, unless a path is set.
if not os.environ.get("RAYACCEL_SCENE_PATH") and (REPO.parent / "shared" / "scenes").is_dir():
    os.environ["RAYACCEL_SCENE_PATH"] = str(REPO.parent / "shared" / "scenes")

import leak_rays  # noqa: E402 - needs the tests folder on the path
import rayaccel  # noqa: E402
import reference  # noqa: E402
from rayaccel.scene import catalog  # noqa: E402

FILE_SCENES = ("living_room", "staircase", "salle_de_bain", "kitchen")
#: Rays per triangle the brute-force check may spend on each mesh.
ORACLE_BUDGET = 2.0e9


def procedural_meshes() -> dict[str, rayaccel.TriangleMesh]:
    """Closed procedural meshes (all of them closed and consistently oriented)."""
    meshes = {
        "icosphere5": reference.icosphere(5),
        "icosphere3-far": reference.icosphere(3, radius=3.0, centre=(1000.0, -2000.0, 500.0)),
        "uv_sphere": reference.uv_sphere(96, 192),
        "cube": reference.cube(),
        "torus": leak_rays.torus(192, 96),
        "icosphere4-jittered": leak_rays.jittered(reference.icosphere(4), 0.005, seed=1),
    }
    flake = leak_rays.closed_parts(rayaccel.scenes.get("sphereflake"), "sphereflake")
    assert flake is not None
    meshes["sphereflake"] = flake
    return meshes


def file_meshes(names: list[str]) -> dict[str, rayaccel.TriangleMesh]:
    """The closed parts of each file scene present."""
    found = catalog.file_scenes()
    meshes = {}
    for name in names:
        if name not in found:
            print(f"  {name}: not found on RAYACCEL_SCENE_PATH, skipped", flush=True)
            continue
        parts = leak_rays.closed_parts(rayaccel.scenes.get(name), f"{name}-closed")
        if parts is None:
            print(f"  {name}: no closed part, skipped", flush=True)
            continue
        meshes[f"{name}-closed"] = parts
    return meshes


def share_rays(sets: dict[str, leak_rays.LeakRays], total: int, seed: int) -> dict:
    """Subsample the sets to ``total`` rays in all: small sets whole, the rest equally."""
    sizes = {name: s.n_rays for name, s in sets.items()}
    left, budget, quota = dict(sizes), total, {}
    while left:
        share = budget // len(left)
        small = {k: v for k, v in left.items() if v <= share}
        if not small:
            for k in left:
                quota[k] = share
            break
        for k, v in small.items():
            quota[k] = v
            budget -= v
            del left[k]
    rng = np.random.default_rng(seed)
    out = {}
    for name, s in sets.items():
        n = quota[name]
        if n < s.n_rays:
            s = s.subset(np.sort(rng.choice(s.n_rays, n, replace=False)))
        out[name] = s
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--rays", type=int, default=1_100_000, help="rays per case over all meshes (default 1.1M)"
    )
    parser.add_argument("--per-edge", type=int, default=2, help="points per edge side")
    parser.add_argument(
        "--scenes",
        nargs="*",
        default=list(FILE_SCENES),
        help="file scenes whose closed parts are used",
    )
    parser.add_argument("--builders", nargs="*", default=None, help="only these builders")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    print("meshes:", flush=True)
    meshes = procedural_meshes()
    meshes.update(file_meshes(args.scenes))
    sets, mesh_rows = {}, []
    for name, mesh in meshes.items():
        t0 = time.perf_counter()
        sets[name] = leak_rays.leak_rays(mesh, per_edge=args.per_edge, seed=11, name=name)
        print(
            f"  {name}: {mesh.n_triangles} triangles, {sets[name].n_rays} rays "
            f"({time.perf_counter() - t0:.1f} s)",
            flush=True,
        )
    sets = share_rays(sets, args.rays, seed=5)
    for name, s in sets.items():
        mesh = meshes[name]
        n_check = int(min(s.n_rays, max(2000, ORACLE_BUDGET / mesh.n_triangles)))
        pick = np.sort(np.random.default_rng(6).choice(s.n_rays, n_check, replace=False))
        ref = reference.oracle(mesh, s.rays.subset(pick))
        mesh_rows.append(
            {
                "mesh": name,
                "triangles": mesh.n_triangles,
                "rays": s.n_rays,
                "exact": float(s.exact.mean()),
                "outside": float(s.outside.mean()),
                "vertex": float((s.target_kind == 0).mean()),
                "dropped": s.dropped,
                "oracle_rays": n_check,
                "oracle_misses": int((ref.prim < 0).sum()),
            }
        )
    total_rays = sum(s.n_rays for s in sets.values())
    print(
        f"\n{'mesh':24s} {'triangles':>9s} {'rays':>8s} {'exact':>6s} {'outside':>7s} "
        f"{'at vertex':>9s} {'oracle checked':>14s} {'oracle misses':>13s}"
    )
    for r in mesh_rows:
        print(
            f"{r['mesh']:24s} {r['triangles']:9d} {r['rays']:8d} {r['exact']:6.1%} "
            f"{r['outside']:7.1%} {r['vertex']:9.1%} {r['oracle_rays']:14d} "
            f"{r['oracle_misses']:13d}"
        )
    print(f"{'total':24s} {'':9s} {total_rays:8d}\n", flush=True)

    from rayaccel import registry

    cases = leak_rays.leak_cases()
    if args.builders:
        cases = [c for c in cases if c[0] in args.builders]
    by_builder: dict[str, list[str]] = {}
    for builder, traversal in cases:
        by_builder.setdefault(builder, []).append(traversal)
    rows = []
    print(
        f"{'structure':9s} {'builder':20s} {'traversal':22s} {'query':7s} {'rays':>9s} "
        f"{'misses':>6s} {'exact misses':>12s} {'seconds':>8s}",
        flush=True,
    )
    for builder, traversals in by_builder.items():
        structure = registry.get(builder, "builder").structure
        accels = {}
        build_s = 0.0
        for name, mesh in meshes.items():
            t0 = time.perf_counter()
            accels[name] = rayaccel.build(mesh, builder)
            build_s += time.perf_counter() - t0
        for traversal in traversals:
            for query in ("closest", "any"):
                t0 = time.perf_counter()
                missed = exact_missed = 0
                first = None
                for name, s in sets.items():
                    idx = leak_rays.misses(accels[name], s.rays, traversal, query)
                    missed += idx.size
                    exact_missed += int(s.exact[idx].sum())
                    if idx.size and first is None:
                        k = idx[0]
                        first = {
                            "mesh": name,
                            "origin": s.rays.origin[k].tolist(),
                            "direction": s.rays.direction[k].tolist(),
                        }
                seconds = time.perf_counter() - t0
                rows.append(
                    {
                        "structure": structure,
                        "builder": builder,
                        "traversal": traversal,
                        "query": query,
                        "rays": total_rays,
                        "misses": missed,
                        "exact_misses": exact_missed,
                        "seconds": seconds,
                        "build_seconds": build_s,
                        "first": first,
                    }
                )
                print(
                    f"{structure:9s} {builder:20s} {traversal:22s} {query:7s} "
                    f"{total_rays:9d} {missed:6d} {exact_missed:12d} {seconds:8.1f}"
                    + (f"  first miss: {first}" if first else ""),
                    flush=True,
                )
        del accels
    traced = total_rays * len(rows)
    all_missed = sum(r["misses"] for r in rows)
    elapsed = time.perf_counter() - started
    print(
        f"\n{len(rows)} cases x {total_rays} rays = {traced} rays traced, "
        f"{all_missed} misses, {elapsed / 60:.1f} min",
        flush=True,
    )
    if args.json:
        args.json.write_text(
            json.dumps(
                {
                    "meshes": mesh_rows,
                    "cases": rows,
                    "rays_per_case": total_rays,
                    "rays_traced": traced,
                    "misses": all_missed,
                },
                indent=1,
            )
        )
    return 1 if all_missed else 0


if __name__ == "__main__":
    sys.exit(main())
