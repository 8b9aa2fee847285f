"""The top-down scheduler shared by the SAH builders (madmann91/bvh's ``top_down_sah_builder.h``).

Every top-down builder runs the same loop; only the split function differs. A work
item is a node of the node pool with its reference range ``[begin, end)``, the
slots it may grow into (``cap``, for spatial splits that duplicate references), its
depth and a six-float item box the split function carries down (binned SAH: the
doubled-centroid box). The loop pops an item and

1. defers it to the frontier when it holds fewer than ``stop_size`` references;
2. makes it a leaf when it holds at most one reference;
3. asks the split function for its best split, ``(cost, axis, pos)``
   (:func:`~rayaccel.bvh.builders.split_binned.binned_try_split`,
   :func:`~rayaccel.bvh.builders.split_sweep.sweep_try_split`,
   :func:`~rayaccel.bvh.builders.split_spatial.spatial_try_split`); the depth
   bound (:func:`~rayaccel.bvh.builders.common.depth_forces_median`) is passed in
   as ``forced``;
4. makes it a leaf when it is small enough (``max_leaf_size``) and no split beats
   ``C_prim · N``;
5. otherwise allocates the two children as an adjacent pair, lets the split
   function partition the references and write the children's boxes
   (``*_apply_split``, which may also cut at the median), and pushes the right child
   then the left, so pairs are allocated in the depth-first order in which
   :func:`~rayaccel.bvh.builders.common.compact_to_canonical` walks them.

Parallelism (STYLE §4.5): :func:`build_top_down` runs the loop serially from the
root with a ``stop_size``, then builds the deferred subtrees concurrently
(:func:`build_frontier`): each gets a block of ``2·(cap − begin) − 2`` pool slots
reserved by a prefix sum in reference order, and threads take the subtrees largest
first from a shared counter, so the pool does not depend on the thread count. A
builder may instead produce the frontier itself (``bvh2.binned_sah`` splits its large
nodes level by level with all threads binning each node).

Split kinds are compile-time constants (:data:`BINNED`, :data:`SWEEP`,
:data:`SPATIAL`): the kernels are ``functools.cache``-d factories over the kind that
branch to the split module's inline functions, so the dead branches are pruned and
each kind compiles to its own specialised loop (STYLE §4.3: no dispatcher is
captured, which would defeat the on-disk cache). Every split kind takes the same
arguments: ``refs`` (what is partitioned), ``aux`` (a tuple of read-only arrays),
``params`` (a NamedTuple with at least ``max_leaf_size`` and ``intersection_cost``)
and the workspace its ``*_workspace`` function allocates once per subtree. The serial
kernel is compiled with ``cpu_kernel(simplify=True)``: without copy propagation, the
array arguments of the two inlined split calls per node cost reference-count updates
on every node.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numba
import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.builders.common import depth_forces_median
from rayaccel.bvh.builders.split_binned import (
    binned_apply_split,
    binned_try_split,
    binned_workspace,
)
from rayaccel.bvh.builders.split_spatial import (
    spatial_apply_split,
    spatial_try_split,
    spatial_workspace,
)
from rayaccel.bvh.builders.split_sweep import sweep_apply_split, sweep_try_split, sweep_workspace
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.dtypes import FloatArray, IntArray
from rayaccel.errors import InvalidInputError

#: Binned SAH object splits (:mod:`rayaccel.bvh.builders.split_binned`).
BINNED = 0
#: Full-sweep SAH object splits (:mod:`rayaccel.bvh.builders.split_sweep`).
SWEEP = 1
#: Object and spatial splits of the SBVH (:mod:`rayaccel.bvh.builders.split_spatial`).
SPATIAL = 2
SPLIT_KINDS = (BINNED, SWEEP, SPATIAL)

#: Work-stack entries: one pending right child per level, and depth <= MAX_DEPTH.
STACK_SIZE = 2 * MAX_DEPTH + 4


def check_split_options(
    max_leaf_size: int,
    traversal_cost: float,
    intersection_cost: float,
    parallel_threshold: int | None = None,
) -> None:
    """Raise :class:`InvalidInputError` for a top-down SAH builder's out-of-range option.

    The checks shared by ``bvh2.binned_sah``, ``bvh2.sbvh`` and ``bvh2.sweep_sah``
    (``parallel_threshold`` None: the builder has none).
    """
    if not 1 <= max_leaf_size <= 64:
        raise InvalidInputError(f"max_leaf_size: expected 1..64, got {max_leaf_size}")
    if not (traversal_cost >= 0 and intersection_cost > 0):
        raise InvalidInputError("traversal_cost must be >= 0 and intersection_cost > 0")
    if parallel_threshold is not None and parallel_threshold < 2:
        raise InvalidInputError("parallel_threshold: expected >= 2")


class NodePool(NamedTuple):
    """The node pool the top-down builders fill; children of a node are a pair.

    Attributes
    ----------
    lo, hi : (capacity, 3) float32
        Node boxes (written by the split functions that track them).
    first : (capacity,) int32
        Leaf: first reference. Inner: left child (the right one is ``first + 1``).
    ref_count : (capacity,) int32
        Leaf: reference count (> 0); inner: 0; never written: -1.
    """

    lo: FloatArray
    hi: FloatArray
    first: IntArray
    ref_count: IntArray


def new_pool(capacity: int) -> NodePool:
    """Return an empty :class:`NodePool` of ``capacity`` slots (``ref_count`` -1 everywhere)."""
    capacity = max(int(capacity), 1)
    return NodePool(
        np.empty((capacity, 3), dtype=np.float32),
        np.empty((capacity, 3), dtype=np.float32),
        np.zeros(capacity, dtype=np.int32),
        np.full(capacity, -1, dtype=np.int32),
    )


def _grow_pool(pool: NodePool, size: int) -> NodePool:
    """Return ``pool`` with at least ``size`` slots (new slots empty)."""
    extra = size - pool.first.shape[0]
    if extra <= 0:
        return pool
    return NodePool(
        np.concatenate((pool.lo, np.empty((extra, 3), dtype=np.float32))),
        np.concatenate((pool.hi, np.empty((extra, 3), dtype=np.float32))),
        np.concatenate((pool.first, np.zeros(extra, dtype=np.int32))),
        np.concatenate((pool.ref_count, np.full(extra, -1, dtype=np.int32))),
    )


@functools.cache
def subtree_kernel(split_kind: int) -> Any:
    """Return the serial work-stack kernel of one split kind (see the module docstring).

    ``kernel(refs, aux, params, begin, end, cap, depth0, root, node_base, stop_size,
    root_box, t_lo, t_hi, t_first, t_count, deferred, deferred_box)`` builds the subtree
    of pool slot ``root`` over ``refs[begin:end]`` (slots up to ``cap``), allocating
    pairs from ``node_base``. Items with fewer than ``stop_size`` references are
    written to ``deferred`` rows ``(node, begin, end, cap, depth)`` and their item
    boxes to ``deferred_box``. Returns ``(next free slot, number deferred)``.
    """

    # simplify: the split functions are inlined twice per node with many array arguments.
    @cpu_kernel(simplify=True)
    def kernel(
        refs, aux, params, begin, end, cap, depth0, root, node_base, stop_size, root_box,
        t_lo, t_hi, t_first, t_count, deferred, deferred_box,
    ):  # fmt: skip
        # The split function's scratch, once per subtree.
        if split_kind == BINNED:
            ws = binned_workspace(params.n_bins)
        elif split_kind == SWEEP:
            ws = sweep_workspace(refs, aux)
        elif split_kind == SPATIAL:
            ws = spatial_workspace(params, cap - begin)
        max_leaf = params.max_leaf_size
        isect_cost = params.intersection_cost
        stack_node = np.empty(STACK_SIZE, dtype=np.int32)
        stack_begin = np.empty(STACK_SIZE, dtype=np.int32)
        stack_end = np.empty(STACK_SIZE, dtype=np.int32)
        stack_cap = np.empty(STACK_SIZE, dtype=np.int32)
        stack_depth = np.empty(STACK_SIZE, dtype=np.int32)
        stack_box = np.empty((STACK_SIZE, 6), dtype=np.float32)
        box = np.empty(12, dtype=np.float32)
        child_item = np.empty((2, 6), dtype=np.float32)
        n_deferred = 0
        next_node = node_base
        stack_node[0] = root
        stack_begin[0] = begin
        stack_end[0] = end
        stack_cap[0] = cap
        stack_depth[0] = depth0
        for k in range(6):
            stack_box[0, k] = root_box[k]
        sp = 1
        while sp > 0:
            sp -= 1
            node = stack_node[sp]
            lo_i = stack_begin[sp]
            hi_i = stack_end[sp]
            node_cap = stack_cap[sp]
            depth = stack_depth[sp]
            count = hi_i - lo_i
            for k in range(6):
                box[6 + k] = stack_box[sp, k]
            # Small subtrees are left to the frontier (built in parallel).
            if count < stop_size:
                deferred[n_deferred, 0] = node
                deferred[n_deferred, 1] = lo_i
                deferred[n_deferred, 2] = hi_i
                deferred[n_deferred, 3] = node_cap
                deferred[n_deferred, 4] = depth
                for k in range(6):
                    deferred_box[n_deferred, k] = box[6 + k]
                n_deferred += 1
                continue
            # Small enough to stop outright.
            if count <= 1:
                t_first[node] = lo_i
                t_count[node] = count
                continue
            forced = depth_forces_median(depth, count, max_leaf)
            if split_kind == BINNED:
                cost, axis, pos = binned_try_split(
                    refs, aux, params, ws, node, lo_i, hi_i, node_cap, depth, forced, box,
                    t_lo, t_hi,
                )  # fmt: skip
            elif split_kind == SWEEP:
                cost, axis, pos = sweep_try_split(
                    refs, aux, params, ws, node, lo_i, hi_i, node_cap, depth, forced, box,
                    t_lo, t_hi,
                )  # fmt: skip
            elif split_kind == SPATIAL:
                cost, axis, pos = spatial_try_split(
                    refs, aux, params, ws, node, lo_i, hi_i, node_cap, depth, forced, box,
                    t_lo, t_hi,
                )  # fmt: skip
            # Leaf when splitting does not pay and the leaf is small enough.
            if count <= max_leaf and (axis < 0 or cost >= isect_cost * count):
                t_first[node] = lo_i
                t_count[node] = count
                continue
            left = next_node
            next_node += 2
            t_first[node] = left
            t_count[node] = 0
            if split_kind == BINNED:
                left_end, right_begin, right_end, left_cap = binned_apply_split(
                    refs, aux, params, ws, node, left, lo_i, hi_i, node_cap, cost, axis, pos,
                    box, child_item, t_lo, t_hi,
                )  # fmt: skip
            elif split_kind == SWEEP:
                left_end, right_begin, right_end, left_cap = sweep_apply_split(
                    refs, aux, params, ws, node, left, lo_i, hi_i, node_cap, cost, axis, pos,
                    box, child_item, t_lo, t_hi,
                )  # fmt: skip
            elif split_kind == SPATIAL:
                left_end, right_begin, right_end, left_cap = spatial_apply_split(
                    refs, aux, params, ws, node, left, lo_i, hi_i, node_cap, cost, axis, pos,
                    box, child_item, t_lo, t_hi,
                )  # fmt: skip
            # Push the right child first so the left is processed next: pairs are then
            # allocated in the depth-first order compaction walks (sequential memory
            # there). The stack holds one pending right child per level.
            for c in (1, 0):
                stack_node[sp] = left + c
                stack_begin[sp] = lo_i if c == 0 else right_begin
                stack_end[sp] = left_end if c == 0 else right_end
                stack_cap[sp] = left_cap if c == 0 else node_cap
                stack_depth[sp] = depth + 1
                for k in range(6):
                    stack_box[sp, k] = child_item[c, k]
                sp += 1
        return next_node, n_deferred

    return kernel


#: The serial kernels, as module globals for the frontier kernels to call (a factory
#: that captured them would miss the disk cache, STYLE §4.3 rule 2).
_subtree_binned = subtree_kernel(BINNED)
_subtree_sweep = subtree_kernel(SWEEP)
_subtree_spatial = subtree_kernel(SPATIAL)


@functools.cache
def frontier_kernel(split_kind: int) -> Any:
    """Return the parallel kernel building a frontier of subtrees of one split kind.

    ``kernel(refs, aux, params, tasks, task_base, task_box, t_lo, t_hi, t_first,
    t_count, n_threads)`` builds subtree ``i`` (``tasks[i] = (node, begin, end, cap,
    depth)``, item box ``task_box[i]``) into the pool slots from ``task_base[i]``.
    ``n_threads`` workers take the subtrees in the given order from a shared counter
    (:mod:`rayaccel._work`).
    """

    @cpu_kernel(parallel=True)
    def kernel(
        refs, aux, params, tasks, task_base, task_box, t_lo, t_hi, t_first, t_count, n_threads
    ):
        counter = new_counter()
        for _worker in prange(worker_count(tasks.shape[0], n_threads, True)):
            while True:
                i = next_item(counter, tasks.shape[0])
                if i < 0:
                    break
                no_tasks = np.empty((0, 5), dtype=np.int32)
                no_boxes = np.empty((0, 6), dtype=np.float32)
                # int64 arguments, as in the serial top-phase call: one compiled signature.
                begin = np.int64(tasks[i, 1])
                end = np.int64(tasks[i, 2])
                cap = np.int64(tasks[i, 3])
                depth = np.int64(tasks[i, 4])
                node = np.int64(tasks[i, 0])
                base = np.int64(task_base[i])
                stop = np.int64(0)
                if split_kind == BINNED:
                    _subtree_binned(
                        refs, aux, params, begin, end, cap, depth, node, base, stop,
                        task_box[i], t_lo, t_hi, t_first, t_count, no_tasks, no_boxes,
                    )  # fmt: skip
                elif split_kind == SWEEP:
                    _subtree_sweep(
                        refs, aux, params, begin, end, cap, depth, node, base, stop,
                        task_box[i], t_lo, t_hi, t_first, t_count, no_tasks, no_boxes,
                    )  # fmt: skip
                elif split_kind == SPATIAL:
                    _subtree_spatial(
                        refs, aux, params, begin, end, cap, depth, node, base, stop,
                        task_box[i], t_lo, t_hi, t_first, t_count, no_tasks, no_boxes,
                    )  # fmt: skip

    return kernel


def build_frontier(
    split_kind: int,
    refs: np.ndarray,
    aux: tuple[np.ndarray, ...],
    params: Any,
    tasks: np.ndarray,
    task_box: np.ndarray,
    next_node: int,
    pool: NodePool,
) -> tuple[int, NodePool]:
    """Build the subtrees ``tasks`` concurrently; return the next free slot and the pool.

    Parameters
    ----------
    split_kind : int
    refs, aux, params
        As the split kind takes them.
    tasks : (k, 5) int32
        ``(node, begin, end, cap, depth)`` of each subtree root (already in the pool).
    task_box : (k, 6) float32
        Item box of each subtree root.
    next_node : int
        First free pool slot.
    pool : NodePool
        Grown as needed (a subtree of ``m = cap − begin`` slots may use ``2m − 2``).
    """
    if tasks.shape[0] == 0:
        return next_node, pool
    # Node blocks reserved in reference order, so blocks lie in depth-first order.
    by_begin = np.argsort(tasks[:, 1], kind="stable")
    tasks, task_box = tasks[by_begin], task_box[by_begin]
    sizes = np.maximum(2 * (tasks[:, 3].astype(np.int64) - tasks[:, 1]) - 2, 0)
    task_base = (next_node + np.concatenate(([0], np.cumsum(sizes)[:-1]))).astype(np.int32)
    pool_end = int(next_node + sizes.sum())
    pool = _grow_pool(pool, pool_end)
    # Largest subtrees first, handed out one at a time, so no thread idles at the end.
    order = np.argsort(-(tasks[:, 2] - tasks[:, 1]), kind="stable")
    frontier_kernel(split_kind)(
        refs, aux, params, np.ascontiguousarray(tasks[order]), task_base[order],
        np.ascontiguousarray(task_box[order]), *pool, numba.get_num_threads(),
    )  # fmt: skip
    return pool_end, pool


def build_top_down(
    split_kind: int,
    refs: np.ndarray,
    aux: tuple[np.ndarray, ...],
    params: Any,
    n_refs: int,
    cap: int,
    root_box: np.ndarray,
    stop_size: int,
    pool: NodePool,
) -> tuple[int, NodePool]:
    """Build the tree over ``refs[0:n_refs]`` rooted at pool slot 0 (its box already set).

    The top levels are split serially until items hold fewer than ``stop_size``
    references (0: the whole tree serially); those subtrees are then built
    concurrently (:func:`build_frontier`). Returns the next free slot and the pool
    (grown when the frontier needed more slots).

    Parameters
    ----------
    split_kind : int
        :data:`BINNED`, :data:`SWEEP` or :data:`SPATIAL`.
    refs, aux, params
        As the split kind takes them.
    n_refs : int
        References in use.
    cap : int
        Reference slots the tree may use (``> n_refs`` for spatial splits).
    root_box : (6,) float32
        The root's item box.
    stop_size : int
    pool : NodePool
        At least ``2·cap − 1`` slots when ``stop_size`` is 0.
    """
    n_slots = cap + 1 if stop_size > 0 else 0
    deferred = np.empty((n_slots, 5), dtype=np.int32)
    deferred_box = np.empty((n_slots, 6), dtype=np.float32)
    next_node, n_deferred = subtree_kernel(split_kind)(
        refs, aux, params, 0, n_refs, cap, 0, 0, 1, stop_size,
        np.ascontiguousarray(root_box, dtype=np.float32), *pool, deferred, deferred_box,
    )  # fmt: skip
    return build_frontier(
        split_kind, refs, aux, params, deferred[:n_deferred], deferred_box[:n_deferred],
        int(next_node), pool,
    )  # fmt: skip
