"""Process-wide settings read from the environment, and the numba threading layer.

``RAYACCEL_DEBUG=1``   run ``validate()`` after every build (pbrt's CHECK/DCHECK split).
``RAYACCEL_SCENE_PATH`` os.pathsep-separated folders searched by ``rayaccel.scenes.get(name)``.
``RAYACCEL_RAY_BUDGET`` bytes of ray copies a query may make at once (default 1 GiB): a
                     larger numpy batch is traced in chunks (:mod:`rayaccel.chunked`).

Numba's default ``workqueue`` threading layer aborts the process when two Python
threads enter parallel kernels at once. We therefore ask for a thread-safe layer
(``omp`` or ``tbb``) when one is installed and otherwise serialise parallel
kernel launches behind :data:`PARALLEL_LOCK` (see :func:`parallel_section`).
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator

import numba

DEBUG: bool = os.environ.get("RAYACCEL_DEBUG", "0") not in ("", "0", "false", "False")
SCENE_PATH_VAR = "RAYACCEL_SCENE_PATH"


def _budget_from_environment() -> int:
    text = os.environ.get("RAYACCEL_RAY_BUDGET", "")
    try:
        value = int(float(text)) if text else 1 << 30
    except ValueError:
        raise ValueError(f"RAYACCEL_RAY_BUDGET: expected a number of bytes, got {text!r}") from None
    if value < 1 << 16:
        raise ValueError(f"RAYACCEL_RAY_BUDGET: expected at least 65536 bytes, got {value}")
    return value


#: Bytes of float32 ray copies (origins, directions, interval) one query makes at once.
RAY_BUDGET: int = _budget_from_environment()

if "NUMBA_THREADING_LAYER" not in os.environ:
    # OpenMP first (libgomp ships with gcc), then TBB (skipped with a warning when the
    # installed TBB is too old for numba); workqueue last, guarded by the lock below.
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

PARALLEL_LOCK = threading.RLock()


def threading_layer_is_threadsafe() -> bool:
    """Return whether the active numba threading layer tolerates concurrent launches."""
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet: layer not chosen
        return False
    return layer in ("tbb", "omp")


@contextlib.contextmanager
def parallel_section() -> Iterator[None]:
    """Serialise parallel kernel launches unless the threading layer is thread-safe."""
    if threading_layer_is_threadsafe():
        yield
        return
    with PARALLEL_LOCK:
        yield
