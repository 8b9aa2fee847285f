"""The dtypes every array in rayaccel uses (STYLE §3): float32 geometry, int32 indices."""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
import numpy.typing as npt

REAL = np.float32
INDEX = np.int32
COUNT = np.int32
TOTAL = np.int64

FloatArray: TypeAlias = npt.NDArray[np.float32]
IntArray: TypeAlias = npt.NDArray[np.int32]
BoolArray: TypeAlias = npt.NDArray[np.bool_]
Int64Array: TypeAlias = npt.NDArray[np.int64]
