"""Checks of ``(n, 3)`` array arguments as they are coerced: shape, real dtype, finite rows.

Mesh vertices and faces, query points and rays all arrive as ``(n, 3)`` arrays. These
checks raise :class:`~rayaccel.errors.InvalidInputError` naming the argument, so each
entry point reports a bad array in the same words; what an entry point does beyond them
(masked arrays, numeric range, broadcasting a single row) stays with it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from rayaccel.errors import InvalidInputError


def rows_of_three(name: str, value: object, rows: str, kind: str) -> npt.NDArray[Any]:
    """Return ``value`` as an array of shape ``(rows, 3)`` (``rows``, ``kind``: for errors).

    Raises
    ------
    InvalidInputError
        ``value`` is not an array, or not two-dimensional with three columns.
    """
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
