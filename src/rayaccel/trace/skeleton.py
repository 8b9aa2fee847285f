"""The parallel skeleton every traversal kernel runs in; a traversal supplies its per-ray body.

One worker per thread (``prange`` over :func:`rayaccel._work.worker_count`) takes chunks
of :data:`RAY_CHUNK` consecutive rays from a shared counter, so coherent rays stay
together and the threads stay busy however unequal the rays are
(:mod:`rayaccel._work`). Each worker first makes its scratch arrays once (a stack, a
short stack, nothing), then runs the traversal's body on every ray of its chunks and
stores the hit it returns. Each ray writes only its own output slots, so results are
identical for every thread count.

A traversal module supplies two inline functions (``rayaccel._jit.cpu_inline``):

``make_scratch(layout) -> scratch``
    The per-worker arrays the body needs (a tuple of arrays, or any value).
``trace_rays(layout, scratch, origin, direction, tmin, tmax, begin, end, hit_t, ...)``
    (then ``hit_prim, hit_u, hit_v, counters, query, with_stats``; returns the number
    of rays that overflowed): its per-ray body inside ``for r in range(begin, end):``,
    ending each ray with
    :func:`store_hit`; with ``with_stats`` it stores the ray's counters in
    ``counters[r]`` (``Counter`` columns, with :func:`store_counts` and
    :func:`store_backtracks`).

Both are inlined into the kernel at numba IR level, so the compiled code is the code
of a hand-written loop. ``with_stats`` reaches the body as a compile-time constant,
and LLVM removes the counter updates when it is off; ``query`` is a compile-time
constant of the plain kernels and a run-time value of the statistics kernels
(:func:`trace_kernel`), which the body tests only once it has a hit. The body runs
a chunk at a time in a function compiled without numba's runtime
(:func:`chunk_body`, ``cpu_kernel(nrt=False)``): numba reference-counts every array
an inlined function receives or unpacks, with an atomic update of a count that every
thread shares, and in a body whose loop calls helpers taking arrays (the packets'
leaf and stack helpers) those updates sat inside the loop. Without the runtime there
are none; the worker, which does use it, owns the arrays meanwhile. So a body
allocates nothing: its arrays come from ``make_scratch``. The kernel returns the
number of rays that overflowed; :func:`rayaccel.trace.run.run_trace` turns a
non-zero count into ``TraversalOverflowError``.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.counters import Counter

#: Rays per work item: enough to amortise taking an item, few enough to balance threads.
RAY_CHUNK = 64


@functools.cache
def chunk_body(trace_rays: Any, with_stats: bool) -> Any:
    """Return ``trace_rays`` compiled for one chunk without numba's runtime (no refcounts).

    ``chunk(layout, scratch, origin, direction, tmin, tmax, begin, end, hit_t,
    hit_prim, hit_u, hit_v, counters, query) -> n_overflowed``; see the module
    docstring for why it is a function of its own.
    """

    @cpu_kernel(nrt=False)
    def chunk(
        layout, scratch, origin, direction, tmin, tmax, begin, end, hit_t, hit_prim, hit_u,
        hit_v, counters, query,
    ):  # fmt: skip
        return trace_rays(
            layout, scratch, origin, direction, tmin, tmax, begin, end,
            hit_t, hit_prim, hit_u, hit_v, counters, query, with_stats,
        )  # fmt: skip

    return chunk


@functools.cache
def chunk_worker(make_scratch: Any, trace_rays: Any, with_stats: bool) -> Any:
    """Return the serial kernel one worker runs: take chunks from ``counter`` until none is left.

    ``worker(layout, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v,
    counters, counter, query) -> n_overflowed`` makes the worker's scratch once, then
    runs the traversal's body on the chunks it takes from the shared ``counter``
    (:func:`rayaccel._work.next_item`). ``query`` is a literal (compile-time) value in
    the plain kernels and a run-time one in the statistics kernels
    (:func:`trace_kernel`); a body tests it only where it finds a hit.
    """
    chunk_trace = chunk_body(trace_rays, with_stats)

    @cpu_kernel()
    def worker(
        layout, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v, counters, counter,
        query,
    ):  # fmt: skip
        overflow = 0
        n_rays = origin.shape[0]
        n_chunks = (n_rays + RAY_CHUNK - 1) // RAY_CHUNK
        scratch = make_scratch(layout)
        while True:
            chunk = next_item(counter, n_chunks)
            if chunk < 0:
                break
            overflow += chunk_trace(
                layout, scratch, origin, direction, tmin, tmax,
                chunk * RAY_CHUNK, min(n_rays, (chunk + 1) * RAY_CHUNK),
                hit_t, hit_prim, hit_u, hit_v, counters, query,
            )  # fmt: skip
        return overflow

    return worker


@functools.cache
def trace_kernel(
    make_scratch: Any, trace_rays: Any, query: int, with_stats: bool, parallel: bool
) -> Any:
    """Return the kernel running ``trace_rays`` over every ray for one compile-time variant.

    The serial and the parallel kernel of a variant both call one compiled
    :func:`chunk_worker` (a call per worker, not per ray): the parallel kernel is a
    ``prange`` over workers around that call, so it compiles in a second instead of
    running numba's parallel passes over the whole inlined traversal again.

    Parameters
    ----------
    make_scratch, trace_rays : numba dispatchers (``cpu_inline``)
        The traversal's per-worker scratch and per-ray body (see the module docstring).
    query : int
        ``QUERY_CLOSEST`` or ``QUERY_ANY`` (:mod:`rayaccel.queries`).
    with_stats : bool
        Whether the body fills per-ray counters.
    parallel : bool
        ``prange`` over one worker per thread (nogil), or one worker on the calling thread.

    Returns
    -------
    numba dispatcher
        ``kernel(layout, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v,
        counters, n_threads) -> n_overflowed``; ``counters`` is ``(n, N_COUNTERS)`` int32
        with stats and a ``(0, N_COUNTERS)`` placeholder without; ``n_threads`` is
        ``numba.get_num_threads()`` read by the caller.
    """
    worker = chunk_worker(make_scratch, trace_rays, with_stats)
    # A plain int reaches the worker as a literal type: the worker is compiled per query
    # kind with the query folded in (the plain kernels, where speed counts). A numpy
    # int64 is a run-time value: one statistics worker serves both kinds, which halves
    # what the statistics variants compile.
    query_arg = np.int64(query) if with_stats else int(query)

    @cpu_kernel(parallel=parallel)
    def kernel(
        layout, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v, counters, n_threads
    ):
        _ = (query_arg, parallel)
        overflow = 0
        n_chunks = (origin.shape[0] + RAY_CHUNK - 1) // RAY_CHUNK
        counter = new_counter()
        for _worker in prange(worker_count(n_chunks, n_threads, parallel)):
            overflow += worker(
                layout, origin, direction, tmin, tmax, hit_t, hit_prim, hit_u, hit_v,
                counters, counter, query_arg,
            )  # fmt: skip
        return overflow

    return kernel


def store_hit_py(hit_t, hit_prim, hit_u, hit_v, r, t, prim, u, v):
    """Store ray ``r``'s hit if it has one (``prim >= 0``); outputs start as misses."""
    if prim >= 0:
        hit_t[r] = t
        hit_prim[r] = prim
        hit_u[r] = u
        hit_v[r] = v


store_hit = cpu_inline(store_hit_py)


def no_scratch_py(layout):
    """Return a worker's scratch for a body that needs none (its per-ray state is scalars)."""
    return 0


no_scratch = cpu_inline(no_scratch_py)


def store_counts_py(counters, r, steps, nodes, box_tests, prim_tests, stack_peak, n_bytes):
    """Store the counters every traversal fills in ``counters[r]`` (0 for one it has not)."""
    counters[r, Counter.STEPS] = steps
    counters[r, Counter.NODES] = nodes
    counters[r, Counter.BOX_TESTS] = box_tests
    counters[r, Counter.PRIM_TESTS] = prim_tests
    counters[r, Counter.STACK_PEAK] = stack_peak
    counters[r, Counter.BYTES] = n_bytes


store_counts = cpu_inline(store_counts_py)


def store_backtracks_py(counters, r, restarts, backtracks, hash_lookups, targets):
    """Store a stackless traversal's counters in ``counters[r]`` (0 for one it has not).

    ``targets`` is the histogram of backtracking targets, in the order of its columns:
    how many went to the sibling (0 levels up), the uncle (1), the grand-uncle (2) and
    further up.
    """
    counters[r, Counter.RESTARTS] = restarts
    counters[r, Counter.BACKTRACKS] = backtracks
    counters[r, Counter.HASH_LOOKUPS] = hash_lookups
    for k in range(4):
        counters[r, Counter.BACKTRACK_SIBLING + k] = targets[k]


store_backtracks = cpu_inline(store_backtracks_py)
