"""``kdtree.short_stack``: a short ring of far children with push-down restarts (Horn et al. 2007).

The far children are kept in a ring of ``size`` entries; a push onto a full ring
overwrites the oldest. When the ring runs dry after an overwrite, the traversal
restarts at the leaf's exit from the push-down root: the deepest node entered
before any push whose cell holds the rest of the segment. Horn et al. report that
three entries cost only 3% more nodes than a full stack. Counters: those of
``kdtree.stack`` (``stack_peak``: ring entries in use) plus ``restarts``.
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel.errors import InvalidInputError
from rayaccel.kdtree.layouts.kdtree import STACK_SIZE, KdTree
from rayaccel.kdtree.traverse.common import kd_trace_layout
from rayaccel.kdtree.traverse.stackless import METHOD_SHORT_STACK, stackless_arrays, trace_kernel
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.trace.register import LayoutCache, TracePlan, register_traversal


@dataclass(frozen=True, slots=True)
class KdShortStackOptions:
    """Options of ``kdtree.short_stack``.

    Attributes
    ----------
    size : int
        Ring entries (1..STACK_SIZE); one kernel serves every size.
    """

    size: int = 3

    def __post_init__(self) -> None:
        if not 1 <= int(self.size) <= STACK_SIZE:
            raise InvalidInputError(f"size must be in 1..{STACK_SIZE}, got {self.size}")


@register_traversal("kdtree.short_stack")
def trace_kdtree_short_stack(
    kd: KdTree, mesh: TriangleMesh, options: KdShortStackOptions, cache: LayoutCache
) -> TracePlan:
    """Short stack (a ring of far children) with push-down restarts.

    Trace rays through a kd-tree with a short stack.

    References
    ----------
    Horn, Sugerman, Houston, Hanrahan 2007, Interactive k-D Tree GPU Raytracing.
    """
    arrays = stackless_arrays(
        kd_trace_layout(kd, mesh, cache), ring_size=int(options.size), method=METHOD_SHORT_STACK
    )
    return TracePlan(trace_kernel(METHOD_SHORT_STACK), arrays)
