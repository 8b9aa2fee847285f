"""Per-ray traversal counters (the thesis's ``TraversalStats``), STYLE §4.4.

An instrumented traversal fills an ``(n_rays, N_COUNTERS)`` int32 array, one row
per ray, counting in registers and storing once per ray. The plain variant gets a
``(0, N_COUNTERS)`` placeholder so both compile to one signature.

Counters shared by every traversal:

``steps``       iterations of the traversal loop (node visits plus leaf visits)
``nodes``       nodes visited (inner and leaf nodes whose box was entered)
``box_tests``   ray/box slab tests
``prim_tests``  ray/primitive tests
``stack_peak``  the deepest the traversal stack got
``bytes``       estimated bytes fetched: nodes, references, triangles, stack traffic

Counters of the stackless traversals (0 for traversals they do not apply to):

``restarts``               restarts from the root (restart trail)
``backtracks``             backtracking operations: trail pops, parent steps, jumps
``hash_lookups``           perfect-hash lookups (constant-time backtracking)
``backtrack_sibling``      backtracks whose target is the sibling (0 levels up)
``backtrack_uncle``        ... the uncle (1 level up)
``backtrack_grand_uncle``  ... the grand-uncle (2 levels up)
``backtrack_further``      ... further up (3 or more levels)

Counters of the kd-trees and grids (0 for traversals they do not apply to):

``leaves``          leaves entered (kd-trees), empty ones included
``empty_leaves``    leaves entered that hold no primitive
``rope_steps``      rope links followed from leaf to leaf (kd-tree ropes)
``cells``           grid cells visited (every level of a hierarchical grid)
``empty_cells``     grid cells visited that hold no primitive
``mailbox_hits``    primitive tests skipped because the mailbox had just tested them
``vertical_steps``  level changes in an occupancy pyramid or a two-level grid
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Counter(IntEnum):
    """Column of a counter in the per-ray counter array."""

    STEPS = 0
    NODES = 1
    BOX_TESTS = 2
    PRIM_TESTS = 3
    STACK_PEAK = 4
    BYTES = 5
    RESTARTS = 6
    BACKTRACKS = 7
    HASH_LOOKUPS = 8
    BACKTRACK_SIBLING = 9
    BACKTRACK_UNCLE = 10
    BACKTRACK_GRAND_UNCLE = 11
    BACKTRACK_FURTHER = 12
    LEAVES = 13
    EMPTY_LEAVES = 14
    ROPE_STEPS = 15
    CELLS = 16
    EMPTY_CELLS = 17
    MAILBOX_HITS = 18
    VERTICAL_STEPS = 19


N_COUNTERS = len(Counter)

#: Public counter names, in column order (``hits.stats[name]``).
COUNTER_NAMES: tuple[str, ...] = tuple(c.name.lower() for c in Counter)


def empty_counters(n_rays: int, with_stats: bool) -> np.ndarray:
    """Return the counter array a trace kernel writes: ``(n, N)`` or a ``(0, N)`` placeholder."""
    return np.zeros((n_rays if with_stats else 0, N_COUNTERS), dtype=np.int32)


def counters_to_dict(counters: np.ndarray) -> dict[str, np.ndarray]:
    """Return the columns of a ``(n, N_COUNTERS)`` counter array by counter name."""
    return {name: np.ascontiguousarray(counters[:, i]) for i, name in enumerate(COUNTER_NAMES)}
