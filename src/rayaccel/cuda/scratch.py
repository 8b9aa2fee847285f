"""Per-thread scratch of the CUDA traversals: the CPU workers' arrays, as local memory.

A CPU worker makes its scratch once with ``np.empty`` of a size read from the layout
(:mod:`rayaccel.trace.skeleton`); a CUDA thread cannot allocate, so each traversal
that needs scratch gets a device stand-in here that makes ``cuda.local.array`` of a
compile-time size, at least as large as any size the layout can ask for (the wrapper
checks run-time sizes against these caps before a launch, see
:mod:`rayaccel.cuda.traversals`). The stand-ins are inlined at numba IR level
(``inline="always"``), so the local arrays live in the kernel's own frame.
Traversals whose scratch is ``0`` (parent links, bitstack, perfect hash) compile their
CPU maker as it is.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import cuda

from rayaccel.bvh.layouts.bvh2 import STACK_SIZE as BVH_STACK_SIZE
from rayaccel.bvh.traverse import restart_trail, stack
from rayaccel.grid.traverse import walk
from rayaccel.grid.traverse.dda import MAX_MAILBOX
from rayaccel.kdtree.layouts.kdtree import STACK_SIZE as KD_STACK_SIZE
from rayaccel.kdtree.traverse import stack as kd_stack
from rayaccel.kdtree.traverse import stackless

#: The largest ``short_stack`` of ``bvh2.restart_trail`` a GPU thread holds.
MAX_SHORT_STACK = 16


def bvh2_stack_scratch_py(bvh):
    """Make ``bvh2.stack``'s reference, count and entry distance stacks and two lane distances."""
    stack_ref = cuda.local.array(BVH_STACK_SIZE, np.int32)
    stack_count = cuda.local.array(BVH_STACK_SIZE, np.int32)
    stack_t = cuda.local.array(BVH_STACK_SIZE, np.float32)
    lane_t = cuda.local.array(2, np.float32)
    return stack_ref, stack_count, stack_t, lane_t


def restart_trail_scratch_py(bvh):
    """Make ``bvh2.restart_trail``'s short stack (far child, entry distance, level)."""
    ss_ref = cuda.local.array(MAX_SHORT_STACK, np.int32)
    ss_t = cuda.local.array(MAX_SHORT_STACK, np.float32)
    ss_level = cuda.local.array(MAX_SHORT_STACK, np.int64)
    return ss_ref, ss_t, ss_level


def kd_ring_scratch_py(kd):
    """Make the kd-tree walks' stack or ring of (node, segment start, segment end)."""
    ring_node = cuda.local.array(KD_STACK_SIZE, np.int32)
    ring_tn = cuda.local.array(KD_STACK_SIZE, np.float32)
    ring_tf = cuda.local.array(KD_STACK_SIZE, np.float32)
    return ring_node, ring_tn, ring_tf


def mailbox_scratch_py(grid):
    """Make the grid walks' ring mailbox of recently tested primitive ids."""
    return cuda.local.array(MAX_MAILBOX, np.int32)


#: CPU scratch maker -> the Python source of its CUDA stand-in.
_STAND_INS: dict[int, Any] = {
    id(stack.make_scratch): bvh2_stack_scratch_py,
    id(restart_trail.make_scratch): restart_trail_scratch_py,
    id(kd_stack.make_scratch): kd_ring_scratch_py,
    id(stackless.make_scratch): kd_ring_scratch_py,
    id(walk.make_mailbox): mailbox_scratch_py,
}

_COMPILED: dict[int, Any] = {}


def device_scratch(make_scratch: Any) -> Any:
    """Return the inlined CUDA device function that makes a thread's scratch."""
    from rayaccel.cuda.retarget import python_function

    key = id(make_scratch)
    if key not in _COMPILED:
        source = _STAND_INS.get(key, python_function(make_scratch))
        _COMPILED[key] = cuda.jit(device=True, inline="always")(source)
    return _COMPILED[key]


def check_capacity(make_scratch: Any, layout_arrays: Any) -> None:
    """Raise if the layout asks for more scratch than a GPU thread holds (see the caps above)."""
    from rayaccel.errors import InvalidInputError

    is_trail = id(make_scratch) == id(restart_trail.make_scratch)
    if is_trail and int(layout_arrays.short_stack) > MAX_SHORT_STACK:
        raise InvalidInputError(
            f"bvh2.restart_trail on CUDA: short_stack must be at most {MAX_SHORT_STACK}, "
            f"got {int(layout_arrays.short_stack)}"
        )
