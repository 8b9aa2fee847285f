"""Checks every entry point applies to array arguments as it coerces them (layer 0).

Masked arrays are refused before coercion; ``(n, 3)`` arrays (mesh vertices and faces,
query points, rays) are checked for shape, a real dtype and finite rows in the same
words at every entry point; the numeric range of each precision (the
coordinates, directions and triangles the intersection tests trace without overflow) is
checked on the coerced arrays against the input.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from rayaccel.errors import InvalidInputError


def reject_masked(name: str, value: object) -> None:
    """Raise if ``value`` is a numpy masked array with masked entries.

    ``np.asarray`` drops the mask and keeps whatever the hidden entries hold, so a
    masked ray or vertex would be used silently; callers fill or drop them instead.

    Raises
    ------
    InvalidInputError
        Naming the argument and the number of masked entries.
    """
    if isinstance(value, np.ma.MaskedArray) and np.ma.getmaskarray(value).any():
        masked = int(np.count_nonzero(np.ma.getmaskarray(value)))
        raise InvalidInputError(
            f"{name}: a masked array with {masked} masked entries; "
            "fill them (.filled()) or drop them (.compressed()) first"
        )


# -- (n, 3) rows -----------------------------------------------------------------------------


def rows_of_three(name: str, value: object, rows: str, kind: str) -> npt.NDArray[Any]:
    """Return ``value`` as an array of shape ``(rows, 3)`` (``rows``, ``kind``: for errors).

    Raises
    ------
    InvalidInputError
        ``value`` is not an array, not two-dimensional with three columns, or a masked
        array with masked entries (:func:`reject_masked`).
    """
    reject_masked(name, value)
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: expected a ({rows}, 3) {kind} array, got {exc}") from exc
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidInputError(f"{name}: expected shape ({rows}, 3), got {array.shape}")
    return array


def check_real(name: str, array: npt.NDArray[Any]) -> None:
    """Raise unless ``array`` holds real numbers (a float or integer dtype).

    Raises
    ------
    InvalidInputError
        Naming ``array``'s dtype (strings, objects, complex numbers, booleans).
    """
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise InvalidInputError(f"{name}: expected a float array, got dtype {array.dtype}")


def check_finite_rows(name: str, array: npt.NDArray[Any], row: str, rows: str) -> None:
    """Raise unless every row of the ``(n, 3)`` real ``array`` is finite.

    ``row`` and ``rows`` name one row and several in the message (``"vertex"``,
    ``"vertices"``).

    Raises
    ------
    InvalidInputError
        Naming the first row holding a NaN or an infinity, its values and how many
        rows do.
    """
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        bad = int(np.argmin(finite))
        raise InvalidInputError(
            f"{name}: {row} {bad} is not finite ({array[bad].tolist()}); "
            f"{int((~finite).sum())} non-finite {rows} in all"
        )


# -- numeric range ---------------------------------------------------------------------------
#
# The intersection code is exact in sign but not in range: the watertight triangle test
# forms products of three lengths in the rays' precision (the scaled distance
# ``T = U·(Sz·Az) + ...`` is an edge function, a product of two coordinate differences,
# times a difference over a direction component), and the slab test divides by direction
# components. Inputs are therefore bounded so that none of these overflows; every bound
# below is derived in docs/reliability.md ("Numbers").

#: The largest coordinate magnitude (vertices, ray origins) a precision traces. With
#: ``|x| <= 2^30`` and a direction's largest component ``>= 2^-30``, float32's ``T`` stays
#: below ``3·2^126`` and every hit distance below ``2^61``. Float64 keeps hit distances
#: below ``2^125``: the BVH traversals store entry distances in float32.
COORDINATE_LIMIT = {"float32": 2.0**30, "float64": 2.0**62}
#: The smallest largest-component of a nonzero direction: below it, hits inside the
#: coordinate range could lie beyond these distances (``t`` is measured in units of the
#: direction's length).
DIRECTION_FLOOR = {"float32": 2.0**-30, "float64": 2.0**-62}
#: The smallest normal number of each precision. A direction component below it is
#: flushed to zero (its reciprocal overflows); a triangle whose doubled area is below it
#: is zero-area to the intersection test.
NORMAL_FLOOR = {
    "float32": float(np.finfo(np.float32).tiny),
    "float64": float(np.finfo(np.float64).tiny),
}
_POWERS = {2.0**30: "2^30", 2.0**62: "2^62", 2.0**-30: "2^-30", 2.0**-62: "2^-62"}


def _bound(value: float) -> str:
    """``2^30 (about 1.07e+09)``: a bound as the power of two and its decimal."""
    return f"{_POWERS[value]} (about {value:.3g})"


def _other(precision: str) -> str:
    """Return the precision that is not ``precision``."""
    return "float64" if precision == "float32" else "float32"


def _rows_failing(ok: Any) -> Any:
    """Return the sorted rows of an ``(n, k)`` bool array with a False entry."""
    return np.unique(np.flatnonzero(~ok) // ok.shape[1])


def check_coordinates(name: str, raw: Any, coerced: Any, precision: str, what: str) -> None:
    """Raise if a finite entry of ``raw`` lies beyond ``COORDINATE_LIMIT[precision]``.

    ``coerced`` is ``raw`` converted to the precision (values beyond float32's range
    became ``inf`` there). The bound applies to the converted values; a non-finite input
    is left to the caller (rays with one miss, meshes refuse them). A ``min`` and a
    ``max`` over ``coerced`` clear a batch in range; otherwise only the rows holding a
    value beyond the bound (or a non-finite one) are looked at again.

    Raises
    ------
    InvalidInputError
        Naming the argument, the row (``what`` and its index), the value and the range,
        with the float64 range when float64 would trace it.
    """
    limit = COORDINATE_LIMIT[precision]
    if coerced.size == 0 or (-limit <= coerced.min() and coerced.max() <= limit):
        return
    with np.errstate(invalid="ignore"):
        rows = _rows_failing(np.abs(coerced) <= limit)
        wide = np.asarray(raw[rows], dtype=np.float64)
        beyond = np.isfinite(wide) & ~(np.abs(coerced[rows]) <= limit)
    if not beyond.any():
        return
    first, column = (int(i) for i in np.argwhere(beyond)[0])
    value = wide[first, column]
    message = (
        f"{name}: {what} {int(rows[first])} has the coordinate {value:.6g}, beyond the "
        f"range |x| <= {_bound(limit)} that {precision} traces "
        f"({int(beyond.any(axis=1).sum())} out of range in all)"
    )
    if precision == "float32" and np.abs(value) <= COORDINATE_LIMIT["float64"]:
        message += f'; precision="float64" traces |x| <= {_bound(COORDINATE_LIMIT["float64"])}'
    else:
        message += "; scale the scene and its rays down"
    raise InvalidInputError(message)


def check_directions(raw: Any, coerced: Any, precision: str) -> Any:
    """Return ``coerced`` directions with subnormal components flushed to (signed) zero.

    Raises for a nonzero finite direction whose largest component is below
    ``DIRECTION_FLOOR[precision]`` (nonzero in ``raw``: a float64 direction that rounds
    to zero in float32 is refused too, not traced as a zero direction), and for a finite
    component that overflowed when converted to ``precision``. Zero and non-finite
    directions are left alone: rays define them to miss.

    Why flush: the slab test multiplies by ``1/d``, which is infinite for a subnormal
    ``d``, while the triangle test shears by ``d/d[kz]``, which is not; the two would
    disagree about the ray (a box missed, the triangle in it hit). A flushed component
    changes the direction by less than ``2^-96`` of its largest one. ``coerced`` itself
    is never written: it may be the caller's array.

    Cost: three passes over the batch when every component is at least the floor (about
    2 ms per million float32 rays), a few more when some are zero; rows out of range,
    zero or non-finite are looked at again, alone.

    Raises
    ------
    InvalidInputError
        Naming ``directions``, the row, its values and the range.
    """
    floor = DIRECTION_FLOOR[precision]
    if coerced.size == 0:
        return coerced
    magnitude = np.abs(coerced)
    smallest = magnitude.min()
    if not (smallest >= floor and magnitude.max() < np.inf):
        # Some component is small (zero, say), non-finite or overflowed: per row now.
        largest = np.maximum(magnitude[:, 0], magnitude[:, 1])
        np.maximum(largest, magnitude[:, 2], out=largest)
        if not (floor <= largest.min() and largest.max() < np.inf):
            with np.errstate(invalid="ignore"):
                rows = np.flatnonzero(~((largest >= floor) & (largest < np.inf)))
            _check_direction_rows(raw, coerced, rows, precision)
    normal = NORMAL_FLOOR[precision]
    if smallest >= normal:  # no zero, subnormal or NaN component
        return coerced
    # The magnitudes' bits less one: zero wraps to the largest integer, a subnormal stays
    # below the smallest normal number's bits (the order of the bits is the values').
    bits = magnitude.view(np.uint32 if magnitude.dtype == np.float32 else np.uint64)
    bits -= 1
    if bits.min() >= np.asarray(normal, dtype=magnitude.dtype).view(bits.dtype) - 1:
        return coerced
    subnormal = (np.abs(coerced) < normal) & (coerced != 0)
    flushed = np.where(subnormal, np.copysign(0.0, coerced), coerced)
    return flushed.astype(coerced.dtype, copy=False)


def _check_direction_rows(raw: Any, coerced: Any, rows: Any, precision: str) -> None:
    """Raise for the first of ``rows`` out of range (the slow path of :func:`check_directions`)."""
    floor = DIRECTION_FLOOR[precision]
    wide = np.asarray(raw[rows], dtype=np.float64)
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(wide).all(axis=1)
        wide_largest = np.abs(wide).max(axis=1)
        largest = np.abs(coerced[rows]).max(axis=1)
        overflow = finite & ~(largest < np.inf)
        # The floor applies to the converted values, nonzero-ness to the input's.
        small = finite & (wide_largest > 0) & ~(largest >= floor)
    if overflow.any():
        first = int(np.flatnonzero(overflow)[0])
        raise InvalidInputError(
            f"directions: row {int(rows[first])} ({wide[first].tolist()}) overflows "
            f"{precision}, whose largest value is {float(np.finfo(precision).max):.6g}; "
            f'scale it down, or use precision="{_other(precision)}"'
        )
    if small.any():
        first = int(np.flatnonzero(small)[0])
        message = (
            f"directions: row {int(rows[first])} ({wide[first].tolist()}) is too short for "
            f"{precision}: its largest component {wide_largest[first]:.6g} is below "
            f"{_bound(floor)} ({int(small.sum())} such rows in all). t is measured in units "
            f"of the direction's length, so hits would lie beyond the distances {precision} "
            "traces; scale the direction up (normalise it)"
        )
        if precision == "float32" and wide_largest[first] >= DIRECTION_FLOOR["float64"]:
            message += f' or use precision="float64" (down to {_bound(DIRECTION_FLOOR["float64"])})'
        raise InvalidInputError(message)
