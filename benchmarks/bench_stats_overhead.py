"""Measure what per-ray statistics cost: plain vs counters-stripped vs instrumented traversal.

The plain ``bvh2.stack`` kernel is the ``with_stats=False`` variant of one factory
whose counter code sits behind ``if with_stats:`` blocks that numba prunes at compile
time. To show that this costs nothing, this script builds a *third* kernel from the
module's source with every ``if with_stats:`` block deleted from the syntax tree (the
counters "removed altogether"), and times the three on the same rays, interleaved,
taking the best of ``--repeats`` runs of each::

    python benchmarks/bench_stats_overhead.py staircase --threads 2

Prints Mrays/s and the ratios plain/stripped and stats/plain.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import inspect
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

import rayaccel as ra
from rayaccel.bvh.traverse import stack as traverse_stack
from rayaccel.rays.bounce import diffuse_rays
from rayaccel.rays.camera import frame_bounds, from_preset
from rayaccel.trace.run import run_trace


class _StripStats(ast.NodeTransformer):
    """Delete every ``if with_stats: ...`` statement (they have no ``else``)."""

    def visit_If(self, node: ast.If) -> ast.AST | None:
        self.generic_visit(node)
        if isinstance(node.test, ast.Name) and node.test.id == "with_stats" and not node.orelse:
            return None
        return node


def stripped_module(folder: Path):
    """Import a copy of ``traverse_stack`` whose kernels contain no counter code at all."""
    tree = _StripStats().visit(ast.parse(inspect.getsource(traverse_stack)))
    ast.fix_missing_locations(tree)
    # Registering the same key twice would clash: drop the decorated public wrapper.
    tree.body = [
        node
        for node in tree.body
        if not (isinstance(node, ast.FunctionDef) and node.name == "trace_bvh2_stack")
    ]
    path = folder / "traverse_stack_stripped.py"
    path.write_text(ast.unparse(tree))
    spec = importlib.util.spec_from_file_location("traverse_stack_stripped", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", nargs="?", default="teapot")
    parser.add_argument("--threads", type=int, default=numba.config.NUMBA_NUM_THREADS)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--size", type=int, default=384, help="image width and height")
    args = parser.parse_args()
    numba.set_num_threads(args.threads)

    mesh = ra.scenes.get(args.scene)
    preset = ra.scenes.camera_preset(args.scene)
    camera = (
        from_preset(preset, args.size, args.size)
        if preset
        else frame_bounds(*mesh.bounds(), width=args.size, height=args.size)
    )
    primary = camera.rays()
    accel = ra.build(mesh, "bvh2.binned_sah")
    hits = accel.trace(primary)
    diffuse, _ = diffuse_rays(primary, hits, mesh.normals(), seed=1)
    pairs = traverse_stack.stack_layout(accel.structure, mesh, None)

    with tempfile.TemporaryDirectory() as folder:
        stripped = stripped_module(Path(folder))
        kernels = {
            "plain": lambda q, s, p: traverse_stack.trace_kernel(q, False, p),
            "stripped": lambda q, s, p: stripped.trace_kernel(q, False, p),
            "stats": lambda q, s, p: traverse_stack.trace_kernel(q, True, p),
        }
        print(
            f"{args.scene}: {mesh.n_triangles} triangles, {args.threads} threads, "
            f"best of {args.repeats}"
        )
        for label, rays in (("primary", primary), ("diffuse", diffuse)):
            best = {}
            results = {}
            for _ in range(args.repeats):
                for name, kernel_for in kernels.items():
                    start = time.perf_counter()
                    hit = run_trace(
                        kernel_for, pairs.arrays(), rays, "closest", name == "stats"
                    )
                    elapsed = time.perf_counter() - start
                    best[name] = min(best.get(name, np.inf), elapsed)
                    results[name] = hit
            same = all(
                np.array_equal(results[name].prim, results["plain"].prim)
                and np.array_equal(results[name].t, results["plain"].t)
                for name in results
            )
            rates = {name: rays.n_rays / t / 1e6 for name, t in best.items()}
            print(
                f"  {label:8s} Mrays/s stripped {rates['stripped']:.2f}  plain {rates['plain']:.2f}"
                f"  stats {rates['stats']:.2f}  | plain/stripped time "
                f"{best['plain'] / best['stripped']:.3f}  stats/plain time "
                f"{best['stats'] / best['plain']:.3f}  identical hits: {same}"
            )


if __name__ == "__main__":
    sys.exit(main())
