"""numba's inliner with one deep-copy memo per inlined call (:mod:`rayaccel._inline_copy`)."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import types

import numba
from numba.core import inline_closurecall

import rayaccel  # noqa: F401  (importing the package patches the inliner)
from rayaccel._inline_copy import share_copy_memo


@numba.njit(inline="always")
def _leaf(x):
    if x > 2.0:
        return x * 2.0
    return x - 1.0


@numba.njit(inline="always")
def _middle(x):
    total = 0.0
    for k in range(3):
        total += _leaf(x + k)
    return total


@numba.njit
def _root(x):
    return _middle(x) + _middle(-x)


def _root_py(x):
    def leaf(v):
        return v * 2.0 if v > 2.0 else v - 1.0

    def middle(v):
        return sum(leaf(v + k) for k in range(3))

    return middle(x) + middle(-x)


def test_the_package_patches_numbas_inliner():
    assert inline_closurecall.copy is not copy
    assert inline_closurecall.copy.memo is None  # outside an inlined call
    assert inline_closurecall.copy.deepcopy is not copy.deepcopy


def test_nested_inlined_helpers_compute_what_python_does():
    for x in (-5.0, 0.0, 0.5, 1.5, 4.0):
        assert _root(x) == _root_py(x)
    assert inline_closurecall.copy.memo is None  # restored after every call


def test_an_unknown_inliner_is_left_alone():
    assert share_copy_memo(types.ModuleType("not_an_inliner")) is False
    fake = types.ModuleType("fake")
    fake.InlineWorker = type("InlineWorker", (), {"inline_ir": lambda self: None})
    assert share_copy_memo(fake) is False  # no ``copy`` module in its namespace


def test_the_environment_can_keep_numbas_own_inliner():
    code = (
        "import copy, rayaccel; from numba.core import inline_closurecall as m; "
        "print(m.copy is copy)"
    )
    env = {**os.environ, "RAYACCEL_PLAIN_INLINER": "1"}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert run.stdout.strip() == "True", run.stderr
