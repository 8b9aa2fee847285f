"""Time this checkout's traversals against another git revision's, interleaved in one process.

The other revision's ``src/rayaccel`` is exported with ``git archive`` into a temporary
folder and imported under the name ``rayaccel_old``; both build the same scene with
the same builder and trace the same standard ray sets, round robin
(:func:`rayaccel.bench.harness.timed_round_robin`), so machine noise hits both alike.
Hits must be identical; the table gives each revision's median Mrays/s and their ratio.

    python benchmarks/compare_revisions.py --rev cc8fb08 --scenes staircase living_room \
        kitchen --traversals bvh2.stack bvh2.wide --threads 2 --repeats 7
"""

from __future__ import annotations

import argparse
import importlib
import io
import re
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numba
import numpy as np

import rayaccel
from rayaccel.bench.harness import timed_round_robin
from rayaccel.bench.raysets import standard_raysets

ROOT = Path(__file__).resolve().parents[1]


def import_revision(rev: str, into: Path) -> object:
    """Export ``rev``'s package as ``rayaccel_old`` under ``into`` and import it."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "--format=tar", rev, "src/rayaccel"],
        check=True, capture_output=True,
    ).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(into, filter="data")
    package = into / "rayaccel_old"
    (into / "src" / "rayaccel").rename(package)
    pattern = re.compile(r"\brayaccel(?=[.\s,)]|$)", re.MULTILINE)
    for path in package.rglob("*.py"):
        path.write_text(pattern.sub("rayaccel_old", path.read_text()))
    sys.path.insert(0, str(into))
    return importlib.import_module("rayaccel_old")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", required=True, help="git revision to compare against")
    parser.add_argument("--scenes", nargs="+", default=["teapot"])
    parser.add_argument("--builder", default="bvh2.binned_sah")
    parser.add_argument("--traversals", nargs="+", default=["bvh2.stack"])
    parser.add_argument("--kinds", nargs="+", default=["primary", "diffuse", "shadow"])
    parser.add_argument("--threads", type=int, default=numba.get_num_threads())
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--size", type=int, default=512, help="image side of the ray sets")
    args = parser.parse_args()
    numba.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        old = import_revision(args.rev, Path(tmp))
        print(f"new = working tree, old = {args.rev}; {args.threads} threads, "
              f"median of {args.repeats} interleaved rounds")
        print(f"{'scene':<14}{'traversal':<18}{'rays':<9}{'new Mrays/s':>12}"
              f"{'old Mrays/s':>12}{'new/old':>9}")
        for scene in args.scenes:
            mesh_new = rayaccel.scenes.get(scene)
            mesh_old = old.scenes.get(scene)  # type: ignore[attr-defined]
            accel_new = rayaccel.build(mesh_new, args.builder)
            accel_old = old.build(mesh_old, args.builder)  # type: ignore[attr-defined]
            sets = standard_raysets(mesh_new, scene, kinds=args.kinds, width=args.size,
                                    height=args.size, accel=accel_new)
            for traversal in args.traversals:
                for kind, rayset in sets.items():
                    rays = rayset.rays
                    rays_old = old.RayBatch(  # type: ignore[attr-defined]
                        rays.origin, rays.direction, rays.tmin, rays.tmax
                    )

                    def run_new(rays=rays, q=rayset.query, t=traversal, a=accel_new):
                        return a.trace(rays, query=q, traversal=t)

                    def run_old(rays=rays_old, q=rayset.query, t=traversal, a=accel_old):
                        return a.trace(rays, query=q, traversal=t)

                    seconds, (hits_new, hits_old) = timed_round_robin(
                        [run_new, run_old], args.repeats
                    )
                    if not (np.array_equal(hits_new.t, hits_old.t)
                            and np.array_equal(hits_new.prim, hits_old.prim)):
                        raise SystemExit(f"{scene} {traversal} {kind}: hits differ")
                    new, old_rate = (rays.n_rays / np.median(s) / 1e6 for s in seconds)
                    print(f"{scene:<14}{traversal:<18}{kind:<9}{new:>12.2f}{old_rate:>12.2f}"
                          f"{new / old_rate:>9.3f}", flush=True)


if __name__ == "__main__":
    main()
