"""Compile the CPU traversals' per-ray code for CUDA: one source, two targets (STYLE §4.2).

Every traversal body and leaf helper is written as a plain ``*_py`` function and
compiled for the CPU by :func:`rayaccel._jit.cpu_inline`. :func:`device_function` makes
the CUDA device function of such a body: it rebuilds the Python function with the same
code object over a copy of its module's globals in which every CPU helper the code
names (a ``cpu_inline`` dispatcher, directly or in a closure cell) is replaced by the
device function of that helper's own ``*_py`` source, recursively, and compiles the
result with ``numba.cuda.jit(device=True)``. So the GPU runs the very statements the
CPU runs and the tests compare, and a fix to a body reaches both targets.

A few CPU helpers have no meaning on a GPU or are written in x86-flavoured LLVM IR
(the prefetch hint, the branch barrier, the SIMD box test of two lanes); they are
replaced through :data:`SUBSTITUTES` by device functions of the same signature
(:mod:`rayaccel.cuda.device_helpers`). Everything else (``math``, numpy scalar
constructors, the precision overloads of :mod:`rayaccel.kernels.real`) compiles for
CUDA as it is.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Iterator
from typing import Any

from numba.core.dispatcher import Dispatcher

#: CPU helper -> its CUDA replacement (filled by :mod:`rayaccel.cuda.device_helpers`).
SUBSTITUTES: dict[int, Any] = {}

_MEMO: dict[tuple[int, ...], Any] = {}


def substitute(cpu_helper: Any, replacement: Any) -> None:
    """Register ``replacement`` (a device function) for the CPU-only ``cpu_helper``."""
    SUBSTITUTES[id(cpu_helper)] = replacement


def _names(code: types.CodeType) -> Iterator[str]:
    """Every global name ``code`` and the code objects nested in it may load."""
    yield from code.co_names
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            yield from _names(const)


def _retarget_value(value: Any) -> Any:
    """Return the device form of a global or closure value (itself if none is needed)."""
    if id(value) in SUBSTITUTES:
        return SUBSTITUTES[id(value)]
    if isinstance(value, Dispatcher):
        return device_function(value.py_func)
    return value


def python_function(func: Any) -> Callable[..., Any]:
    """Return the plain Python function behind ``func`` (a CPU dispatcher, or ``func``)."""
    return func.py_func if isinstance(func, Dispatcher) else func  # type: ignore[no-any-return]


def device_function(func: Any) -> Any:
    """Return the CUDA device function compiled from the Python source of ``func``.

    ``func`` is a plain ``*_py`` function, a closure made by a kernel factory, or a
    ``cpu_inline`` dispatcher (its ``py_func`` is used). Results are memoised by the
    function and its closure cells, so each helper compiles once per process.
    """
    from numba import cuda

    from rayaccel.cuda import device_helpers  # noqa: F401  (registers the stand-ins)

    py = python_function(func)
    cells = tuple(c.cell_contents for c in py.__closure__ or ())
    key = (id(py.__code__), id(py.__globals__), *(id(c) for c in cells))
    if key in _MEMO:
        return _MEMO[key]
    namespace = dict(py.__globals__)
    for name in set(_names(py.__code__)):
        if name in namespace:
            namespace[name] = _retarget_value(namespace[name])
    closure = tuple(types.CellType(_retarget_value(c)) for c in cells) or None
    rebuilt = types.FunctionType(py.__code__, namespace, py.__name__, py.__defaults__, closure)
    rebuilt.__qualname__ = py.__qualname__
    rebuilt.__doc__ = py.__doc__
    compiled = cuda.jit(device=True)(rebuilt)
    _MEMO[key] = compiled
    return compiled
