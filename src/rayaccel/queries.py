"""Query kinds: closest hit (Embree's ``intersect``) and any hit (Embree's ``occluded``).

Kernels take the kind as the integer constant of a compile-time variant (STYLE §4.3):
``QUERY_CLOSEST`` keeps the nearest hit in ``[tmin, tmax]``, ``QUERY_ANY`` stops at the
first hit found. The module sits in layer 0 beside :mod:`rayaccel.counters`, so the
oracle in :mod:`rayaccel.kernels` and every family share one definition.
"""

from __future__ import annotations

from typing import Literal

from rayaccel.errors import InvalidInputError

QUERY_CLOSEST = 0
QUERY_ANY = 1
#: Public query names and their kernel constants.
QUERIES: dict[str, int] = {"closest": QUERY_CLOSEST, "any": QUERY_ANY}
QUERY_KINDS: tuple[str, ...] = tuple(QUERIES)
QueryKind = Literal["closest", "any"]


def query_constant(query: str) -> int:
    """Return the kernel constant of ``query``; anything but "closest"/"any" raises."""
    if query not in QUERIES:
        raise InvalidInputError(f"query: expected one of {QUERY_KINDS}, got {query!r}")
    return QUERIES[query]
