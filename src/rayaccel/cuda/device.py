"""Traversals on an NVIDIA GPU: device-resident layouts, rays in or out of device memory.

:meth:`rayaccel.api.Accel.trace` with ``device="cuda"`` calls the registered traversal
as on the CPU, inside :func:`on_cuda`: the traversal derives its layout exactly as it
always does (memoised in the accel's cache) and hands it to
:func:`rayaccel.trace.run.run_trace`, which passes the launch to the :class:`CudaTarget`
set here instead of running its CPU kernel. The target copies the layout's arrays to
the GPU once (kept in the same cache, so a refit, which swaps the cache, also drops
them), compiles the traversal's CPU per-ray body for CUDA
(:mod:`rayaccel.cuda.skeleton`) and launches it. Rays come as :class:`DeviceRays`:
either copied from numpy (hits are copied back), or taken as they are from any array
with ``__cuda_array_interface__`` (CuPy, PyTorch, Numba device arrays), in which case
hits stay on the GPU as Numba device arrays, which CuPy and PyTorch wrap without a
copy.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from rayaccel.counters import COUNTER_NAMES, N_COUNTERS
from rayaccel.errors import BackendUnavailableError, InvalidInputError, TraversalOverflowError
from rayaccel.queries import query_constant
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.trace import skeleton as cpu_skeleton
from rayaccel.trace.run import TRACE_TARGET

#: Traversals whose per-ray body compiles for CUDA (checked by tests/cuda).
CUDA_TRAVERSALS = (
    "bvh2.stack", "bvh2.restart_trail", "bvh2.parent_link", "bvh2.bitstack",
    "bvh2.perfect_hash", "kdtree.stack", "kdtree.ropes", "kdtree.short_stack",
    "kdtree.restart", "kdtree.backtrack", "grid.dda", "grid.skip",
)  # fmt: skip


def cuda_module() -> Any:
    """Return ``numba.cuda`` with a GPU (or the simulator) behind it, or raise why not."""
    try:
        from numba import cuda
    except ImportError as exc:  # pragma: no cover - numba-cuda is a dependency of [gpu]
        raise BackendUnavailableError(
            "device='cuda' needs numba-cuda: pip install 'rayaccel[gpu]'"
        ) from exc
    if not cuda.is_available():
        raise BackendUnavailableError(
            "device='cuda': no CUDA GPU or driver found (numba.cuda.is_available() is False); "
            "set NUMBA_ENABLE_CUDASIM=1 to run the kernels in numba's CUDA simulator"
        )
    return cuda


def is_device_array(value: Any) -> bool:
    """Whether ``value`` lives in GPU memory (has ``__cuda_array_interface__``).

    Under numba's CUDA simulator, its stand-in device arrays count too.
    """
    if hasattr(value, "__cuda_array_interface__"):
        return True
    from numba.cuda import config

    return bool(config.ENABLE_CUDASIM) and hasattr(value, "copy_to_host")


@dataclass(frozen=True, slots=True)
class DeviceRays:
    """Rays in GPU memory, in place of a :class:`RayBatch` for a CUDA query.

    ``origin``/``direction`` are ``(n, 3)`` float32 and ``tmin``/``tmax`` ``(n,)`` float32
    device arrays. ``on_device`` says whether the caller gave device arrays (hits then
    stay on the device) or numpy arrays (hits are copied back).
    """

    origin: Any
    direction: Any
    tmin: Any
    tmax: Any
    on_device: bool
    precision: str = "float32"

    @property
    def n_rays(self) -> int:
        """Number of rays."""
        return int(self.origin.shape[0])

    def astype(self, precision: str) -> DeviceRays:
        """Return ``self`` for float32; the GPU kernels trace float32 rays only."""
        if precision != "float32":
            raise InvalidInputError("device='cuda' traces float32 accels only")
        return self


def _as_device(cuda: Any, value: Any) -> Any:
    """Return a Numba view of a device array (no copy); simulator arrays as they are."""
    if hasattr(value, "__cuda_array_interface__"):
        return cuda.as_cuda_array(value)
    return value


def _device_vectors(cuda: Any, name: str, value: Any) -> Any:
    array = _as_device(cuda, value)
    if array.ndim != 2 or array.shape[1] != 3 or array.dtype != np.float32:
        raise InvalidInputError(
            f"{name}: a device array must be (n, 3) float32, got {array.shape} {array.dtype}"
        )
    return array


def _device_interval(cuda: Any, name: str, value: Any, n: int) -> Any:
    from rayaccel.cuda.skeleton import BLOCK_THREADS, fill

    if is_device_array(value):
        array = _as_device(cuda, value)
        if array.shape != (n,) or array.dtype != np.float32:
            raise InvalidInputError(
                f"{name}: a device array must be ({n},) float32, got {array.shape} {array.dtype}"
            )
        return array
    host = np.asarray(value)
    if host.ndim == 0:
        scalar = float(host)
        if np.isnan(scalar):
            raise InvalidInputError(f"{name}: must not be NaN")
        out = cuda.device_array(n, dtype=np.float32)
        if n:
            fill[-(-n // BLOCK_THREADS), BLOCK_THREADS](out, np.float32(scalar))
        return out
    checked = RayBatch(np.zeros((n, 3)), np.ones((n, 3)), host, None)
    if name == "tmax":
        checked = RayBatch(np.zeros((n, 3)), np.ones((n, 3)), None, host)
    return cuda.to_device(checked.tmin if name == "tmin" else checked.tmax)


def device_rays(origins: Any, directions: Any, tmin: Any, tmax: Any) -> DeviceRays:
    """Return the rays of a CUDA query: device arrays as given, or numpy rays copied over.

    Device arrays are used in place (no copy), so they must already be float32 and
    ``(n, 3)``; ``tmin``/``tmax`` may be scalars, numpy or device arrays. Numpy input
    is validated and coerced as :class:`RayBatch` does, then copied to the GPU.
    """
    cuda = cuda_module()
    if is_device_array(origins) or is_device_array(directions):
        origin = _device_vectors(cuda, "origins", origins)
        direction = _device_vectors(cuda, "directions", directions)
        n = origin.shape[0]
        if direction.shape[0] != n:
            raise InvalidInputError(
                f"directions: expected {n} rows like origins, got {direction.shape[0]}"
            )
        lo = _device_interval(cuda, "tmin", tmin, n)
        hi = _device_interval(cuda, "tmax", tmax, n)
        return DeviceRays(origin, direction, lo, hi, on_device=True)
    rays = RayBatch(origins, directions, tmin, tmax)
    return from_ray_batch(rays)


def from_ray_batch(rays: RayBatch) -> DeviceRays:
    """Copy a float32 :class:`RayBatch` to the GPU."""
    cuda = cuda_module()
    if rays.precision != "float32":
        raise InvalidInputError("device='cuda' traces float32 rays only")
    return DeviceRays(
        cuda.to_device(rays.origin),
        cuda.to_device(rays.direction),
        cuda.to_device(rays.tmin),
        cuda.to_device(rays.tmax),
        on_device=False,
    )


class CudaTarget:
    """Runs :func:`rayaccel.trace.run.run_trace`'s launches on the GPU (see the module docstring).

    ``memo`` maps ``id(host array)`` to ``(host array, device copy)``; it lives in the
    accel's cache, so layouts are copied once per accel and dropped with the cache.
    """

    def __init__(self, memo: dict[int, tuple[Any, Any]]):
        self.memo = memo
        self.cuda = cuda_module()

    def upload(self, arrays: Any) -> Any:
        """Return ``arrays`` (a NamedTuple) with every numpy array replaced by its device copy."""
        fields = []
        for value in arrays:
            if isinstance(value, np.ndarray):
                held = self.memo.get(id(value))
                if held is None or held[0] is not value:
                    held = (value, self.cuda.to_device(np.ascontiguousarray(value)))
                    self.memo[id(value)] = held
                value = held[1]
            fields.append(value)
        return type(arrays)(*fields)

    def run(
        self,
        kernel_for: Any,
        layout_arrays: Any,
        rays: Any,
        query: str,
        stats: bool,
        overflow_hint: str,
    ) -> HitBatch:
        """Launch the traversal behind ``kernel_for`` over ``rays`` (:class:`DeviceRays`)."""
        from rayaccel.cuda.scratch import check_capacity
        from rayaccel.cuda.skeleton import BLOCK_THREADS, blocks_for, reset_hits, trace_kernel

        make_scratch, trace_rays = body_of(kernel_for)
        check_capacity(make_scratch, layout_arrays)
        layout = self.upload(layout_arrays)
        if not isinstance(rays, DeviceRays):
            rays = from_ray_batch(rays)
        cuda = self.cuda
        n = rays.n_rays
        hit_t = cuda.device_array(n, dtype=np.float32)
        hit_prim = cuda.device_array(n, dtype=np.int32)
        hit_u = cuda.device_array(n, dtype=np.float32)
        hit_v = cuda.device_array(n, dtype=np.float32)
        counters = cuda.device_array((n if stats else 0, N_COUNTERS), dtype=np.int32)
        if n == 0:
            return _hits(hit_t, hit_prim, hit_u, hit_v, counters, stats, rays.on_device)
        reset_hits[-(-n // BLOCK_THREADS), BLOCK_THREADS](hit_t, hit_prim, hit_u, hit_v, counters)
        work = cuda.to_device(np.zeros(1, dtype=np.int32))
        overflow = cuda.to_device(np.zeros(1, dtype=np.int32))
        kernel = trace_kernel(trace_rays, make_scratch, query_constant(query), bool(stats))
        kernel[blocks_for(n), BLOCK_THREADS](
            layout, rays.origin, rays.direction, rays.tmin, rays.tmax,
            hit_t, hit_prim, hit_u, hit_v, counters, work, overflow,
        )  # fmt: skip
        lost = int(overflow.copy_to_host()[0])
        if lost:
            raise TraversalOverflowError(
                f"{lost} rays overflowed the traversal stack; {overflow_hint}"
            )
        return _hits(hit_t, hit_prim, hit_u, hit_v, counters, stats, rays.on_device)


def _hits(
    hit_t: Any, hit_prim: Any, hit_u: Any, hit_v: Any, counters: Any, stats: bool, on_device: bool
) -> HitBatch:
    """Wrap device outputs as a HitBatch: device arrays, or numpy copies."""
    if on_device:
        columns = {name: counters[:, i] for i, name in enumerate(COUNTER_NAMES)}
        return HitBatch(hit_t, hit_prim, hit_u, hit_v, stats=columns if stats else None)
    columns_host = None
    if stats:
        table = counters.copy_to_host()
        columns_host = {
            name: np.ascontiguousarray(table[:, i]) for i, name in enumerate(COUNTER_NAMES)
        }
    return HitBatch(
        hit_t.copy_to_host(),
        hit_prim.copy_to_host(),
        hit_u.copy_to_host(),
        hit_v.copy_to_host(),
        stats=columns_host,
    )


def body_of(kernel_for: Any) -> tuple[Any, Any]:
    """Return ``(make_scratch, trace_rays)`` of a traversal's ``kernel_for``, or raise.

    Every traversal that runs in the shared skeleton passes
    ``functools.partial(rayaccel.trace.skeleton.trace_kernel, make_scratch, trace_rays)``
    (:func:`rayaccel.trace.run.body_kernels`); others have no per-ray body to compile.
    """
    if isinstance(kernel_for, functools.partial) and kernel_for.func is cpu_skeleton.trace_kernel:
        make_scratch, trace_rays = kernel_for.args
        return make_scratch, trace_rays
    raise InvalidInputError("this traversal has no per-ray body to run on CUDA")


@contextlib.contextmanager
def on_cuda(memo: dict[int, tuple[Any, Any]]) -> Iterator[CudaTarget]:
    """Run every :func:`rayaccel.trace.run.run_trace` inside the block on the GPU."""
    target = CudaTarget(memo)
    token = TRACE_TARGET.set(target)
    try:
        yield target
    finally:
        TRACE_TARGET.reset(token)


def hit_mask(prim: Any) -> Any:
    """``prim >= 0`` as a device bool array (``occluded`` with device arrays)."""
    from rayaccel.cuda.skeleton import BLOCK_THREADS
    from rayaccel.cuda.skeleton import hit_mask as mask_kernel

    cuda = cuda_module()
    n = prim.shape[0]
    out = cuda.device_array(n, dtype=np.bool_)
    if n:
        mask_kernel[-(-n // BLOCK_THREADS), BLOCK_THREADS](prim, out)
    return out
