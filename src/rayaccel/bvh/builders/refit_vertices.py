"""Refitting a built BVH to moved vertices: same topology, new boxes, bottom up.

When a mesh deforms but keeps its triangles (skinned characters, cloth, simulation
frames), the tree need not be rebuilt: every leaf box is recomputed from its
triangles' new corners and every inner box as the union of its children's, leaves
first (Wald, Boulos & Shirley 2007, *Ray tracing deformable scenes using dynamic
bounding volume hierarchies*, §3; Karras 2012 §4 does the same bottom-up pass after
an LBVH build). The cost is O(n) with no sorting or partitioning, typically one to two
orders of magnitude below a rebuild. The topology was chosen for the old geometry, so
the tree's quality decays as the mesh moves away from it; :func:`sah_of` measures the
SAH cost so the caller can rebuild once it has grown too much (Wald et al. 2007 §4.2).

Parallelism follows :func:`rayaccel.bvh.builders.refit.refit_collapse`: the tree is
cut below its top levels into about :data:`~rayaccel.bvh.builders.refit.FRONTIER_SIZE`
independent subtrees (:func:`~rayaccel.bvh.builders.refit.top_frontier`), each refitted
by one thread in post-order, then the few top nodes serially, children first. Every box
is a min/max of the same values in any order, so the result does not depend on the
thread count.

Split references (SBVH, pre-split input): a reference's box was the triangle clipped to
a cell at build time. Clipping against the new geometry would need the split planes,
which the tree does not keep, so a refit gives each leaf the *whole* boxes of its
triangles. The boxes are then conservative (larger than an exact clip), still enclose
every part of each triangle, and traversal stays correct; only some of the spatial
splits' tightening is lost.
"""

from __future__ import annotations

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.bvh.builders.refit import FRONTIER_SIZE, push, top_frontier
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH, Bvh2
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.kernels.sah import node_half_area


@cpu_kernel(parallel=True)
def _refit_kernel(node_first, node_count, prim_index, vertices, faces, left, right, lo, hi):
    """Recompute every box of a BVH2 from the triangles its leaves list.

    Parameters
    ----------
    node_first, node_count : (n,) int32
        The canonical topology (:class:`~rayaccel.bvh.layouts.bvh2.Bvh2`).
    prim_index : (n_refs,) int32
    vertices : (V, 3) float32
        The new vertex positions.
    faces : (F, 3) int32
    left, right : (n,) int32
        Children of inner nodes (``-1`` for leaves), for cutting the tree into subtrees.
    lo, hi : (n, 3) float32
        Output boxes; every node is written.
    """
    frontier, top = top_frontier(np.int32(0), left, right, FRONTIER_SIZE)
    # Frontier subtrees in parallel, each in post-order on an explicit stack.
    for f in prange(frontier.shape[0]):
        stack = np.empty(2 * MAX_DEPTH + 64, dtype=np.int32)
        stack[0] = frontier[f]
        sp = 1
        last = np.int32(-1)
        while sp > 0:
            node = stack[sp - 1]
            u = np.uint64(node)
            first = node_first[u]
            count = node_count[u]
            # An inner node is finished once its right child (popped last) is.
            if count == 0 and last != first + 1:
                stack = push(stack, sp, first + 1)
                stack = push(stack, sp + 1, first)
                sp += 2
                continue
            sp -= 1
            last = node
            if count > 0:
                # A leaf: the union of its triangles' corner boxes.
                x0 = y0 = z0 = np.float32(np.inf)
                x1 = y1 = z1 = np.float32(-np.inf)
                for j in range(first, first + count):
                    p = np.uint64(prim_index[np.uint64(j)])
                    for c in range(3):
                        v = np.uint64(faces[p, c])
                        x0 = min(x0, vertices[v, 0])
                        y0 = min(y0, vertices[v, 1])
                        z0 = min(z0, vertices[v, 2])
                        x1 = max(x1, vertices[v, 0])
                        y1 = max(y1, vertices[v, 1])
                        z1 = max(z1, vertices[v, 2])
                lo[u, 0] = x0
                lo[u, 1] = y0
                lo[u, 2] = z0
                hi[u, 0] = x1
                hi[u, 1] = y1
                hi[u, 2] = z1
            else:
                # An inner node: the union of its two children.
                a = np.uint64(first)
                b = np.uint64(first + 1)
                for k in range(3):
                    lo[u, k] = min(lo[a, k], lo[b, k])
                    hi[u, k] = max(hi[a, k], hi[b, k])
    # The top levels, children before parents.
    for i in range(top.shape[0] - 1, -1, -1):
        u = np.uint64(top[i])
        a = np.uint64(node_first[u])
        b = a + np.uint64(1)
        for k in range(3):
            lo[u, k] = min(lo[a, k], lo[b, k])
            hi[u, k] = max(hi[a, k], hi[b, k])


@cpu_kernel()
def _sah_sums(lo, hi, node_count):
    """Return ``(Σ_inner half area, Σ_leaf half area × count, root half area)``, in float64.

    One serial pass in node order, so the sum (and every SAH ratio built from it) is
    the same on every run and thread count.
    """
    inner = 0.0
    leaf = 0.0
    for i in range(node_count.shape[0]):
        area = node_half_area(lo, hi, i)
        if node_count[i] > 0:
            leaf += area * node_count[i]
        else:
            inner += area
    return inner, leaf, node_half_area(lo, hi, 0)


def sah_of(bvh: Bvh2, inner_cost: float = 1.2, prim_cost: float = 1.0) -> float:
    """Return the SAH cost of ``bvh`` (the value of :meth:`Bvh2.sah_cost`, from a kernel).

    ``(C_inner · Σ_inner SA(n) + C_prim · Σ_leaf SA(l)·N(l)) / SA(root)`` (MacDonald &
    Booth 1990; Aila et al. 2013), summed in float64 in node order. It agrees with
    :meth:`~rayaccel.bvh.layouts.bvh2.Bvh2.sah_cost` to about 1e-7 (that method rounds
    box extents to float32 before widening) and needs no temporaries on large trees.
    """
    inner, leaf, root = _sah_sums(bvh.node_lo, bvh.node_hi, bvh.node_count)
    if root <= 0.0:
        if bvh.node_count[0] > 0:
            return float(prim_cost * bvh.n_refs)
        return float(inner_cost + prim_cost)
    return float((inner_cost * inner + prim_cost * leaf) / root)


def refit_bvh2(bvh: Bvh2, vertices: FloatArray, faces: IntArray) -> Bvh2:
    """Return ``bvh`` with every box recomputed for new vertex positions.

    Parameters
    ----------
    bvh : Bvh2
        A valid tree built over a mesh with the same faces; it is not changed (the new
        tree shares its ``node_first``, ``node_count`` and ``prim_index``).
    vertices : (V, 3) float32 ndarray
        The new positions (finite, C-contiguous; validated by the caller).
    faces : (F, 3) int32 ndarray
        The mesh's faces, unchanged since the build.

    Returns
    -------
    Bvh2
        The same topology with new ``node_lo``/``node_hi``. Leaves over split
        references get their triangles' whole boxes (see the module docstring).

    Notes
    -----
    O(n_nodes + 3·n_refs): one pass over the references' corners and one over the
    inner nodes, parallel over independent subtrees.
    """
    count = bvh.node_count
    inner = count == 0
    left = np.where(inner, bvh.node_first, -1).astype(INDEX)
    right = np.where(inner, bvh.node_first + 1, -1).astype(INDEX)
    lo = np.empty_like(bvh.node_lo, dtype=REAL)
    hi = np.empty_like(bvh.node_hi, dtype=REAL)
    _refit_kernel(
        bvh.node_first,
        count,
        bvh.prim_index,
        np.ascontiguousarray(vertices, dtype=REAL),
        np.ascontiguousarray(faces, dtype=INDEX),
        left,
        right,
        lo,
        hi,
    )
    return Bvh2(
        node_lo=lo,
        node_hi=hi,
        node_first=bvh.node_first,
        node_count=bvh.node_count,
        prim_index=bvh.prim_index,
        n_prims=bvh.n_prims,
    )
