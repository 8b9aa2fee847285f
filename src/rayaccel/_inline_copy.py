"""Inlining without the quadratic copy: one deep-copy memo per inlined call.

Every kernel of the package is built by inlining helpers at numba IR level
(``inline="always"``, :func:`rayaccel._jit.cpu_inline`), often helpers that inline
helpers. numba's inliner (``InlineWorker.inline_ir`` in
``numba.core.inline_closurecall``) copies the callee's IR one block at a time, each
block with a deep copy of its own. Every variable of a block points at the function's
scope, which lists every variable of the function, so each block copies the whole
scope again: a call site costs blocks × variables, and the grid's DDA spent more than
half of its compile time in those copies (numba issue #8989 describes the redundant
copies). :func:`share_copy_memo` gives the inliner one deep-copy memo per inlined call,
so the callee's scope and variables are copied once and its copied blocks share that
scope, as the blocks of the original IR share the original. The inliner then renames
every variable into the caller's scope as before, so the inlined IR, and the machine
code, are those numba makes without the memo.

``RAYACCEL_PLAIN_INLINER=1`` in the environment leaves numba's inliner as it is.
"""

from __future__ import annotations

import copy
import functools
import os
from types import ModuleType
from typing import Any


class _CallMemoCopy:
    """Stands in for the ``copy`` module inside the inliner's module.

    ``deepcopy(x)`` without a memo uses the memo of the inlined call in progress (none
    outside one, as :func:`copy.deepcopy`); every other name is the ``copy`` module's.
    """

    def __init__(self) -> None:
        self.memo: dict[int, Any] | None = None

    def deepcopy(self, x: Any, memo: dict[int, Any] | None = None) -> Any:
        """Return :func:`copy.deepcopy` of ``x`` with ``memo``, or the current call's memo."""
        return copy.deepcopy(x, self.memo if memo is None else memo)

    def __getattr__(self, name: str) -> Any:
        return getattr(copy, name)


def share_copy_memo(module: ModuleType) -> bool:
    """Make ``module.InlineWorker.inline_ir`` copy the callee's blocks with one memo per call.

    Returns whether it did: False when the environment asks for numba's own inliner,
    or when ``module`` does not look like the inliner this was written for (no
    ``InlineWorker.inline_ir``, or no ``copy`` module in its namespace), so a numba
    that changes it runs unpatched rather than wrongly.
    """
    worker = getattr(module, "InlineWorker", None)
    original = getattr(worker, "inline_ir", None)
    if (
        os.environ.get("RAYACCEL_PLAIN_INLINER", "") not in ("", "0")
        or original is None
        or getattr(module, "copy", None) is not copy
    ):
        return False
    shim = _CallMemoCopy()

    @functools.wraps(original)
    def inline_ir(self: Any, *args: Any, **kwargs: Any) -> Any:
        outer, shim.memo = shim.memo, {}
        try:
            return original(self, *args, **kwargs)
        finally:
            shim.memo = outer

    module.copy = shim  # type: ignore[attr-defined]
    worker.inline_ir = inline_ir  # type: ignore[union-attr]
    return True
