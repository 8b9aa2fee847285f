"""CUDA stand-ins for the few CPU helpers that do not compile for a GPU.

:mod:`rayaccel.cuda.retarget` compiles the CPU traversals' per-ray code for CUDA and
swaps each helper below for its stand-in (same arguments, same results):

- ``prefetch_row`` and ``keep_branch`` are hints to an x86 core (a cache prefetch, a
  branch the predictor should keep); a GPU hides latency by switching warps, so their
  stand-ins do nothing.
- ``slab_test2/4/8`` are explicit LLVM vector code; their stand-in runs the scalar
  robust slab test (:func:`rayaccel.kernels.aabb.ray_box_entry_py`) once per lane,
  which is what each lane of the vector code computes (the CPU tests check that).
- ``trailing_zeros`` (numba's ``cttz`` intrinsic) becomes ``ffs - 1``, the GPU's
  find-first-set.
- ``next_up``, ``as_real_like`` and ``edge_function`` choose their float32 or float64
  form through numba overloads of the CPU target; the GPU kernels trace float32 rays
  only, so their stand-ins are the float32 forms: ``nextafterf`` from libdevice (numpy's
  ``nextafter`` under the simulator), a
  float32 conversion, and the edge function in float64 (exact products of float32
  operands, so the watertight test stays exact with fused multiply-adds).
"""

from __future__ import annotations

import numpy as np
from numba import cuda
from numba.cpython.unsafe.numbers import trailing_zeros
from numba.cuda import config, libdevice

from rayaccel._jit import keep_branch, prefetch_row
from rayaccel.cuda.retarget import device_function, substitute
from rayaccel.kernels import aabb_wide, real
from rayaccel.kernels.aabb import ray_box_entry_py

INF32 = np.float32(np.inf)


@cuda.jit(device=True)
def no_prefetch(array, row):  # pragma: no cover - compiled for CUDA
    """Do nothing: a GPU hides memory latency by switching warps, not by prefetching."""
    return


@cuda.jit(device=True)
def no_branch_hint():  # pragma: no cover - compiled for CUDA
    """Do nothing: a GPU has no branch predictor to steer."""
    return


_ray_box_entry = device_function(ray_box_entry_py)


def _slab_lanes(lanes):
    """Return the device stand-in of ``slab_test<lanes>`` (scalar test per lane)."""

    def slab_test(
        box, row, near_x, far_x, near_y, far_y, near_z, far_z,
        ox, oy, oz, ix, iy, iz, t_lo, t_hi, out,
    ):  # fmt: skip
        mask = 0
        for lane in range(lanes):
            entry = _ray_box_entry(
                ox, oy, oz, ix, iy, iz,
                box[row, near_x + lane], box[row, near_y + lane], box[row, near_z + lane],
                box[row, far_x + lane], box[row, far_y + lane], box[row, far_z + lane],
                t_lo, t_hi,
            )  # fmt: skip
            out[lane] = entry
            if entry != INF32:
                mask |= 1 << lane
        return np.int32(mask)

    return cuda.jit(device=True)(slab_test)


def next_up_py(x):
    """Return the next float32 above ``x`` (NaN and +inf unchanged), as ``next_up``."""
    return libdevice.nextafterf(x, INF32)


def as_real_like_py(x, ref):
    """Return ``x`` as float32 (the GPU kernels trace float32 rays)."""
    return np.float32(x)


def edge_function_py(a, b, c, d):
    """``a*b - c*d`` in float64: exact products of float32 operands, as on the CPU."""
    return np.float64(a) * np.float64(b) - np.float64(c) * np.float64(d)


def trailing_zeros_py(x):
    """Index of the lowest set bit of ``x`` (``x != 0``), as numba's ``trailing_zeros``."""
    return cuda.ffs(x) - 1


def trailing_zeros_simulated(x):
    """:func:`trailing_zeros_py` in plain Python (the simulator has no ``ffs``)."""
    return (int(x) & -int(x)).bit_length() - 1


substitute(prefetch_row, no_prefetch)
substitute(
    trailing_zeros,
    cuda.jit(device=True)(trailing_zeros_simulated if config.ENABLE_CUDASIM else trailing_zeros_py),
)
substitute(keep_branch, no_branch_hint)
substitute(aabb_wide.slab_test2, _slab_lanes(2))
substitute(aabb_wide.slab_test4, _slab_lanes(4))
substitute(aabb_wide.slab_test8, _slab_lanes(8))
# The simulator runs device functions as Python, where libdevice has no body.
substitute(
    real.next_up, cuda.jit(device=True)(real.next_up if config.ENABLE_CUDASIM else next_up_py)
)
substitute(real.as_real_like, cuda.jit(device=True)(as_real_like_py))
substitute(real.edge_function, cuda.jit(device=True)(edge_function_py))
