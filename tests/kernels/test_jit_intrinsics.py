"""The small LLVM intrinsics of ``rayaccel._jit`` against their numpy meaning."""

from __future__ import annotations

import numpy as np

from rayaccel._jit import atomic_exchange, cpu_kernel, keep_branch, next_up_float32


@cpu_kernel()
def _next_up_all(x, out):
    for i in range(x.size):
        out[i] = next_up_float32(x[i])


def test_next_up_matches_numpy_nextafter_bit_for_bit():
    rng = np.random.default_rng(0)
    bits = rng.integers(-(2**31), 2**31, 200_000, dtype=np.int64).astype(np.int32)
    f32 = np.finfo(np.float32)
    special = [0.0, -0.0, np.inf, -np.inf, np.nan, 1.0, -1.0, f32.max, -f32.max, f32.tiny,
               -f32.tiny, f32.smallest_subnormal, -f32.smallest_subnormal]  # fmt: skip
    x = np.concatenate([bits.view(np.float32), np.array(special, dtype=np.float32)])
    out = np.empty_like(x)
    _next_up_all(x, out)
    with np.errstate(all="ignore"):
        expected = np.nextafter(x, np.float32(np.inf))
    nan = np.isnan(expected)
    assert np.array_equal(np.isnan(out), nan)
    assert np.array_equal(out.view(np.int32)[~nan], expected.view(np.int32)[~nan])


@cpu_kernel()
def _exchange_all(slots, index, values, old):
    for i in range(values.size):
        old[i] = atomic_exchange(slots, index[i], values[i])


def test_atomic_exchange_returns_the_previous_value():
    slots = np.full(3, -1, dtype=np.int32)
    index = np.array([0, 1, 0, 2, 0], dtype=np.int64)
    values = np.array([5, 6, 7, 8, 9], dtype=np.int32)
    old = np.empty(5, dtype=np.int32)
    _exchange_all(slots, index, values, old)
    assert old.tolist() == [-1, -1, 5, -1, 7]
    assert slots.tolist() == [9, 6, 8]


@cpu_kernel()
def _pick_with_kept_branches(flags, a, b, out):
    for i in range(flags.size):
        if flags[i]:
            keep_branch()
            out[i] = a[i]
        else:
            keep_branch()
            out[i] = b[i]


def test_keep_branch_changes_no_result():
    rng = np.random.default_rng(1)
    flags = rng.random(1000) < 0.5
    a, b = rng.random(1000), rng.random(1000)
    out = np.empty(1000)
    _pick_with_kept_branches(flags, a, b, out)
    assert np.array_equal(out, np.where(flags, a, b))
