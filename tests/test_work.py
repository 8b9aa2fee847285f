"""The shared-counter work distribution of parallel kernels (``rayaccel._work``)."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from numba import prange

from rayaccel._jit import atomic_fetch_add, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count, worker_count_py


@cpu_kernel(parallel=True)
def _take_all(n_items, n_threads, parallel, taken, work):
    """Count how often each item is taken; item ``i`` spins ``work[i]`` steps (uneven costs)."""
    counter = new_counter()
    for _worker in prange(worker_count(n_items, n_threads, parallel)):
        while True:
            i = next_item(counter, n_items)
            if i < 0:
                break
            x = 0.0
            for _ in range(work[i]):
                x = x * 0.5 + 1.0
            taken[i] += 1 if x >= 0 else 2


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("parallel", [True, False])
@pytest.mark.parametrize("n_items", [0, 1, 3, 1000])
def test_every_item_is_taken_exactly_once(threads, parallel, n_items):
    work = np.random.default_rng(n_items).integers(0, 20_000, max(n_items, 1))
    taken = np.zeros(max(n_items, 1), dtype=np.int64)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        _take_all(n_items, numba.get_num_threads(), parallel, taken, work)
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    assert np.array_equal(taken[:n_items], np.ones(n_items, dtype=np.int64))


def test_worker_count():
    assert worker_count_py(10, 4, True) == 4
    assert worker_count_py(3, 4, True) == 3
    assert worker_count_py(0, 4, True) == 1
    assert worker_count_py(10, 4, False) == 1


@cpu_kernel()
def _add_all(counter, values, old):
    for i in range(values.size):
        old[i] = atomic_fetch_add(counter, 0, values[i])


def test_atomic_fetch_add_returns_the_previous_value():
    counter = np.zeros(1, dtype=np.int64)
    values = np.array([1, 5, -2, 7], dtype=np.int64)
    old = np.empty_like(values)
    _add_all(counter, values, old)
    assert old.tolist() == [0, 1, 6, 4]
    assert counter[0] == 11
