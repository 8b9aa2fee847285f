"""GPU traversal kernels: Mrays/s per traversal, scene and ray set, against Warp and the CPU.

For every scene (``--scenes``: catalog names found through ``RAYACCEL_SCENE_PATH``, or
procedural ones) the standard ray sets (:func:`rayaccel.bench.raysets.standard_raysets`:
``--size`` primary rays from the scene's camera preset, one cosine bounce from every
hit, shadow rays to the preset's point light) are copied to the GPU once. Each CUDA
traversal (:data:`rayaccel.cuda.device.CUDA_TRAVERSALS`, the families chosen with
``--families``) then answers them through the public API with device arrays
(``accel.intersect(..., device="cuda")`` / ``occluded``; the layout is copied once by
``to_device()``): one untimed call compiles the kernel, then ``--repeats`` timed calls,
each ending in ``cuda.synchronize()``; the median counts. Beside them on the same rays:

- ``warp (GPU)``: NVIDIA Warp's ``mesh_query_ray`` / ``mesh_query_ray_anyhit`` in a
  Warp kernel on the same GPU (its own BVH), timed the same way (launch + synchronize);
- ``cpu bvh2.stack`` and ``cpu bvh2.wide``: the CPU kernels on every core of the
  machine the GPU sits in (the numpy rays, hits copied nowhere).

Every GPU answer is checked against the CPU's ``bvh2.stack`` on the same rays: the
number of rays whose hit/miss differs is reported (it must be 0). Each kernel's
registers, local memory per thread and occupancy come from the compiler
(:func:`rayaccel.cuda.report.kernel_resources`). The talk's table (constant-time
backtracking against stack and stackless traversals, Ylitie et al. / Binder & Keller
2016) is printed as ratios to ``bvh2.stack`` on the GPU. One JSON file of records
(``--out``), a Markdown table on stdout.

    RAYACCEL_SCENE_PATH=$SCENES python benchmarks/bench_gpu.py \
        --scenes staircase living_room kitchen --size 1024 768 --out gpu.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
import numpy as np

import rayaccel
from rayaccel.bench.raysets import standard_raysets
from rayaccel.cuda.device import CUDA_TRAVERSALS
from rayaccel.scene import catalog

#: The builder each family's traversals walk; the grid DDA runs on two structures.
STRUCTURES = {
    "bvh2": [("bvh2.binned_sah", [k for k in CUDA_TRAVERSALS if k.startswith("bvh2.")])],
    "kdtree": [("kdtree.sah", ["kdtree.stack", "kdtree.ropes", "kdtree.short_stack"])],
    "grid": [("grid.uniform", ["grid.dda"]), ("grid.two_level", ["grid.dda"])],
}


def median_seconds(call: Callable[[], Any], repeats: int, sync: Callable[[], None]) -> float:
    """Median wall time of ``repeats`` calls, each followed by ``sync()``; one untimed first."""
    call()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_cuda(
    accel: Any, traversal: str, query: str, rays: tuple[Any, ...], repeats: int
) -> tuple[float, np.ndarray]:
    """Median seconds of one query over device rays, and its hit mask (copied back)."""
    from numba import cuda

    o, d, lo, hi = rays

    def call() -> Any:
        if query == "any":
            return accel.occluded(o, d, lo, hi, traversal=traversal, device="cuda")
        return accel.intersect(o, d, lo, hi, traversal=traversal, device="cuda")

    seconds = median_seconds(call, repeats, cuda.synchronize)
    answer = call()
    hit = answer.copy_to_host() if query == "any" else answer.prim.copy_to_host() >= 0
    return seconds, hit


def resources_of(accel: Any, traversal: str, query: str) -> dict[str, Any]:
    """Registers, local memory and occupancy of the kernel ``traversal`` ran for ``query``."""
    from rayaccel.cuda.report import kernel_plan, kernel_resources
    from rayaccel.cuda.skeleton import BLOCK_THREADS, trace_kernel
    from rayaccel.queries import query_constant

    make_scratch, trace_rays, _ = kernel_plan(accel, traversal)
    kernel = trace_kernel(trace_rays, make_scratch, query_constant(query), False)
    try:
        return kernel_resources(kernel, BLOCK_THREADS)
    except Exception as exc:  # report it and keep timing
        return {"resources_error": f"{type(exc).__name__}: {exc}"}


def warp_gpu(mesh: Any) -> Any:
    """Return ``(trace(kind, rays) -> hit mask, sync)`` with Warp on ``cuda:0``, or None."""
    try:
        import warp as wp

        from rayaccel.bench import warp_kernels
    except Exception as exc:
        print(f"warp (GPU): unavailable ({type(exc).__name__}: {exc})", file=sys.stderr)
        return None
    wp.config.quiet = True
    wp.init()
    points = wp.array(mesh.vertices.astype(np.float32), dtype=wp.vec3, device="cuda:0")
    faces = wp.array(np.ravel(mesh.faces).astype(np.int32), dtype=wp.int32, device="cuda:0")
    handle = wp.Mesh(points=points, indices=faces)
    held: dict[int, Any] = {}

    def arrays(rays: Any) -> Any:
        if id(rays) not in held:
            held[id(rays)] = (
                wp.array(rays.origin, dtype=wp.vec3, device="cuda:0"),
                wp.array(rays.direction, dtype=wp.vec3, device="cuda:0"),
                wp.array(rays.tmax.astype(np.float32), dtype=wp.float32, device="cuda:0"),
                wp.empty(rays.n_rays, dtype=wp.float32, device="cuda:0"),
                wp.empty(rays.n_rays, dtype=wp.int32, device="cuda:0"),
            )
        return held[id(rays)]

    def trace(query: str, rays: Any) -> Any:
        o, d, tmax, t, prim = arrays(rays)
        if query == "any":
            wp.launch(warp_kernels.any_hits, dim=rays.n_rays, inputs=[handle.id, o, d, tmax],
                      outputs=[prim], device="cuda:0")  # fmt: skip
            return prim
        wp.launch(warp_kernels.closest_hits, dim=rays.n_rays, inputs=[handle.id, o, d, tmax],
                  outputs=[t, prim], device="cuda:0")  # fmt: skip
        return prim

    def mask(query: str, rays: Any) -> np.ndarray:
        prim = trace(query, rays).numpy()
        return prim != 0 if query == "any" else prim >= 0

    return trace, mask, lambda: wp.synchronize_device("cuda:0")


def bench_scene(name: str, args: argparse.Namespace, records: list[dict[str, Any]]) -> None:
    """Time every traversal and peer on one scene's ray sets (records appended)."""
    from numba import cuda

    mesh = catalog.get(name)
    width, height = args.size
    reference = rayaccel.build(mesh, "bvh2.binned_sah")
    sets = standard_raysets(mesh, name, width=width, height=height, accel=reference)
    print(f"{name}: {mesh.n_triangles} triangles, "
          + ", ".join(f"{k} {s.n_rays}" for k, s in sets.items()), file=sys.stderr)  # fmt: skip
    truth = {k: reference.trace(s.rays, query=s.query).prim >= 0 for k, s in sets.items()}
    on_gpu = {}
    for kind, s in sets.items():
        columns = (s.rays.origin, s.rays.direction, s.rays.tmin, s.rays.tmax)
        on_gpu[kind] = tuple(cuda.to_device(a) for a in columns)

    def record(kind: str, who: str, seconds: float, mismatches: int, **extra: Any) -> None:
        n = sets[kind].n_rays
        records.append({"scene": name, "rays": kind, "traversal": who, "n_rays": n,
                        "seconds": seconds, "mrays_per_s": n / seconds / 1e6,
                        "mismatches": mismatches, **extra})  # fmt: skip
        print(f"  {kind:8s} {who:28s} {n / seconds / 1e6:9.1f} Mrays/s  "
              f"mismatches {mismatches}", file=sys.stderr, flush=True)  # fmt: skip

    for family in args.families:
        for builder, traversals in STRUCTURES[family]:
            start = time.perf_counter()
            accel = rayaccel.build(mesh, builder)
            build_s = time.perf_counter() - start
            for traversal in traversals:
                label = traversal if family != "grid" else f"{traversal} ({builder})"
                accel.to_device(traversal)
                for kind, s in sets.items():
                    seconds, hit = time_cuda(accel, traversal, s.query, on_gpu[kind], args.repeats)
                    record(kind, label, seconds, int(np.count_nonzero(hit != truth[kind])),
                           build_s=build_s, **resources_of(accel, traversal, s.query))  # fmt: skip
    peer = warp_gpu(mesh) if "warp" in args.peers else None
    if peer is not None:
        trace, mask, warp_sync = peer
        for kind, s in sets.items():
            try:
                seconds = median_seconds(
                    lambda s=s: trace(s.query, s.rays), args.repeats, warp_sync
                )
                wrong = int(np.count_nonzero(mask(s.query, s.rays) != truth[kind]))
            except Exception as exc:  # a Warp without this query: say so, keep going
                print(f"  warp (GPU) {kind}: {type(exc).__name__}: {exc}", file=sys.stderr)
                continue
            record(kind, "warp (GPU)", seconds, wrong)
    if "cpu" in args.peers:
        for traversal in ("bvh2.stack", "bvh2.wide"):
            for kind, s in sets.items():
                seconds = median_seconds(
                    lambda s=s, t=traversal: reference.trace(s.rays, query=s.query, traversal=t),
                    max(1, args.repeats // 3),
                    lambda: None,
                )
                got = reference.trace(s.rays, query=s.query, traversal=traversal).prim >= 0
                record(kind, f"cpu {traversal} ({numba.get_num_threads()} threads)", seconds,
                       int(np.count_nonzero(got != truth[kind])))  # fmt: skip


def table(records: list[dict[str, Any]]) -> str:
    """Return Markdown: Mrays/s and the ratio to the GPU's ``bvh2.stack`` per scene and rays."""
    lines = [
        "| scene | rays | traversal | Mrays/s | × gpu bvh2.stack | mismatches | regs | local B "
        "| occupancy |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    base = {(r["scene"], r["rays"]): r["mrays_per_s"] for r in records
            if r["traversal"] == "bvh2.stack"}  # fmt: skip
    for r in records:
        ratio = (
            r["mrays_per_s"] / base[(r["scene"], r["rays"])]
            if (r["scene"], r["rays"]) in base
            else float("nan")
        )
        regs = r.get("registers", "")
        local = r.get("local_bytes", "")
        occ = f"{r['occupancy']:.2f}" if "occupancy" in r else ""
        lines.append(f"| {r['scene']} | {r['rays']} | {r['traversal']} | {r['mrays_per_s']:.1f} "
                     f"| {ratio:.2f} | {r['mismatches']} | {regs} | {local} | {occ} |")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box"])
    parser.add_argument("--size", nargs=2, type=int, default=[1024, 768], metavar=("W", "H"))
    parser.add_argument("--families", nargs="+", default=["bvh2", "kdtree", "grid"],
                        choices=sorted(STRUCTURES))  # fmt: skip
    parser.add_argument("--peers", nargs="*", default=["warp", "cpu"], choices=["warp", "cpu"])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    from numba import cuda

    name = getattr(cuda.get_current_device(), "name", "numba's CUDA simulator")
    print(f"GPU: {name.decode() if isinstance(name, bytes) else name}, numba {numba.__version__}",
          file=sys.stderr)  # fmt: skip
    records: list[dict[str, Any]] = []
    for name in args.scenes:
        bench_scene(name, args, records)
        if args.out:
            partial = args.out.with_suffix(".partial")
            partial.write_text(json.dumps(records, indent=1))
            partial.replace(args.out)
    print(table(records))
    return 0


if __name__ == "__main__":
    sys.exit(main())
