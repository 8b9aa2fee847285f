"""One decorator policy for every CPU kernel (STYLE §4.1).

``fastmath`` keeps IEEE infinities and NaN (no ``nnan``/``ninf``): slab tests for
axis-parallel rays rely on ``1/±0 = ±inf``. ``error_model="numpy"`` makes division
by zero give ``inf`` instead of raising.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba

FASTMATH = frozenset({"nsz", "arcp", "contract"})


def cpu_kernel(*, parallel: bool = False) -> Callable[[Callable[..., Any]], Any]:
    """Return the ``njit`` decorator used for every CPU kernel.

    Parameters
    ----------
    parallel : bool
        Compile ``prange`` loops as parallel loops.
    """
    return numba.njit(  # type: ignore[no-any-return]
        parallel=parallel,
        cache=True,
        nogil=True,
        fastmath=set(FASTMATH),
        error_model="numpy",
    )


def cpu_inline(fn: Callable[..., Any]) -> Any:
    """Compile a leaf helper that is always inlined into its callers."""
    return numba.njit(
        inline="always", cache=True, nogil=True, fastmath=set(FASTMATH), error_model="numpy"
    )(fn)
