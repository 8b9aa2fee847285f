"""The cost of ``precision="float64"``: float64 against float32 traversal, in one run.

For each scene the same vertices make a float32 mesh and a float64 one
(``TriangleMesh(..., precision="float64")``), each built with ``bvh2.binned_sah``; the
two trees have the same topology, the float64 one's boxes one float32 ulp wider. Both
trace the same primary rays of a pinhole camera framing the scene (float32 rays for the
float32 accel, the same values in float64 for the other), with ``bvh2.stack`` and
``bvh2.wide`` (4 and 8 wide). Each round traces every (traversal, precision) pair once,
interleaved so the noise of a shared machine hits both alike; the report is the median
over rounds after one warm-up round (compilation), and ``ratio`` is float64 Mrays/s over
float32 Mrays/s in the same run (tinybvh reports about 0.91 for its 4-wide BVH);
``ratio(min)`` compares the fastest rounds, the least disturbed on a shared machine. Hits
are compared before timing (the same triangle on all but a few rays). ``--pair
BUILDER:TRAVERSAL`` (repeatable) times other structures instead, e.g. ``kdtree.sah:
kdtree.stack`` or ``grid.uniform:grid.dda`` (a float64 kd-tree lists a few more
references, :mod:`rayaccel.kdtree.precision`).

    NUMBA_NUM_THREADS=2 RAYACCEL_SCENE_PATH=../shared/scenes \\
        python benchmarks/bench_float64.py sphereflake stanford-bunny --rounds 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numba
import numpy as np

import rayaccel
from rayaccel.errors import SceneFileError
from rayaccel.rays.camera import frame_bounds

DEFAULT_SCENES = ("sphereflake", "stanford-bunny")
BUILDER = "bvh2.binned_sah"
TRAVERSALS = (("bvh2.stack", {}), ("bvh2.wide", {"width": 4}), ("bvh2.wide", {"width": 8}))


def run_scene(name: str, args: argparse.Namespace) -> list[dict[str, object]]:
    try:
        scene = rayaccel.scenes.get(name)
    except (SceneFileError, KeyError, rayaccel.InvalidInputError) as exc:
        print(f"{name}: skipped ({exc})", file=sys.stderr)
        return []
    vertices = scene.vertices.astype(np.float64)
    pairs = [(BUILDER, key, options) for key, options in TRAVERSALS]
    if args.pair:
        pairs = [(*pair.split(":", 1), {}) for pair in args.pair]
    built: dict[str, dict[str, rayaccel.Accel]] = {}
    for builder, _, _ in pairs:
        if builder not in built:
            built[builder] = {
                p: rayaccel.build(
                    rayaccel.TriangleMesh(vertices, scene.faces, name, precision=p), builder
                )
                for p in ("float32", "float64")
            }
    lo, hi = (b.astype(np.float64) for b in scene.bounds())
    camera = frame_bounds(lo, hi, width=args.width, height=args.width)
    rays32 = camera.rays()
    rays = {"float32": rays32, "float64": rays32.astype("float64")}
    n = rays32.n_rays
    rows = []
    for builder, key, options in pairs:
        accels = built[builder]
        label = key + (f"[{options['width']}]" if options else "")
        hits = {p: accels[p].trace(rays[p], traversal=key, **options) for p in rays}
        differ = int((hits["float32"].prim != hits["float64"].prim).sum())
        if differ > max(n // 1000, 1):
            print(f"{name} {label}: {differ} of {n} hits differ; not timed", file=sys.stderr)
            continue
        times: dict[str, list[float]] = {"float32": [], "float64": []}
        batches = {
            p: [rays[p].subset(slice(b, b + args.batch)) for b in range(0, n, args.batch)]
            for p in rays
        }
        for round_ in range(args.rounds + 1):
            for p in ("float32", "float64"):
                start = time.perf_counter()
                for batch in batches[p]:
                    accels[p].trace(batch, traversal=key, **options)
                if round_:  # round 0 warms up
                    times[p].append(time.perf_counter() - start)
        mrays = {p: n / statistics.median(t) / 1e6 for p, t in times.items()}
        fastest = {p: min(t) for p, t in times.items()}
        rows.append(
            {
                "scene": name,
                "n_tris": scene.n_triangles,
                "traversal": label,
                "f32_mrays": mrays["float32"],
                "f64_mrays": mrays["float64"],
                "ratio": mrays["float64"] / mrays["float32"],
                "ratio_min": fastest["float32"] / fastest["float64"],
                "differ": differ,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="*", default=list(DEFAULT_SCENES))
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--width", type=int, default=512, help="camera width = height (rays)")
    parser.add_argument(
        "--batch",
        type=int,
        default=1 << 30,
        help="trace in batches of this many rays (below 4096: the serial kernels, no "
        "parallel launch, the steadiest timings on a loaded machine)",
    )
    parser.add_argument(
        "--pair",
        action="append",
        metavar="BUILDER:TRAVERSAL",
        help="time this builder and traversal instead of the bvh2 ones (repeatable)",
    )
    args = parser.parse_args(argv)
    print(
        f"threads: {numba.get_num_threads()}, rays per round: {args.width**2}, "
        f"batch: {min(args.batch, args.width**2)}"
    )
    print(f"{'scene':<18}{'tris':>9}  {'traversal':<14}{'f32 Mrays/s':>12}{'f64 Mrays/s':>12}"
          f"{'f64/f32':>9}{'(min)':>7}")  # fmt: skip
    for name in args.scenes:
        for row in run_scene(name, args):
            print(
                f"{row['scene']:<18}{row['n_tris']:>9}  {row['traversal']:<14}"
                f"{row['f32_mrays']:>12.2f}{row['f64_mrays']:>12.2f}{row['ratio']:>9.2f}"
                f"{row['ratio_min']:>7.2f}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
