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
    from rayaccel import registry
    from rayaccel.cuda.device import body_of

    variant = registry.get(traversal, "traversal")
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
