"""The CUDA kernel every traversal runs in: persistent warps over a shared ray counter.

The GPU counterpart of :mod:`rayaccel.trace.skeleton`, after Aila & Laine 2009
("Understanding the Efficiency of Ray Traversal on GPUs", §4 persistent threads):
the grid holds only as many warps as the GPU keeps resident, and each warp takes the
next 32 rays from a global counter (lane 0 adds 32 atomically and shares the base
with ``shfl_sync``) whenever all its lanes are done, so a warp of long rays never
holds back a block, launching costs nothing per ray, and the 32 lanes of a warp trace
32 consecutive (coherent) rays. numba's CUDA simulator has no warp shuffles; under it
each thread takes its next ray from the counter alone (:func:`take_rays`), which
changes only which thread traces which ray. Each lane runs the
traversal's CPU per-ray body on its ray, compiled for CUDA by
:func:`rayaccel.cuda.retarget.device_function` (one source, two targets), with its
scratch made once per thread in local memory (:mod:`rayaccel.cuda.scratch`).

``query`` and ``with_stats`` are compile-time constants of each kernel, as on the
CPU; rays that overflow a stack add to ``overflow[0]``.
"""

from __future__ import annotations

import functools
from typing import Any

from numba import cuda
from numba.cuda import config

from rayaccel.cuda.retarget import device_function
from rayaccel.cuda.scratch import device_scratch

WARP_SIZE = 32
FULL_MASK = 0xFFFFFFFF
#: Threads per block of the persistent kernels.
BLOCK_THREADS = 128


def _take_rays_warp(work, lane):
    """Lane 0 takes the warp's next 32 rays; every lane gets its ray (warp-synchronous)."""
    base = 0
    if lane == 0:
        base = cuda.atomic.add(work, 0, WARP_SIZE)
    base = cuda.shfl_sync(FULL_MASK, base, 0)
    return base, base + lane


def _take_rays_thread(work, lane):
    """Take one ray for this thread alone (the simulator has no warp shuffles)."""
    ray = cuda.atomic.add(work, 0, 1)
    return ray, ray


#: ``take_rays(work, lane) -> (first ray of the batch, this thread's ray)``.
take_rays = cuda.jit(device=True)(_take_rays_thread if config.ENABLE_CUDASIM else _take_rays_warp)


@functools.cache
def trace_kernel(trace_rays: Any, make_scratch: Any, query: int, with_stats: bool) -> Any:
    """Return the CUDA kernel running ``trace_rays`` (a CPU body) for one query and stats flag.

    ``kernel[blocks, BLOCK_THREADS](layout, origin, direction, tmin, tmax, hit_t, hit_prim,
    hit_u, hit_v, counters, work, overflow)``: ``work`` is a one-element int32 counter
    starting at 0, ``overflow`` a one-element int32 count of rays that overflowed.
    """
    body = device_function(trace_rays)
    scratch_for = device_scratch(make_scratch)

    @cuda.jit
    def kernel(
        layout, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v, counters,
        work, overflow,
    ):  # fmt: skip
        scratch = scratch_for(layout)
        n_rays = origin.shape[0]
        lane = cuda.laneid
        while True:
            first, r = take_rays(work, lane)
            if first >= n_rays:
                return
            if r < n_rays:
                lost = body(
                    layout, scratch, origin, direction, tmin, tmax, r, r + 1,
                    hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
                )  # fmt: skip
                if lost > 0:
                    cuda.atomic.add(overflow, 0, lost)

    return kernel


@cuda.jit
def reset_hits(hit_t, hit_prim, hit_u, hit_v, counters):  # pragma: no cover - CUDA
    """Start every ray as a miss and zero its counters (the bodies store hits only)."""
    r = cuda.grid(1)
    if r < hit_t.shape[0]:
        hit_t[r] = float("inf")
        hit_prim[r] = -1
        hit_u[r] = 0.0
        hit_v[r] = 0.0
        if counters.shape[0] > r:
            for k in range(counters.shape[1]):
                counters[r, k] = 0


@cuda.jit
def fill(out, value):  # pragma: no cover - CUDA
    """``out[:] = value`` on the device (per-ray tmin/tmax from a scalar)."""
    r = cuda.grid(1)
    if r < out.shape[0]:
        out[r] = value


@cuda.jit
def hit_mask(hit_prim, out):  # pragma: no cover - CUDA
    """``out = hit_prim >= 0`` on the device (``occluded`` with device arrays)."""
    r = cuda.grid(1)
    if r < out.shape[0]:
        out[r] = hit_prim[r] >= 0


def blocks_for(n_rays: int) -> int:
    """Blocks of a persistent launch: enough to fill every multiprocessor, fewer for small batches.

    A multiprocessor keeps at most 2048 threads resident, so ``2048 / BLOCK_THREADS``
    blocks per multiprocessor fill the GPU (fewer fit when a kernel needs many
    registers; the extra blocks then start late, find the counter exhausted and exit).
    """
    needed = max(1, -(-n_rays // BLOCK_THREADS))
    device = cuda.get_current_device()
    resident = int(getattr(device, "MULTIPROCESSOR_COUNT", 1)) * (2048 // BLOCK_THREADS)
    return max(1, min(needed, resident))
