"""One decorator policy for every CPU kernel (STYLE §4.1), and where compiled kernels are cached.

``fastmath`` keeps IEEE infinities and NaN (no ``nnan``/``ninf``): slab tests for
axis-parallel rays rely on ``1/±0 = ±inf``. ``error_model="numpy"`` makes division
by zero give ``inf`` instead of raising.

``contract`` lets LLVM fuse multiply-adds. The watertight triangle test stays exact
under it because its edge functions are evaluated in float64 (``kernels/triangle.py``);
in float32 the fused ``Cx*By - Cy*Bx`` is not antisymmetric and opens cracks
(``tests/kernels/test_triangle.py`` holds the repros).

Cache location: numba invalidates a cached kernel only when *its own* file changes,
so a kernel that inlines a helper from another file keeps stale machine code after
that helper is edited (STYLE §4.3 rule 4). We therefore key the cache folder by a
digest of every rayaccel source file: ``$NUMBA_CACHE_DIR/rayaccel-<digest>`` (or
``~/.cache/rayaccel/numba/rayaccel-<digest>`` when ``NUMBA_CACHE_DIR`` is unset).
Any source change starts a fresh cache; ``rayaccel cache clear`` removes old ones.

Within one cache folder, numba keys a closure's kernels by a pickle of its closure
cells. A compiled function in a cell pickles with a per-process id, so a kernel
factory that captures one (the shared traversal skeleton of :mod:`rayaccel.trace`
captures each traversal's per-ray body) would miss the cache in every new process.
:class:`StableClosureCache` keys such a cell by the function's module, qualified name
and (recursively) its own closure instead: the source digest of the folder already
pins the code behind those names.

Symbol names: numba names a compiled function after its module, qualified name, flags,
argument types and a counter of the process that compiled it, and a kernel loaded
from the cache brings the machine code of the kernels it calls under those names.
Closures of one factory share a qualified name, and often their argument types
(``bvh2.bitstack`` and ``bvh2.parent_link`` walk one layout; a traversal's statistics
variants take the same arrays), so two of them compiled in different processes can
carry the same symbol; loaded into one process, every caller then runs whichever was
loaded first (the statistics kernel ran the plain body and counted nothing).
:func:`cpu_kernel` therefore appends :func:`closure_digest` to a closure's qualified
name, which also gives each closure its own index and data files in the cache
(numba names them after the qualified name), so processes compiling kernels of one
factory at once (``rayaccel cache warm --jobs``) never rewrite each other's index.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
from llvmlite import ir
from numba.core import cgutils, inline_closurecall, serialize, types
from numba.core.caching import FunctionCache
from numba.core.dispatcher import Dispatcher
from numba.core.errors import NumbaPerformanceWarning
from numba.extending import intrinsic

from rayaccel._inline_copy import share_copy_memo

# Before any kernel compiles: numba's inliner copies each inlined callee without the
# quadratic block-by-block copy (:mod:`rayaccel._inline_copy`).
share_copy_memo(inline_closurecall)

FASTMATH = frozenset({"nsz", "arcp", "contract"})


def source_digest() -> str:
    """Return a digest of every ``.py`` file of the installed rayaccel package."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha1()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def cache_root() -> Path:
    """Return the folder that holds every rayaccel kernel cache (one subfolder per digest)."""
    base = os.environ.get("NUMBA_CACHE_DIR")
    if base:
        return Path(base)
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "rayaccel" / "numba"


#: The cache folder of this exact source tree (set before any kernel is decorated).
CACHE_DIR = cache_root() / f"rayaccel-{source_digest()}"
numba.config.CACHE_DIR = str(CACHE_DIR)


def _stable_cell(value: Any) -> Any:
    """Return a process-independent stand-in for a closure cell's value (see the module)."""
    if isinstance(value, Dispatcher):
        return ("compiled", *_stable_function(value.py_func))
    return value


def _stable_function(func: Callable[..., Any]) -> tuple[Any, ...]:
    cells = tuple(_stable_cell(c.cell_contents) for c in func.__closure__ or ())
    return (func.__module__, func.__qualname__, cells)


def closure_digest(func: Callable[..., Any]) -> str:
    """Return a process-independent digest of ``func``'s closure cells (:func:`_stable_cell`)."""
    return hashlib.sha256(serialize.dumps(_stable_function(func)[2])).hexdigest()


class StableClosureCache(FunctionCache):  # type: ignore[misc]
    """numba's on-disk function cache, keyed by :func:`_stable_cell` for closure cells."""

    def __init__(self, py_func: Callable[..., Any]) -> None:
        super().__init__(py_func)
        self._cells = closure_digest(py_func)

    def _index_key(self, sig: Any, codegen: Any) -> Any:
        code = hashlib.sha256(self._py_func.__code__.co_code).hexdigest()
        return (sig, codegen.magic_tuple(), (code, self._cells))


#: ``parallel=`` options that run numba's parfor pipeline only for its IR clean-up (copy
#: propagation and dead-code removal over the whole function) and convert nothing to
#: parallel code: the kernel stays serial. See :func:`cpu_kernel`'s ``simplify``.
SIMPLIFY_ONLY = {
    "comprehension": False, "reduction": False, "inplace_binop": False, "setitem": False,
    "numpy": False, "stencil": False, "fusion": False, "prange": False,
}  # fmt: skip


def _without_parallel_warning(compile_: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap a dispatcher's ``compile`` to drop numba's warning that nothing was parallelised."""

    def compile_quietly(sig: Any) -> Any:
        with warnings.catch_warnings():
            warnings.filterwarnings(
                "ignore",
                message=r"(?s).*no transformation for parallel execution was possible",
                category=NumbaPerformanceWarning,
            )
            return compile_(sig)

    return compile_quietly


def cpu_kernel(
    *, parallel: bool = False, simplify: bool = False, exact: bool = False, nrt: bool = True
) -> Callable[[Callable[..., Any]], Any]:
    """Return the ``njit`` decorator used for every CPU kernel.

    Parameters
    ----------
    parallel : bool
        Compile ``prange`` loops as parallel loops.
    simplify : bool
        For serial kernels that inline helpers taking many arrays, per call of a
        loop: run numba's copy propagation over the kernel (:data:`SIMPLIFY_ONLY`).
        Inlining binds each array argument to a new variable, and numba increments
        and decrements the array's reference count (two atomic calls) around every
        such binding; propagating the copies removes them (on SBVH's top-down loop,
        two inlined split functions per node, they were a fifth of its time).
        numba's "no parallel transformation" warning is silenced while the kernel
        compiles.
    exact : bool
        Leave out the ``contract`` fast-math flag, so no multiply and add are fused:
        products round as numpy's do, for kernels whose results must match numpy's
        bit for bit on every machine.
    nrt : bool
        False compiles the kernel without numba's runtime: it allocates nothing, and
        no array it binds, passes or unpacks is reference-counted (numba's ``_nrt``
        flag). For hot loops that inline helpers taking arrays; the caller owns the
        arrays for the duration of the call.
    """
    if parallel and simplify:
        raise ValueError("simplify is for serial kernels (parallel kernels already simplify)")
    jit = numba.njit(
        parallel=dict(SIMPLIFY_ONLY) if simplify else parallel,
        cache=True,
        nogil=True,
        fastmath=set(FASTMATH) - {"contract"} if exact else set(FASTMATH),
        error_model="numpy",
        **({} if nrt else {"_nrt": False}),
    )

    def decorate(func: Callable[..., Any]) -> Any:
        if func.__closure__:
            # One name per closure (see the module docstring, Symbol names).
            func.__qualname__ = f"{func.__qualname__}_{closure_digest(func)[:16]}"
        dispatcher = jit(func)
        dispatcher._cache = StableClosureCache(func)
        if simplify:
            dispatcher.compile = _without_parallel_warning(dispatcher.compile)
        return dispatcher

    return decorate


def cpu_inline(fn: Callable[..., Any]) -> Any:
    """Compile a leaf helper that is always inlined into its callers."""
    return numba.njit(
        inline="always", cache=True, nogil=True, fastmath=set(FASTMATH), error_model="numpy"
    )(fn)


@intrinsic
def prefetch_row(typingctx: Any, array: Any, row: Any) -> Any:
    """Hint the CPU to start loading row ``row`` of a 2D array (``llvm.prefetch``, no fault).

    Used by traversals to overlap the memory latency of the next node with the box
    tests of the current one. Out-of-range rows are harmless (prefetches never fault).
    """
    sig = types.void(array, row)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        array_type = signature.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        index = context.cast(builder, args[1], signature.args[1], types.intp)
        zero = context.get_constant(types.intp, 0)
        pointer = cgutils.get_item_pointer(
            context, builder, array_type, view, [index, zero], wraparound=False
        )
        byte_pointer = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        function_type = ir.FunctionType(ir.VoidType(), [byte_pointer, i32, i32, i32])
        function = cgutils.get_or_insert_function(builder.module, function_type, "llvm.prefetch.p0")
        # Read access, high temporal locality, data cache.
        builder.call(function, [builder.bitcast(pointer, byte_pointer), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


def _atomic_rmw(operation: str, ordering: str) -> Callable[..., Any]:
    """Return the codegen of ``atomicrmw operation`` on ``array[index]``, returning the old value.

    For intrinsics typed ``(array, index, value)``: a 1D array and an index in range (no
    wraparound).
    """

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        array_type = signature.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        position = context.cast(builder, args[1], signature.args[1], types.intp)
        pointer = cgutils.get_item_pointer(
            context, builder, array_type, view, [position], wraparound=False
        )
        return builder.atomic_rmw(operation, pointer, args[2], ordering)

    return codegen


@intrinsic
def atomic_exchange(typingctx: Any, array: Any, index: Any, value: Any) -> Any:
    """Store ``value`` in ``array[index]`` atomically and return the previous value.

    Sequentially consistent (``atomicrmw xchg seq_cst``): every write a thread made
    before its exchange is visible to the thread whose exchange returns that value,
    which is what bottom-up builders need to read the box a sibling's thread wrote.
    ``array`` is a 1D integer array and ``index`` must be in range (no wraparound).
    """
    return array.dtype(array, index, array.dtype), _atomic_rmw("xchg", "seq_cst")


@intrinsic
def atomic_fetch_add(typingctx: Any, array: Any, index: Any, value: Any) -> Any:
    """Add ``value`` to ``array[index]`` atomically and return the previous value.

    Monotonic ordering (``atomicrmw add monotonic``): enough for a shared counter that
    hands out work items (:mod:`rayaccel._work`). ``array`` is a 1D integer array and
    ``index`` must be in range.
    """
    return array.dtype(array, index, array.dtype), _atomic_rmw("add", "monotonic")


@intrinsic
def keep_branch(typingctx: Any) -> Any:
    """Keep the branch this is called in a branch (an empty ``asm sideeffect``, no code).

    LLVM turns a cheap two-way choice into a select (x86 ``cmov``), which makes the
    value chosen wait for the condition. In a traversal the condition is a box test
    and the value the next node, so every step would wait for the whole test; as a
    branch, the CPU predicts it and starts fetching the next node at once. A side
    effect cannot be speculated, so the choice stays a branch.
    """
    sig = types.void()

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        barrier = ir.InlineAsm(ir.FunctionType(ir.VoidType(), []), "", "", side_effect=True)
        builder.call(barrier, [])
        return context.get_dummy_value()

    return sig, codegen


def _next_up(width: int) -> Callable[..., Any]:
    """Return the codegen of ``np.nextafter(x, inf)`` for a float of ``width`` bits (32, 64).

    The bits of the float read as a signed int of the same width step to the next
    float up: +1 for a positive value, -1 for a negative one; ±0 steps to the smallest
    subnormal, while NaN and +inf stay themselves.
    """
    as_int = ir.IntType(width)
    as_float = ir.FloatType() if width == 32 else ir.DoubleType()

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        value = args[0]
        bits = builder.bitcast(value, as_int)
        positive = builder.icmp_signed(">=", bits, as_int(0))
        stepped = builder.select(
            positive, builder.add(bits, as_int(1)), builder.sub(bits, as_int(1))
        )
        is_zero = builder.fcmp_ordered("==", value, as_float(0.0))
        stepped = builder.bitcast(builder.select(is_zero, as_int(1), stepped), as_float)
        is_nan = builder.fcmp_unordered("uno", value, value)
        is_inf = builder.fcmp_ordered("==", value, as_float(float("inf")))
        return builder.select(builder.or_(is_nan, is_inf), value, stepped)

    return codegen


@intrinsic
def next_up_float32(typingctx: Any, x: Any) -> Any:
    """``np.nextafter(x, inf)`` for a float32, inline (numba calls a C function for it).

    The bit trick of :func:`_next_up` on the float32's bits read as an int32.
    """
    return types.float32(types.float32), _next_up(32)


@intrinsic
def next_up_float64(typingctx: Any, x: Any) -> Any:
    """``np.nextafter(x, inf)`` for a float64, inline: the bit trick of :func:`next_up_float32`."""
    return types.float64(types.float64), _next_up(64)
