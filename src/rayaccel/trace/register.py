"""``register_traversal``: a CPU traversal is a plan, its kernel and the layout it reads.

Every traversal of every family has the same public form, ``trace(structure, mesh,
rays, *, query, stats, options, cache) -> HitBatch``, and the same tail: derive the
layout (memoised in ``cache``), pick the compiled kernel, :func:`run_trace`. What
differs is only the plan, so a traversal module writes the plan and this decorator
makes and registers the public function around it, with the shared signature and the
shared numpydoc sections (:func:`rayaccel._variant.with_shared_sections`).
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any, NamedTuple, TypeAlias

from rayaccel._variant import annotated_options, register
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.trace.run import DEFAULT_OVERFLOW_HINT, run_trace

#: The memo of derived layouts a traversal's plan receives (an ``Accel`` passes its own).
LayoutCache: TypeAlias = "dict[str, Any] | None"


class TracePlan(NamedTuple):
    """What a traversal runs: the kernel picker, the layout arrays, the overflow reason.

    Attributes
    ----------
    kernel_for : callable
        ``kernel_for(query, with_stats, parallel)``, usually
        :func:`rayaccel.trace.run.body_kernels` of the traversal.
    arrays : NamedTuple of arrays
        What the kernel's ``layout`` argument receives.
    overflow_hint : str
        Why rays can overflow the traversal's stack, for the error message.
    """

    kernel_for: Callable[[int, bool, bool], Any]
    arrays: Any
    overflow_hint: str = DEFAULT_OVERFLOW_HINT


def _public_signature(trace: Callable[..., HitBatch], plan: Callable[..., TracePlan],
                      options: type) -> inspect.Signature:  # fmt: skip
    """Return ``trace``'s signature with the plan's first two parameters and the options type."""
    signature = inspect.signature(trace)
    public = list(signature.parameters.values())
    structure, mesh = list(inspect.signature(plan).parameters.values())[:2]
    public[0] = structure.replace(kind=public[0].kind)
    public[1] = mesh.replace(kind=public[1].kind)
    public = [p.replace(annotation=f"{options.__name__} | None") if p.name == "options" else p
              for p in public]  # fmt: skip
    return signature.replace(parameters=public)


def register_traversal(
    key: str,
    *,
    default: bool = False,
) -> Callable[[Callable[..., TracePlan]], Callable[..., HitBatch]]:
    """Return a decorator that registers a traversal from its plan.

    The decorated ``plan(structure, mesh, options, cache) -> TracePlan`` receives the
    options (of the dataclass its ``options`` parameter is annotated with, their
    defaults when the caller passes none) and the ``Accel``'s layout
    cache. The decorator returns, and registers as the variant ``key``, the public
    ``trace(structure, mesh, rays, *, query="closest", stats=False, options=None,
    cache=None) -> HitBatch`` that runs the plan with :func:`run_trace`; it keeps the
    plan's name and docstring (whose first line and ``References`` section the
    registry lists).
    """

    def decorate(plan: Callable[..., TracePlan]) -> Callable[..., HitBatch]:
        options_type = annotated_options(plan)

        # The plan's name and docstring; its annotations are not the public function's.
        @functools.wraps(plan, assigned=("__module__", "__name__", "__qualname__", "__doc__"))
        def trace(
            structure: Any,
            mesh: Any,
            rays: RayBatch,
            *,
            query: str = "closest",
            stats: bool = False,
            options: Any = None,
            cache: dict[str, Any] | None = None,
        ) -> HitBatch:
            chosen = options_type() if options is None else options
            kernel_for, arrays, overflow_hint = plan(structure, mesh, chosen, cache)
            return run_trace(kernel_for, arrays, rays, query, stats, overflow_hint)

        del trace.__wrapped__
        trace.__signature__ = _public_signature(trace, plan, options_type)  # type: ignore[attr-defined]
        registered: Callable[..., HitBatch] = register(
            "traversal", key, options=options_type, default=default
        )(trace)
        return registered

    return decorate
