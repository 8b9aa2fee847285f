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

Parallelism follows Karras 2012 §4 (the bottom-up pass of his LBVH builder). Every
node's parent and every reference's three vertex indices, in leaf order, are found once
per tree (:class:`RefitTopology`; neither changes when the vertices move) and kept for
the refits that follow. Threads take blocks of nodes from a shared counter
(:mod:`rayaccel._work`), compute the box of each leaf in the block and climb towards the
root. At each inner node the first thread to arrive flags it and stops; the second,
which then finds both children done, writes the union and climbs on. The flag is a
sequentially consistent exchange (:func:`rayaccel._jit.atomic_exchange`), so the second
thread sees the box the first wrote. Every inner box is finished exactly once, by one
thread, and every box is a min/max of the same values whichever thread computes it, so
the result does not depend on the thread count. The work is O(n) with no stack and no
sorting; the leaf pass, a gather of three vertices per reference, dominates.

Split references (SBVH, pre-split input): a reference's box was the triangle clipped to
a cell at build time. Clipping against the new geometry would need the split planes,
which the tree does not keep, so a refit gives each leaf the *whole* boxes of its
triangles. The boxes are then conservative (larger than an exact clip), still enclose
every part of each triangle, and traversal stays correct; only some of the spatial
splits' tightening is lost.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numba import prange

from rayaccel._hugepages import zeros_huge
from rayaccel._jit import atomic_exchange, cpu_kernel
from rayaccel._work import new_counter, next_item, worker_count
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.config import parallel_section
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.kernels.box_grow import store_box, union_bounds
from rayaccel.kernels.sah import node_half_area

#: Nodes per work item of the refit pass (about 100 KB of boxes; small enough to balance
#: two to sixty-four threads on trees of 10^4 nodes and more).
BLOCK_NODES = 4096


#: Trees with fewer nodes are refitted (and their SAH summed) on the calling thread: the
#: serial pass takes a few milliseconds there, less than a parallel launch can cost on a
#: loaded machine.
PARALLEL_MIN_NODES = 1 << 17


@dataclass(frozen=True, slots=True)
class RefitTopology:
    """What every refit of one tree reads and none changes (the topology and the faces).

    Attributes
    ----------
    parent : (n_nodes,) int32
        Each node's parent (-1 at the root).
    corners : (n_refs, 3) int32
        The vertex indices of each reference's triangle, in leaf order
        (``faces[prim_index]``): the leaf pass reads them in sequence instead of looking
        up ``faces`` through ``prim_index`` at random.
    """

    parent: IntArray
    corners: IntArray

    def nbytes(self) -> int:
        """Return the bytes held."""
        return int(self.parent.nbytes + self.corners.nbytes)


def refit_topology(bvh: Bvh2, faces: IntArray) -> RefitTopology:
    """Return the parent links and the leaf-order corner indices of ``bvh`` over ``faces``.

    A refit keeps both (the tree's topology and the mesh's faces do not move), so an
    animation computes them once and passes them to every :func:`refit_bvh2`.
    """
    n = bvh.n_nodes
    parent = np.full(n, -1, dtype=INDEX)
    inner = np.flatnonzero(bvh.node_count == 0).astype(INDEX)
    first = bvh.node_first[inner]
    parent[first] = inner
    parent[first + 1] = inner
    corners = np.ascontiguousarray(np.asarray(faces, dtype=INDEX)[bvh.prim_index])
    for array in (parent, corners):
        array.flags.writeable = False
    return RefitTopology(parent, corners)


@functools.cache
def _refit_kernel(parallel: bool) -> Any:
    """Return the refit kernel, parallel or serial (STYLE §4.3: one dispatcher per variant)."""

    @cpu_kernel(parallel=parallel)
    def kernel(node_first, node_count, parent, corners, vertices, lo, hi, n_threads):
        """Recompute every box of a BVH2 from the triangles its leaves list (Karras 2012 §4).

        Parameters
        ----------
        node_first, node_count : (n,) int32
            The canonical topology (:class:`~rayaccel.bvh.layouts.bvh2.Bvh2`).
        parent : (n,) int32
            Each node's parent, -1 at the root (:class:`RefitTopology`).
        corners : (n_refs, 3) int32
            Each reference's vertex indices, in leaf order.
        vertices : (V, 3) float32
            The new vertex positions.
        lo, hi : (n, 3) float32
            Output boxes; every node is written.
        n_threads : int
            Workers to start (``numba.get_num_threads()`` of the caller).
        """
        n = node_count.shape[0]
        arrived = zeros_huge(n, np.int32)
        n_blocks = (n + BLOCK_NODES - 1) // BLOCK_NODES
        counter = new_counter()
        for _worker in prange(worker_count(n_blocks, n_threads, parallel)):
            while True:
                block = next_item(counter, n_blocks)
                if block < 0:
                    break
                for node in range(block * BLOCK_NODES, min(n, (block + 1) * BLOCK_NODES)):
                    u = np.uint64(node)
                    count = node_count[u]
                    if count == 0:
                        continue
                    # A leaf: the union of its triangles' corner boxes.
                    inf = np.float32(np.inf)
                    box = (inf, inf, inf, -inf, -inf, -inf)
                    first = node_first[u]
                    for j in range(first, first + count):
                        r = np.uint64(j)
                        for c in range(3):
                            box = union_bounds(box, vertices, vertices, np.uint64(corners[r, c]), 0)
                    store_box(lo, hi, u, box)
                    # Climb while this thread is the second to reach each parent.
                    up = parent[u]
                    while up >= 0 and atomic_exchange(arrived, up, np.int32(1)) == 1:
                        w = np.uint64(up)
                        a = np.uint64(node_first[w])
                        b = a + np.uint64(1)
                        for k in range(3):
                            lo[w, k] = min(lo[a, k], lo[b, k])
                            hi[w, k] = max(hi[a, k], hi[b, k])
                        up = parent[w]

    return kernel


@functools.cache
def _sah_kernel(parallel: bool) -> Any:
    """Return the SAH sum kernel, parallel or serial."""

    @cpu_kernel(parallel=parallel)
    def kernel(lo, hi, node_count):
        """Return ``(Σ_inner half area, Σ_leaf half area × count, root half area)``, in float64.

        Each block of :data:`BLOCK_NODES` nodes is summed in node order into its own slot,
        then the blocks in order, so the sum (and every SAH ratio built from it) is the same
        on every run and thread count.
        """
        _ = parallel  # STYLE §4.3 rule 1: the flag joins the cache key
        n = node_count.shape[0]
        n_blocks = (n + BLOCK_NODES - 1) // BLOCK_NODES
        partial = np.zeros((n_blocks, 2), dtype=np.float64)
        for block in prange(n_blocks):
            inner = 0.0
            leaf = 0.0
            for i in range(block * BLOCK_NODES, min(n, (block + 1) * BLOCK_NODES)):
                area = node_half_area(lo, hi, i)
                if node_count[i] > 0:
                    leaf += area * node_count[i]
                else:
                    inner += area
            partial[block, 0] = inner
            partial[block, 1] = leaf
        inner = 0.0
        leaf = 0.0
        for block in range(n_blocks):
            inner += partial[block, 0]
            leaf += partial[block, 1]
        return inner, leaf, node_half_area(lo, hi, 0)

    return kernel


def _read_only(array: np.ndarray, dtype: Any) -> Any:
    """Return a read-only C-contiguous view of ``array`` in ``dtype`` (one kernel signature).

    Mesh arrays are read-only and tree arrays writable; numba types the two differently,
    so every input goes in as a read-only view.
    """
    view = np.ascontiguousarray(array, dtype=dtype).view()
    view.flags.writeable = False
    return view


def sah_of(bvh: Bvh2, inner_cost: float = 1.2, prim_cost: float = 1.0) -> float:
    """Return the SAH cost of ``bvh`` (the value of :meth:`Bvh2.sah_cost`, from a kernel).

    ``(C_inner · Σ_inner SA(n) + C_prim · Σ_leaf SA(l)·N(l)) / SA(root)`` (MacDonald &
    Booth 1990; Aila et al. 2013), summed in float64 in a fixed order. It agrees with
    :meth:`~rayaccel.bvh.layouts.bvh2.Bvh2.sah_cost` to about 1e-7 (that method rounds
    box extents to float32 before widening) and needs no temporaries on large trees.
    """
    with parallel_section():
        kernel = _sah_kernel(bvh.n_nodes >= PARALLEL_MIN_NODES)
        inner, leaf, root = kernel(
            _read_only(bvh.node_lo, REAL), _read_only(bvh.node_hi, REAL),
            _read_only(bvh.node_count, INDEX),
        )  # fmt: skip
    if root <= 0.0:
        if bvh.node_count[0] > 0:
            return float(prim_cost * bvh.n_refs)
        return float(inner_cost + prim_cost)
    return float((inner_cost * inner + prim_cost * leaf) / root)


def refit_bvh2(
    bvh: Bvh2, vertices: FloatArray, faces: IntArray, topology: RefitTopology | None = None
) -> Bvh2:
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
    topology : RefitTopology, optional
        :func:`refit_topology` of ``bvh`` and ``faces``, kept from an earlier refit of the
        same tree (computed here when None).

    Returns
    -------
    Bvh2
        The same topology with new ``node_lo``/``node_hi``. Leaves over split
        references get their triangles' whole boxes (see the module docstring).

    Notes
    -----
    O(n_nodes + 3·n_refs), parallel over blocks of nodes (see the module docstring).
    """
    if topology is None:
        topology = refit_topology(bvh, faces)
    lo = np.empty((bvh.n_nodes, 3), dtype=REAL)
    hi = np.empty((bvh.n_nodes, 3), dtype=REAL)
    with parallel_section():
        _refit_kernel(bvh.n_nodes >= PARALLEL_MIN_NODES)(
            _read_only(bvh.node_first, INDEX),
            _read_only(bvh.node_count, INDEX),
            _read_only(topology.parent, INDEX),
            _read_only(topology.corners, INDEX),
            _read_only(vertices, REAL),
            lo,
            hi,
            numba.get_num_threads(),
        )
    return Bvh2(
        node_lo=lo,
        node_hi=hi,
        node_first=bvh.node_first,
        node_count=bvh.node_count,
        prim_index=bvh.prim_index,
        n_prims=bvh.n_prims,
    )
