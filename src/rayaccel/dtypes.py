"""The dtypes every array in rayaccel uses (STYLE §3): float32 geometry, int32 indices.

Geometry is float32 unless a mesh asks for ``precision="float64"`` (huge coordinates):
its triangle rows, rays and hits are then float64, its structure's boxes stay float32.
"""

from __future__ import annotations

from typing import Any, TypeAlias

import numpy as np
import numpy.typing as npt

from rayaccel.errors import InvalidInputError

REAL = np.float32
INDEX = np.int32
COUNT = np.int32
TOTAL = np.int64

FloatArray: TypeAlias = npt.NDArray[np.float32]
#: float32 or float64 (triangle rows, rays and hits of a mesh of either precision).
RealArray: TypeAlias = npt.NDArray[np.floating[Any]]
IntArray: TypeAlias = npt.NDArray[np.int32]
BoolArray: TypeAlias = npt.NDArray[np.bool_]
Int64Array: TypeAlias = npt.NDArray[np.int64]

#: The precisions of a mesh's triangle rows and of the rays and hits traced against them.
PRECISIONS = ("float32", "float64")


def check_precision(precision: object) -> str:
    """Return ``precision`` if it is ``"float32"`` or ``"float64"``; raise otherwise.

    Raises
    ------
    InvalidInputError
        Anything else (the message names the argument and the accepted values).
    """
    if not isinstance(precision, str) or precision not in PRECISIONS:
        raise InvalidInputError(
            f"precision: expected one of {PRECISIONS}, got {precision!r} (float64 keeps "
            "vertices, rays and hit distances in double precision; BVH builders only)"
        )
    return precision
