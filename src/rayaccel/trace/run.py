"""The Python side of every traversal: check the query, allocate outputs, run, wrap the hits.

:func:`run_trace` is what a registered ``trace_<structure>_<method>`` function calls
after deriving its layout (memoised per ``Accel`` by :func:`memoised_layout`). It runs
batches below :data:`PARALLEL_MIN_RAYS` on the calling thread, where a parallel
launch costs more than it saves, and serialises parallel kernels when numba's threading
layer is not thread-safe (:func:`rayaccel.config.parallel_section`).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from contextvars import ContextVar
from typing import Any, TypeVar

import numba

from rayaccel.config import parallel_section
from rayaccel.counters import counters_to_dict, empty_counters
from rayaccel.errors import TraversalOverflowError
from rayaccel.queries import query_constant
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.trace.skeleton import trace_kernel

#: Batches smaller than this run on the calling thread (no parallel launch overhead).
PARALLEL_MIN_RAYS = 4096

#: Where :func:`run_trace` launches: ``None`` for the CPU kernels, or a target whose
#: ``run(kernel_for, layout_arrays, rays, query, stats, overflow_hint)`` launches the same
#: per-ray body elsewhere (the GPU: :func:`rayaccel.cuda.device.on_cuda` sets it for one
#: query, so every traversal derives its layout once for both targets).
TRACE_TARGET: ContextVar[Any] = ContextVar("rayaccel_trace_target", default=None)

#: The reason :func:`run_trace` gives for rays that overflow a traversal stack unless told.
DEFAULT_OVERFLOW_HINT = "the structure is deeper than its traversal stack"

_Layout = TypeVar("_Layout")


def memoised_layout(
    cache: dict[str, Any] | None, name: str, make: Callable[[], _Layout]
) -> _Layout:
    """Return the derived layout ``name`` from ``cache``, made by ``make()`` on first use.

    Every traversal layout derived from a canonical structure (packed rows, links,
    ropes, cell ranges) is memoised this way in its ``Accel``'s cache; without a cache
    it is made afresh. Making one may launch parallel kernels, so it runs in
    :func:`rayaccel.config.parallel_section` like a traversal.
    """
    if cache is not None and name in cache:
        return cache[name]  # type: ignore[no-any-return]
    start = time.perf_counter()
    with parallel_section():
        layout = make()
    if cache is not None:
        cache[name] = layout
        cache.setdefault(LAYOUT_MS, {})[name] = (time.perf_counter() - start) * 1e3
    return layout


#: The cache entry holding each memoised layout's build time in ms (``Accel.info``).
LAYOUT_MS = "layout_ms"


def body_kernels(make_scratch: Any, trace_rays: Any) -> Callable[[int, bool, bool], Any]:
    """Return ``kernel_for(query, with_stats, parallel)`` running a per-ray body in the skeleton.

    See :mod:`rayaccel.trace.skeleton` for what ``make_scratch`` and ``trace_rays`` are.
    """
    return functools.partial(trace_kernel, make_scratch, trace_rays)


def run_trace(
    kernel_for: Callable[[int, bool, bool], Any],
    layout_arrays: Any,
    rays: RayBatch,
    query: str,
    stats: bool,
    overflow_hint: str = DEFAULT_OVERFLOW_HINT,
) -> HitBatch:
    """Allocate outputs, run a ``kernel_for(query, stats, parallel)`` kernel, wrap the hits.

    Parameters
    ----------
    kernel_for : callable
        Returns the compiled variant; usually :func:`body_kernels` of a traversal.
    layout_arrays : NamedTuple of arrays
        What the kernel's ``layout`` argument receives.
    rays : RayBatch
        The rays to trace.
    query : {"closest", "any"}
        Closest hit, or stop at the first hit found (validated here).
    stats : bool
        Allocate per-ray counters and return them in ``hits.stats``.
    overflow_hint : str
        Why rays can overflow, for the error message.

    Returns
    -------
    HitBatch

    Raises
    ------
    InvalidInputError
        ``query`` is not "closest" or "any".
    TraversalOverflowError
        Some rays ran out of traversal stack.
    """
    target = TRACE_TARGET.get()
    if target is not None:
        return target.run(kernel_for, layout_arrays, rays, query, stats, overflow_hint)  # type: ignore[no-any-return]
    constant = query_constant(query)
    n = rays.n_rays
    # Hits in the rays' precision: float64 rays compile float64 kernels (kernels/real.py).
    hits = HitBatch.empty(n, rays.precision)
    counters = empty_counters(n, stats)
    parallel = n >= PARALLEL_MIN_RAYS
    kernel = kernel_for(constant, bool(stats), parallel)
    args = (
        layout_arrays,
        rays.origin,
        rays.direction,
        rays.tmin,
        rays.tmax,
        hits.t,
        hits.prim,
        hits.u,
        hits.v,
        counters,
        numba.get_num_threads(),
    )
    if parallel:
        with parallel_section():
            overflow = kernel(*args)
    else:
        overflow = kernel(*args)
    if overflow:
        raise TraversalOverflowError(
            f"{overflow} rays overflowed the traversal stack; {overflow_hint}"
        )
    if stats:
        return HitBatch(hits.t, hits.prim, hits.u, hits.v, stats=counters_to_dict(counters))
    return hits
