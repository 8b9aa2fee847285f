"""Compile every CUDA traversal kernel to PTX for sm_90 with NVVM, no GPU (run by a test).

Runs in its own process with ``NUMBA_ENABLE_CUDASIM=0`` (the test process runs the
simulator). Prints one ``<builder> <traversal> <query> <stats> ok`` line per kernel and,
where ``ptxas`` is installed, assembles each closest-hit kernel and fails if it spills
registers to local memory. Exits non-zero on the first failure, or with :data:`NO_NVVM`
when NVVM is not installed.
"""

from __future__ import annotations

import sys

from rayaccel.cuda.report import KERNEL_CASES

#: Exit status when NVVM is absent (the test then skips, saying why).
NO_NVVM = 3

#: (builder, traversal) of every CUDA kernel (:data:`rayaccel.cuda.report.KERNEL_CASES`).
CASES = KERNEL_CASES


def main() -> int:
    try:
        from numba.cuda.cudadrv.nvvm import NVVM

        NVVM()
    except Exception as exc:
        print(f"NVVM not installed ({type(exc).__name__}); pip install 'rayaccel[gpu]'")
        return NO_NVVM
    import rayaccel as ra
    from rayaccel.cuda.report import compile_ptx, find_ptxas, ptxas_resources
    from rayaccel.scene import procedural

    mesh = procedural.cornell_box()
    for builder, traversal in CASES:
        accel = ra.build(mesh, builder)
        for query, stats in (("closest", False), ("any", False), ("closest", True)):
            ptx = compile_ptx(accel, traversal, query, stats)
            if ".entry" not in ptx or "sm_90" not in ptx:
                print(f"{builder} {traversal} {query} {stats} no kernel entry in the PTX")
                return 1
            print(f"{builder} {traversal} {query} {stats} ok", flush=True)
            if query == "closest" and not stats and find_ptxas() is not None:
                # What ptxas makes of it: registers in range, nothing spilled to local memory.
                used = ptxas_resources(ptx)
                print(f"{builder} {traversal} resources {used}", flush=True)
                if not 0 < used["registers"] <= 255 or used["spill_stores"]:
                    return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
