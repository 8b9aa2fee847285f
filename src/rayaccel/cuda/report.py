"""What the CUDA compiler made of each traversal kernel: PTX without a GPU, resources with one.

:func:`kernel_plan` records, without launching anything, the per-ray body, scratch
maker and layout arrays a traversal would launch (:data:`rayaccel.trace.run.TRACE_TARGET`
set to a recorder). :func:`compile_ptx` compiles that kernel to PTX for a given
compute capability with NVVM alone, no GPU needed (the CI-free check that every body
in :data:`rayaccel.cuda.device.CUDA_TRAVERSALS` types and lowers for the real target, not
only under the simulator). :func:`kernel_resources` reads, on a GPU, the registers,
local memory and occupancy the compiled kernel gets.
"""

from __future__ import annotations

import types
from typing import Any

import numba
import numpy as np

from rayaccel.queries import query_constant
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.trace.run import TRACE_TARGET

#: ``(builder, traversal)`` of every CUDA kernel: each traversal of
#: :data:`rayaccel.cuda.device.CUDA_TRAVERSALS` on its structure's default tree, and the
#: grid walks on every grid class they handle (each class has its own layout and kernel).
KERNEL_CASES = [
    ("bvh2.binned_sah", "bvh2.stack"),
    ("bvh2.binned_sah", "bvh2.restart_trail"),
    ("bvh2.binned_sah", "bvh2.parent_link"),
    ("bvh2.binned_sah", "bvh2.bitstack"),
    ("bvh2.binned_sah", "bvh2.perfect_hash"),
    ("kdtree.sah", "kdtree.stack"),
    ("kdtree.sah", "kdtree.ropes"),
    ("kdtree.sah", "kdtree.short_stack"),
    ("kdtree.sah", "kdtree.restart"),
    ("kdtree.sah", "kdtree.backtrack"),
    ("grid.uniform", "grid.dda"),
    ("grid.two_level", "grid.dda"),
    ("grid.irregular", "grid.dda"),
    ("grid.macro_regions", "grid.skip"),
    ("grid.distance", "grid.skip"),
    ("grid.mipmap", "grid.skip"),
]


class _Recorder:
    """A trace target that records the launch instead of running it."""

    def __init__(self) -> None:
        self.plan: tuple[Any, Any] | None = None

    def run(
        self, kernel_for: Any, layout_arrays: Any, rays: Any, query: str, stats: bool, hint: str
    ) -> HitBatch:
        self.plan = (kernel_for, layout_arrays)
        return HitBatch.empty(rays.n_rays)


def kernel_plan(accel: Any, traversal: str, **options: Any) -> tuple[Any, Any, Any]:
    """Return ``(make_scratch, trace_rays, layout_arrays)`` of ``traversal`` on ``accel``."""
    from rayaccel._variant import REGISTRY
    from rayaccel.cuda.device import body_of

    # The accel was built through the registry, so every variant module is loaded.
    variant = REGISTRY[traversal]
    recorder = _Recorder()
    token = TRACE_TARGET.set(recorder)
    try:
        rays = RayBatch(np.zeros((1, 3)), np.ones((1, 3)))
        variant.func(accel.structure, accel.mesh, rays, query="closest", stats=False,
                     options=variant.make_options(options), cache=accel._cache)  # fmt: skip
    finally:
        TRACE_TARGET.reset(token)
    assert recorder.plan is not None, f"{traversal} launched nothing"
    kernel_for, layout = recorder.plan
    make_scratch, trace_rays = body_of(kernel_for)
    return make_scratch, trace_rays, layout


def kernel_signature(layout: Any) -> Any:
    """Return the numba signature of a trace kernel over ``layout`` (float32 rays)."""
    f32_2d = numba.types.float32[:, ::1]
    f32_1d = numba.types.float32[::1]
    i32_1d = numba.types.int32[::1]
    return numba.types.void(
        numba.typeof(layout), f32_2d, f32_2d, f32_1d, f32_1d,
        f32_1d, i32_1d, f32_1d, f32_1d, numba.types.int32[:, ::1], i32_1d, i32_1d,
    )  # fmt: skip


def compile_ptx(
    accel: Any, traversal: str, query: str = "closest", stats: bool = False,
    cc: tuple[int, int] = (9, 0), **options: Any,
) -> str:  # fmt: skip
    """Return the PTX of ``traversal``'s CUDA kernel for compute capability ``cc``.

    Needs NVVM (``pip install "cuda-toolkit[nvvm,nvrtc]"``) but no GPU: device functions
    are compiled for ``cc`` instead of the current device's.
    """
    from numba import cuda
    from numba.cuda import dispatcher

    from rayaccel.cuda.skeleton import trace_kernel

    make_scratch, trace_rays, layout = kernel_plan(accel, traversal, **options)
    kernel = trace_kernel(trace_rays, make_scratch, query_constant(query), stats)
    current = dispatcher.get_current_device
    dispatcher.get_current_device = lambda: types.SimpleNamespace(compute_capability=cc)
    try:
        ptx, _ = cuda.compile_ptx(kernel.py_func, kernel_signature(layout), cc=cc)
    finally:
        dispatcher.get_current_device = current
    return str(ptx)


def kernel_resources(kernel: Any, block_threads: int) -> dict[str, Any]:
    """Return registers, local memory per thread and occupancy of a compiled kernel.

    Empty under the simulator, which compiles nothing.
    """
    from numba import cuda
    from numba.cuda import config

    if config.ENABLE_CUDASIM:
        return {}
    device = cuda.get_current_device()
    resources: dict[str, Any] = {
        "registers": int(kernel.get_regs_per_thread()),
        "local_bytes": int(kernel.get_local_mem_per_thread()),
        "shared_bytes": int(kernel.get_shared_mem_per_block()),
    }
    compiled = next(iter(kernel.overloads.values()))
    try:
        blocks = int(compiled.max_cooperative_grid_blocks(block_threads))
    except Exception:
        return resources
    sms = int(device.MULTIPROCESSOR_COUNT)
    per_sm = int(device.MAX_THREADS_PER_MULTI_PROCESSOR)
    resources["blocks_per_sm"] = blocks / sms
    resources["occupancy"] = blocks / sms * block_threads / per_sm
    return resources


#: Hopper's per-multiprocessor limits (sm_90, CUDA C Programming Guide, table 21).
SM90_REGISTERS = 65536
SM90_MAX_WARPS = 64
SM90_MAX_BLOCKS = 32
#: Registers are allocated per warp in units of this many.
REGISTER_UNIT = 256


def find_ptxas() -> str | None:
    """Return the ``ptxas`` of the pip CUDA toolkit (``cuda-toolkit[nvcc]``), else the PATH's.

    The pip toolkit's comes first: it matches the pip NVVM that wrote the PTX (an older
    system ``ptxas`` rejects a newer PTX version).
    """
    import glob
    import shutil
    import site

    for root in [*site.getsitepackages(), site.getusersitepackages()]:
        hits = sorted(glob.glob(f"{root}/nvidia/*/bin/ptxas"))
        if hits:
            return hits[-1]
    return shutil.which("ptxas")


def ptxas_resources(ptx: str, arch: str = "sm_90", block_threads: int = 128) -> dict[str, Any]:
    """Assemble ``ptx`` with ``ptxas -v`` and return its registers, stack, spills, occupancy.

    ``occupancy`` is the resident fraction of the multiprocessor's 64 warps that blocks of
    ``block_threads`` reach with that many registers per thread (the register file is the
    limit these kernels meet; they use no shared memory).
    """
    import re
    import subprocess
    import tempfile

    ptxas = find_ptxas()
    if ptxas is None:
        raise FileNotFoundError("ptxas not found: pip install 'rayaccel[gpu]'")
    with tempfile.TemporaryDirectory() as folder:
        source = f"{folder}/kernel.ptx"
        with open(source, "w") as handle:
            handle.write(ptx)
        run = subprocess.run(
            [ptxas, "-v", f"-arch={arch}", source, "-o", f"{folder}/kernel.cubin"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
    log = run.stderr + run.stdout
    registers = int(re.search(r"Used (\d+) registers", log).group(1))  # type: ignore[union-attr]
    frame = re.search(
        r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", log
    )
    stack, spill_stores, spill_loads = (int(g) for g in frame.groups()) if frame else (0, 0, 0)
    warps = block_threads // 32
    per_warp = -(-registers * 32 // REGISTER_UNIT) * REGISTER_UNIT
    blocks = min(SM90_REGISTERS // (per_warp * warps), SM90_MAX_WARPS // warps, SM90_MAX_BLOCKS)
    return {
        "registers": registers,
        "stack_bytes": stack,
        "spill_stores": spill_stores,
        "spill_loads": spill_loads,
        "occupancy": blocks * warps / SM90_MAX_WARPS,
    }
