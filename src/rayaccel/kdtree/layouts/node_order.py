"""The kd-tree's nodes in cache blocks: a pair's subtree near it in memory.

A builder emits the nodes in the order it splits them, so a node's children's pairs
may lie megabytes away from it (the kitchen's tree has 83 MB of nodes, more than the
L3 cache). :func:`blocked_node_order` renumbers the tree into treelets: starting from
a pair of children, the pairs below it are taken breadth first until a treelet holds
:data:`PAIRS_PER_BLOCK` pairs (256 bytes, four cache lines), the treelets follow
each other depth first, and a treelet's overflowing children start the treelets
after it. A walk that enters a treelet at its top pair finds the next three or four
levels within 256 bytes of it, in lines it has loaded or that the hardware fetches
alongside (a fixed-block form of the cache-efficient layouts of Yoon & Manocha 2006,
"Cache-Efficient Layouts of Bounding Volume Hierarchies"). The root stays at node 0
and its children at 1 and 2; children stay adjacent, so every invariant of the
canonical layout holds and every derived layout follows the new numbering.

:func:`line_aligned_copy` copies the nodes with node 1 at a cache line's start, so
every pair starts at a multiple of 16 bytes and never straddles two lines.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.dtypes import FloatArray
from rayaccel.errors import StructureInvariantError

#: Child pairs (16 bytes each) per treelet: 256 bytes (docs/performance.md, ``kdtree.stack``).
PAIRS_PER_BLOCK = 16
LINE_BYTES = 64


@cpu_kernel()
def _blocked_positions(bits, pairs_per_block):
    """Return each node's index in the blocked order and the number of nodes placed.

    The count is -1 when a child index lies outside the array or the walk finds more
    pairs than there are nodes (a node reached twice), so a corrupt tree stops here
    instead of reading or writing out of bounds.
    """
    n = bits.shape[0]
    new = np.empty(n, dtype=np.int32)
    new[0] = 0
    pos = 1
    # A pair is named by its first (lower) node; the pending tops of treelets.
    stack = np.empty(n // 2 + 1, dtype=np.int32)
    sp = 0
    if (bits[0] & 3) != 3:
        stack[0] = bits[0] >> 2
        sp = 1
    treelet = np.empty(pairs_per_block, dtype=np.int32)
    overflow = np.empty(2 * pairs_per_block, dtype=np.int32)
    while sp > 0:
        sp -= 1
        treelet[0] = stack[sp]
        m = 1
        n_over = 0
        q = 0
        while q < m:
            pair = treelet[q]
            q += 1
            for node in range(pair, pair + 2):
                word = bits[node]
                if (word & 3) != 3:
                    child = word >> 2
                    if child < 1 or child + 1 >= n:
                        return new, -1  # a child outside the array
                    if m < pairs_per_block:
                        treelet[m] = child
                        m += 1
                    else:
                        overflow[n_over] = child
                        n_over += 1
        if pos + 2 * m > n or sp + n_over > stack.shape[0]:
            return new, -1  # more pairs than nodes: not a tree
        for k in range(m):
            new[treelet[k]] = pos
            new[treelet[k] + 1] = pos + 1
            pos += 2
        # The first overflowing pair becomes the next treelet (depth first).
        for k in range(n_over - 1, -1, -1):
            stack[sp] = overflow[k]
            sp += 1
    return new, pos


@cpu_kernel(parallel=True)
def _renumbered(words, new):
    """Return the ``(n, 2)`` int32 words moved to their new indices, children renamed."""
    n = words.shape[0]
    out = np.empty((n, 2), dtype=np.int32)
    for node in prange(n):
        bits = words[node, 1]
        if (bits & 3) != 3:
            bits = (new[bits >> 2] << 2) | (bits & 3)
        out[new[node], 0] = words[node, 0]
        out[new[node], 1] = bits
    return out


def blocked_node_order(nodes: FloatArray) -> FloatArray:
    """Return ``nodes`` (canonical ``(n, 2)`` rows) renumbered into treelets of 256 bytes.

    Inner nodes' child indices are rewritten; leaves keep their leaf index, so the leaf
    tables and references are unchanged.
    """
    words = nodes.view(np.int32)
    new, placed = _blocked_positions(np.ascontiguousarray(words[:, 1]), PAIRS_PER_BLOCK)
    if placed < 0:
        raise StructureInvariantError(
            "kd nodes are reached twice from the root or name a child outside the array: not a tree"
        )
    if placed != nodes.shape[0]:
        raise StructureInvariantError(
            f"{nodes.shape[0] - placed} kd nodes are not reached from the root"
        )
    out: FloatArray = _renumbered(words, new).view(nodes.dtype)
    return out


def line_aligned_copy(nodes: FloatArray) -> FloatArray:
    """Return a copy of ``nodes`` whose node 1 starts a :data:`LINE_BYTES` cache line."""
    row = nodes.itemsize * 2
    buffer = np.empty(nodes.nbytes + LINE_BYTES + row, dtype=np.uint8)
    skip = (-(buffer.ctypes.data + row)) % LINE_BYTES
    out: FloatArray = buffer[skip : skip + nodes.nbytes].view(nodes.dtype).reshape(nodes.shape)
    out[...] = nodes
    return out
