"""Batches of rays too large to copy at once, and Dask arrays of rays.

:class:`rayaccel.rays.batch.RayBatch` makes float32 copies of its inputs (32 bytes a
ray). A query over more rays than :data:`rayaccel.config.RAY_BUDGET` allows is traced
by :func:`trace_in_chunks`: one slice of the inputs at a time is copied and traced,
and its hits are written into outputs allocated once, so memory grows by the outputs
and one chunk's copies, never by a float32 copy of the whole input.

:func:`trace_dask` takes Dask arrays (``dask.array``) and returns Dask arrays: each
block of rows becomes one task tracing its rays with the ``Accel``, which enters the
task graph once, under one key (``dask.delayed``), so a distributed scheduler ships
it to each worker once however many blocks there are.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

import numpy as np

from rayaccel.dtypes import INDEX, REAL
from rayaccel.errors import InvalidInputError
from rayaccel.rays.batch import HitBatch, RayBatch

#: Bytes of the float32 copies ``RayBatch`` makes per ray (origin, direction, tmin, tmax).
RAY_COPY_BYTES = 32


def is_dask_array(value: Any) -> bool:
    """Return whether ``value`` is a Dask array (without importing Dask)."""
    return type(value).__module__.startswith("dask.") and hasattr(value, "__dask_graph__")


def rays_per_chunk(budget: int) -> int:
    """Return how many rays one chunk holds within ``budget`` bytes of copies."""
    return max(4096, int(budget) // RAY_COPY_BYTES)


def count_rays(origins: Any, directions: Any) -> int | None:
    """Return the number of rays of ``(origins, directions)``, or None if not an (n, 3) pair.

    A (3,) origin or direction is broadcast to the other's length, as in ``RayBatch``.
    Nothing is copied; shapes the batch refuses return None and are left to it.
    """
    shapes = [np.shape(origins), np.shape(directions)]
    rows = [shape[0] for shape in shapes if len(shape) == 2]
    return rows[0] if rows else None


def _rows(value: Any, begin: int, end: int) -> Any:
    """Rows ``begin:end`` of a per-ray input; a scalar or a broadcast (3,) vector as it is."""
    array = np.asarray(value)
    if array.ndim == 0 or (array.ndim == 1 and array.shape[0] == 3 and np.ndim(value) == 1):
        return value
    return array[begin:end]


def _per_ray(value: Any, n: int) -> Any:
    """``value`` unless it is a scalar; used for tmin/tmax, which may be (n,) arrays."""
    array = np.asarray(value)
    if array.ndim == 1 and array.shape[0] != n:
        raise InvalidInputError(f"expected a scalar or shape ({n},), got {array.shape}")
    return value


def trace_in_chunks(
    trace: Callable[[RayBatch], HitBatch],
    origins: Any,
    directions: Any,
    tmin: Any,
    tmax: Any,
    n: int,
    chunk: int,
    precision: str = "float32",
) -> HitBatch:
    """Trace ``n`` rays ``chunk`` at a time with ``trace``; return all hits in input order.

    ``origins``/``directions`` are (n, 3) (or one of them (3,)), ``tmin``/``tmax``
    scalars or (n,); each chunk is validated by ``RayBatch`` as a whole batch would be,
    in ``precision`` (the accel's).
    """
    tmin = _per_ray(tmin, n)
    tmax = _per_ray(tmax, n)
    real = np.float64 if precision == "float64" else REAL
    t = np.empty(n, dtype=real)
    prim = np.empty(n, dtype=INDEX)
    u = np.empty(n, dtype=real)
    v = np.empty(n, dtype=real)
    stats: dict[str, Any] | None = None
    for begin in range(0, n, chunk):
        end = min(n, begin + chunk)
        try:
            rays = RayBatch(
                _rows(origins, begin, end),
                _rows(directions, begin, end),
                _rows(tmin, begin, end),
                _rows(tmax, begin, end),
                precision=precision,
            )
        except InvalidInputError as exc:
            raise InvalidInputError(f"rays {begin}..{end - 1}: {exc}") from exc
        hits = trace(rays)
        t[begin:end] = hits.t
        prim[begin:end] = hits.prim
        u[begin:end] = hits.u
        v[begin:end] = hits.v
        if hits.stats is not None:
            if stats is None:
                stats = {k: np.empty(n, dtype=a.dtype) for k, a in hits.stats.items()}
            for name, values in hits.stats.items():
                stats[name][begin:end] = values
    return HitBatch(t, prim, u, v, stats=stats)


def _dask_array() -> Any:
    """Return ``dask.array``, imported on first use (Dask is optional), untyped."""
    return importlib.import_module("dask.array")


def _dask_rows(value: Any, chunks: tuple[int, ...], name: str) -> Any:
    """Return a per-ray Dask input as a column with the rays' row chunks; a scalar as it is."""
    da = _dask_array()

    if not is_dask_array(value) and np.ndim(value) == 0:
        return float(value)
    array = da.asarray(value)
    if array.ndim != 1 or array.shape[0] != sum(chunks):
        raise InvalidInputError(f"{name}: expected a scalar or shape ({sum(chunks)},), "
                                f"got {array.shape}")  # fmt: skip
    # A column, so map_blocks pairs its blocks with the rays' row blocks (a 1-D array
    # would be aligned with their last axis, numpy's broadcasting rule)
    return array.rechunk((chunks,))[:, None]


def _column(block: Any) -> Any:
    """Return a (k, 1) block of a per-ray input as (k,); a scalar as it is."""
    return block if np.ndim(block) == 0 else np.ravel(block)


def trace_dask(
    accel: Any,
    origins: Any,
    directions: Any,
    tmin: Any,
    tmax: Any,
    *,
    query: str,
    traversal: str | None,
    options: dict[str, Any],
) -> HitBatch:
    """Return the hits of Dask arrays of rays as a :class:`HitBatch` of Dask arrays.

    ``origins`` and ``directions`` are (n, 3) arrays (Dask or numpy; they are chunked
    by rows alike, all three columns in one block); ``tmin``/``tmax`` scalars or (n,).
    Nothing is traced until the result is computed. Each task traces one block with
    ``accel.trace``, so results equal a numpy call's ray for ray.
    """
    da = _dask_array()
    from dask.delayed import delayed

    o = da.asarray(origins)
    d = da.asarray(directions)
    for name, array in (("origins", o), ("directions", d)):
        if array.ndim != 2 or array.shape[1] != 3:
            raise InvalidInputError(f"{name}: expected shape (n, 3), got {array.shape}")
    if o.shape[0] != d.shape[0]:
        raise InvalidInputError(
            f"directions: expected {o.shape[0]} rows to match origins, got {d.shape[0]}"
        )
    o = o.rechunk({1: 3})
    rows = o.chunks[0]
    d = d.rechunk((rows, 3))
    lo = _dask_rows(tmin, rows, "tmin")
    hi = _dask_rows(tmax, rows, "tmax")
    # One key for this Accel: every block's task depends on it, so it is sent once
    token = f"rayaccel-accel-{accel.key}-{accel.mesh.digest()[:16]}-{id(accel):x}"
    shared = delayed(accel, name=token, pure=True)
    real = np.float64 if accel.precision == "float64" else REAL
    fields = np.dtype([("t", real), ("prim", INDEX), ("u", real), ("v", real)])

    def trace_block(o_block: Any, d_block: Any, lo_block: Any, hi_block: Any, acc: Any) -> Any:
        hits = acc.trace(
            RayBatch(
                o_block, d_block, _column(lo_block), _column(hi_block), precision=acc.precision
            ),
            query=query,
            traversal=traversal,
            **options,
        )
        out = np.empty(len(hits), dtype=fields)
        out["t"], out["prim"], out["u"], out["v"] = hits.t, hits.prim, hits.u, hits.v
        return out

    blocks = da.map_blocks(trace_block, o, d, lo, hi, shared, drop_axis=1, dtype=fields,
                           chunks=(rows,), meta=np.empty(0, dtype=fields))  # fmt: skip
    return HitBatch(blocks["t"], blocks["prim"], blocks["u"], blocks["v"])
