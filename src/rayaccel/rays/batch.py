"""Batches of rays and of their hits, as flat float32/int32 arrays (STYLE §3).

Both take ``precision="float64"`` for meshes with huge coordinates: their float arrays
are then float64 (:class:`rayaccel.scene.mesh.TriangleMesh`, ``precision``).

A :class:`RayBatch` is what every traversal takes: origins and directions
``(n, 3)`` float32 and per-ray ``tmin``/``tmax`` ``(n,)`` float32. Directions need
not be normalised; ``t`` is measured in units of the direction's length. Rays with
a zero-length or non-finite direction, a non-finite origin, or ``tmin > tmax`` are
kept in the batch and defined to miss (the traversal never enters them).

Numeric range (docs/reliability.md, "Numbers"; bounds in :mod:`rayaccel.validation`). A
finite origin coordinate beyond ``2^30`` (``2^62`` in float64), a nonzero direction whose
largest component is below ``2^-30`` (``2^-62``), or a finite direction component that
overflows the precision is refused with an :class:`InvalidInputError` naming the row: in
range, no product of the intersection tests overflows and every hit distance is finite.
Direction components below the precision's smallest normal number are flushed to
(signed) zero, so the slab test, which divides by them, and the triangle test see the
same ray. ``tmin``/``tmax`` beyond float32's range round to ``-inf``/``inf``, which keeps
the same hits.

A :class:`HitBatch` is what a closest-hit query returns: ``t`` (``inf`` on a miss),
``prim`` (``-1`` on a miss) and the barycentrics ``u, v`` of the hit point
``(1-u-v)·A + u·B + v·C``; ``stats`` maps counter names to ``(n,)`` int32 arrays
when statistics were requested.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from rayaccel.dtypes import (
    INDEX,
    REAL,
    BoolArray,
    FloatArray,
    IntArray,
    RealArray,
    check_precision,
)
from rayaccel.errors import InvalidInputError
from rayaccel.validation import check_coordinates, check_directions, check_real, reject_masked


def _as_vectors(
    name: str, value: object, n: int | None, dtype: type = REAL
) -> tuple[npt.NDArray[Any], FloatArray]:
    """Return ``(array, coerced)``: the checked input and its C-contiguous ``dtype`` copy.

    Values beyond ``dtype``'s range become ``inf`` in ``coerced`` without a warning; the
    range checks of :mod:`rayaccel.validation` compare the two and refuse them.
    """
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: expected an (n, 3) float array ({exc})") from exc
    if array.ndim == 1 and array.shape[0] == 3 and n is not None:
        array = np.broadcast_to(array, (n, 3))
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidInputError(f"{name}: expected shape (n, 3), got {array.shape}")
    check_real(name, array)
    if n is not None and array.shape[0] != n:
        raise InvalidInputError(f"{name}: expected {n} rows to match origins, got {array.shape[0]}")
    with np.errstate(over="ignore"):
        coerced: FloatArray = _writable(np.ascontiguousarray(array, dtype=dtype))
    return array, coerced


def _writable(array: FloatArray) -> FloatArray:
    """``array``, copied if read-only (a broadcast single row, a read-only memmap).

    Kernels compile one specialisation per argument type and read-only is part of the
    type: passing both kinds would compile every traversal twice.
    """
    return array if array.flags.writeable else array.copy()


def _as_interval(name: str, value: object, n: int, dtype: type = REAL) -> FloatArray:
    reject_masked(name, value)
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(
            f"{name}: expected a float scalar or an (n,) array ({exc})"
        ) from exc
    if raw.dtype.kind not in "fiu":  # strings, bools and objects are not distances
        raise InvalidInputError(
            f"{name}: expected a float scalar or an (n,) array, got {value!r:.60} "
            f"(dtype {raw.dtype})"
        )
    array = raw.astype(np.float64, copy=False)
    if array.ndim == 0:
        array = np.full(n, array, dtype=np.float64)
    if array.shape != (n,):
        raise InvalidInputError(f"{name}: expected a scalar or shape ({n},), got {array.shape}")
    if np.isnan(array).any():
        raise InvalidInputError(f"{name}: contains NaN at index {int(np.argmax(np.isnan(array)))}")
    # Beyond float32's range a bound rounds to +-inf: no hit of a ray in range lies that
    # far (docs/reliability.md, "Numbers"), so the interval keeps the same hits.
    with np.errstate(over="ignore"):
        return _writable(np.ascontiguousarray(array, dtype=dtype))


@dataclass(frozen=True, slots=True, eq=False, init=False)
class RayBatch:
    """A batch of rays ``o + t·d`` for ``t`` in ``[tmin, tmax]``.

    Parameters
    ----------
    origin, direction : (n, 3) array_like of float
        Coerced once to C-contiguous float32 (float64 with ``precision="float64"``).
        A single (3,) direction or origin is broadcast to the other's length.
    tmin, tmax : float or (n,) array_like of float, optional
        Ray interval; scalars are broadcast. Defaults ``0`` and ``inf``.
    precision : {"float32", "float64"}
        The dtype of every array. An accel converts a batch to its mesh's precision
        (:attr:`rayaccel.scene.mesh.TriangleMesh.precision`) before tracing it.

    Raises
    ------
    InvalidInputError
        Wrong shapes or dtypes, NaN in ``tmin``/``tmax``, or values outside the numeric
        range of ``precision`` (see the module docstring); the message names the
        argument, the row and the range.
    """

    origin: FloatArray
    direction: FloatArray
    tmin: FloatArray
    tmax: FloatArray

    def __init__(
        self,
        origin: npt.ArrayLike,
        direction: npt.ArrayLike,
        tmin: npt.ArrayLike | None = None,
        tmax: npt.ArrayLike | None = None,
        *,
        precision: str = "float32",
    ) -> None:
        precision = check_precision(precision)
        dtype = np.float64 if precision == "float64" else REAL
        reject_masked("origins", origin)
        reject_masked("directions", direction)
        origin_raw = np.asarray(origin)
        direction_raw = np.asarray(direction)
        n = None
        if origin_raw.ndim == 2:
            n = origin_raw.shape[0]
        elif direction_raw.ndim == 2:
            n = direction_raw.shape[0]
        origin_in, origin_f32 = _as_vectors("origins", origin_raw, n, dtype)
        n = origin_f32.shape[0]
        direction_in, direction_f32 = _as_vectors("directions", direction_raw, n, dtype)
        # The numeric range (docs/reliability.md, "Numbers"): finite origins within
        # COORDINATE_LIMIT, nonzero directions not below DIRECTION_FLOOR, subnormal
        # direction components flushed to zero.
        check_coordinates("origins", origin_in, origin_f32, precision, "row")
        direction_f32 = check_directions(direction_in, direction_f32, precision)
        # The dataclass is frozen: fields are set once, here, through object.__setattr__.
        object.__setattr__(self, "origin", origin_f32)
        object.__setattr__(self, "direction", direction_f32)
        lo = _as_interval("tmin", 0.0 if tmin is None else tmin, n, dtype)
        hi = _as_interval("tmax", np.inf if tmax is None else tmax, n, dtype)
        object.__setattr__(self, "tmin", lo)
        object.__setattr__(self, "tmax", hi)

    @property
    def precision(self) -> str:
        """``"float32"`` or ``"float64"``: the dtype of every array of the batch."""
        return str(self.origin.dtype)

    def astype(self, precision: str) -> RayBatch:
        """Return this batch in ``precision`` (itself when it already is)."""
        if check_precision(precision) == self.precision:
            return self
        return RayBatch(self.origin, self.direction, self.tmin, self.tmax, precision=precision)

    def __len__(self) -> int:
        return int(self.origin.shape[0])

    @property
    def n_rays(self) -> int:
        """Number of rays."""
        return int(self.origin.shape[0])

    def valid(self) -> BoolArray:
        """Return which rays can hit anything.

        A valid ray has a finite origin, a finite non-zero direction and ``tmin <= tmax``.
        """
        finite = np.isfinite(self.origin).all(axis=1) & np.isfinite(self.direction).all(axis=1)
        nonzero = (self.direction != 0).any(axis=1)
        valid: BoolArray = finite & nonzero & (self.tmin <= self.tmax)
        return valid

    @classmethod
    def concatenate(cls, batches: Sequence[RayBatch]) -> RayBatch:
        """Return one batch of the rays of ``batches``, in order (at least one)."""
        if len(batches) == 1:
            return batches[0]
        return cls(
            np.concatenate([b.origin for b in batches]),
            np.concatenate([b.direction for b in batches]),
            np.concatenate([b.tmin for b in batches]),
            np.concatenate([b.tmax for b in batches]),
            precision=batches[0].precision,
        )

    def subset(
        self, index: slice | npt.NDArray[np.bool_] | npt.NDArray[np.integer[Any]]
    ) -> RayBatch:
        """Return the rays selected by ``index``.

        Parameters
        ----------
        index : slice, (n,) bool ndarray or (k,) int ndarray
            The rows to keep, as for numpy indexing.

        Returns
        -------
        RayBatch
            A new batch of the selected rays (copies of the rows).
        """
        return RayBatch(
            self.origin[index],
            self.direction[index],
            self.tmin[index],
            self.tmax[index],
            precision=self.precision,
        )


@dataclass(frozen=True, slots=True, eq=False)
class HitBatch:
    """Closest hits of a :class:`RayBatch`.

    Attributes
    ----------
    t : (n,) float32 (float64 for float64 rays)
        Hit distance in units of the ray direction; ``inf`` on a miss.
    prim : (n,) int32
        Index of the hit triangle in the mesh; ``-1`` on a miss.
    u, v : (n,) float32 (float64 for float64 rays)
        Barycentric coordinates of the hit on the triangle (0 on a miss).
    stats : dict of str to (n,) int32, or None
        Per-ray traversal counters by name, when requested.
    """

    t: RealArray
    prim: IntArray
    u: RealArray
    v: RealArray
    stats: dict[str, IntArray] | None = None

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def hit(self) -> BoolArray:
        """``(n,)`` bool: whether each ray hit something."""
        return self.prim >= 0

    def points(self, rays: RayBatch) -> RealArray:
        """Return the ``(n, 3)`` hit points ``o + t·d`` (NaN on a miss), in the rays' dtype."""
        dtype = rays.origin.dtype
        t = np.where(self.hit, self.t, np.nan).astype(dtype)
        return (rays.origin + t[:, None] * rays.direction).astype(dtype)

    @staticmethod
    def empty(n: int, precision: str = "float32") -> HitBatch:
        """Return ``n`` misses (``t``, ``u``, ``v`` in ``precision``)."""
        dtype = np.float64 if check_precision(precision) == "float64" else REAL
        return HitBatch(
            t=np.full(n, np.inf, dtype=dtype),
            prim=np.full(n, -1, dtype=INDEX),
            u=np.zeros(n, dtype=dtype),
            v=np.zeros(n, dtype=dtype),
        )
