"""Registers, local memory (stack frame, spills) and occupancy of every CUDA traversal kernel.

Compiles each kernel of :data:`rayaccel.cuda.report.KERNEL_CASES` to PTX for sm_90
with NVVM and assembles it with ``ptxas -v`` (:func:`rayaccel.cuda.report.ptxas_resources`):
no GPU needed, only the pip CUDA toolkit of the ``gpu`` extra (``pip install 'rayaccel[gpu]'``).
Occupancy is what the register count allows for blocks of 128 threads on a Hopper
multiprocessor. Prints a Markdown table.

    NUMBA_ENABLE_CUDASIM=0 python benchmarks/gpu_kernel_resources.py
"""

from __future__ import annotations

import sys

import rayaccel
from rayaccel.cuda.report import KERNEL_CASES, compile_ptx, ptxas_resources
from rayaccel.cuda.skeleton import BLOCK_THREADS
from rayaccel.scene import procedural


def main() -> int:
    mesh = procedural.cornell_box()
    print("| kernel | query | registers | stack B | spill st/ld B | occupancy |")
    print("|---|---|---:|---:|---:|---:|")
    for builder, traversal in KERNEL_CASES:
        accel = rayaccel.build(mesh, builder)
        label = traversal if not builder.startswith("grid") else f"{traversal} ({builder})"
        for query in ("closest", "any"):
            r = ptxas_resources(compile_ptx(accel, traversal, query), block_threads=BLOCK_THREADS)
            spills = f"{r['spill_stores']}/{r['spill_loads']}"
            print(f"| {label} | {query} | {r['registers']} | {r['stack_bytes']} | {spills} "
                  f"| {r['occupancy']:.2f} |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
