"""The teapot in a stadium at several scale disparities: which grids collapse, and when.

Builds each structure on ``teapot_in_stadium(stadium_scale=s)`` for every ``s`` and
traces the scene's preset camera (closest hit): Mrays/s (median of ``--repeats``
passes after an untimed one), triangle tests and cells (nodes for BVHs) per ray.
Every structure is checked against the brute-force oracle on 200 of the rays first.

    python benchmarks/bench_stadium.py --scales 1000 100 20
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SYSTEMS = (
    ("grid.uniform", "grid.dda"),
    ("grid.two_level", "grid.dda"),
    ("grid.irregular", "grid.dda"),
    ("bvh2.binned_sah", "bvh2.stack"),
)


def main(argv: list[str] | None = None) -> int:
    """Run the sweep and print a markdown table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", type=float, nargs="+", default=[1000.0, 100.0, 20.0])
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT / "tests"))
    import reference
    from rayaccel import build
    from rayaccel.rays.camera import PinholeCamera
    from rayaccel.scene.catalog import camera_preset
    from rayaccel.scene.procedural import teapot_in_stadium

    rays = PinholeCamera(
        width=args.width, height=args.height, **camera_preset("teapot-in-stadium")
    ).rays()
    check = reference.subsample(rays, 200)
    print("| stadium / teapot | system | Mrays/s | × `bvh2.stack` | triangle tests/ray "
          "| cells (nodes)/ray |")  # fmt: skip
    print("|---:|---|---:|---:|---:|---:|")
    for scale in args.scales:
        mesh = teapot_in_stadium(stadium_scale=scale)
        ref = reference.oracle(mesh, check)
        rows = []
        for key, traversal in SYSTEMS:
            accel = build(mesh, key)
            reference.assert_closest_matches(
                reference.tri9(mesh), check, accel.trace(check, traversal=traversal), ref, key
            )
            accel.trace(rays, traversal=traversal)
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                accel.trace(rays, traversal=traversal)
                times.append(time.perf_counter() - t0)
            stats = accel.trace(rays, traversal=traversal, stats=True).stats
            visits = stats["cells"] if stats["cells"].any() else stats["nodes"]
            speed = rays.origin.shape[0] / float(np.median(times)) / 1e6
            rows.append((key, traversal, speed, stats["prim_tests"].mean(), visits.mean()))
        bvh = rows[-1][2]
        for key, traversal, speed, tests, visits in rows:
            print(f"| {scale:g} | `{key} + {traversal}` | {speed:.2f} | {speed / bvh:.3f} "
                  f"| {tests:.0f} | {visits:.1f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
