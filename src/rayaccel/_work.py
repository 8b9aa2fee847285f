"""How parallel kernels share out work: one worker per thread, items from a shared counter.

numba's OpenMP threading layer runs a ``prange`` as one ``omp for`` with libgomp's
default static schedule: each thread gets a fixed, contiguous share of the iterations,
whatever ``numba.parallel_chunksize`` says. When items cost unequal amounts (the rays
of a ceiling and of a cluttered floor; subtrees sorted largest first) one thread then
waits for the other. Parallel kernels therefore run their ``prange`` over
:func:`worker_count` workers, and each worker takes items from a shared counter until
none is left::

    counter = new_counter()
    for _worker in prange(worker_count(n_items, n_threads, parallel)):
        while True:
            i = next_item(counter, n_items)
            if i < 0:
                break
            ...  # item i

``n_threads`` is ``numba.get_num_threads()`` read by the caller: called inside a kernel
it is a ctypes call, and numba will not cache such a kernel. Items are taken in order,
so a list sorted largest first is scheduled largest first. Which thread runs an item
changes from run to run, so kernels keep every item's output to itself (results stay
identical for any thread count). With a shared counter an idle thread always finds the
next item, so a second thread helps even when costs are uneven; the traversal and
builder measurements are in ``docs/performance.md`` (What was tried, "Work
distribution").
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import atomic_fetch_add, cpu_inline


def worker_count_py(n_items, n_threads, parallel):
    """Workers to start: one per thread but at most one per item; 1 when not ``parallel``."""
    if not parallel:
        return 1
    return max(1, min(n_threads, n_items))


def new_counter_py():
    """Return a fresh shared counter (a one-element int64 array at 0)."""
    return np.zeros(1, dtype=np.int64)


def next_item_py(counter, n_items):
    """Take the next item index from ``counter``; -1 once all ``n_items`` are taken."""
    i = atomic_fetch_add(counter, 0, 1)
    if i < n_items:
        return i
    return -1


worker_count = cpu_inline(worker_count_py)
new_counter = cpu_inline(new_counter_py)
next_item = cpu_inline(next_item_py)
