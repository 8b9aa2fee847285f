"""Insertion build (Goldsmith & Salmon 1987): add primitives one by one where the SAH grows least.

Goldsmith & Salmon 1987, "Automatic Creation of Object Hierarchies for Ray Tracing"
(IEEE CG&A 7(5)). The tree starts as one leaf; every further primitive becomes a
one-primitive leaf that is made the sibling of some node X: a new inner node takes
X's place with children X and the leaf, and the ancestors are refitted. Placing the
leaf next to X costs ``C_I(X) + A(X ∪ B)``, where B is the leaf's box and the
*induced* cost ``C_I`` sums the area growth of X's ancestors
(``C_I(root) = 0``, ``C_I(child of X) = C_I(X) + A(X ∪ B) − A(X)``). Two searches:

- ``search="branch_and_bound"`` (default): the optimal sibling for the induced cost,
  by the best-first search of Bittner et al. 2013 (shared with ``+reinsert``,
  :func:`rayaccel.bvh.steps.reinsert.find_best_sibling`).
- ``search="greedy"``: Goldsmith & Salmon's descent. From the root, follow the child
  whose area grows least (ties: the smaller merged box, then left), evaluate the
  sibling cost at every node on the path and keep the cheapest; stop at a leaf or
  when ``C_I + A(B)`` (a lower bound below) cannot beat it. O(depth) per insertion,
  but one wrong turn is never undone: on the kitchen scene its tree costs about
  twice the SAH of the branch and bound's (which beats a binned SAH build there).

Both searches evaluate at most ``max_visits`` nodes per insertion, which bounds the
build time (and the refit path) on inputs where the search would grow with the tree.

The result depends strongly on the insertion order (``order``): in input order a
mesh's first, spatially clustered triangles form the top of the tree, whose boxes
then grow over the whole scene, and primitives sorted along a line become a chain.
``"random"`` (the default, a seeded shuffle, as Goldsmith & Salmon suggest) makes
every prefix of the order a sample of the whole scene, so the top levels split space
evenly: it gives the lowest SAH of the three orders on every scene we measured.
``"morton"`` inserts along a Z-curve: consecutive searches touch the same nodes, so
it builds several times faster on large scenes, at a higher SAH. Trees are finished
by the SAH leaf collapse of :func:`rayaccel.bvh.layouts.linked_tree.linked_to_canonical`, whose
depth guard rebalances any subtree deeper than ``MAX_DEPTH`` (chains from ties: all
primitives identical). Serial and deterministic for a given seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.common import reference_boxes
from rayaccel.bvh.builders.lbvh import check_leaf_costs
from rayaccel.bvh.builders.refs import BuildRefs
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import LinkedTree, collapsed_to_canonical
from rayaccel.bvh.steps.reinsert import attach_sibling, find_best_sibling
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.morton import morton_codes
from rayaccel.kernels.radix_sort import radix_sort
from rayaccel.kernels.sah import node_half_area, union_half_area
from rayaccel.scene.mesh import TriangleMesh

ORDERS = ("input", "random", "morton")
SEARCHES = ("greedy", "branch_and_bound")
GREEDY = 0
BRANCH_AND_BOUND = 1


@dataclass(frozen=True, slots=True)
class InsertionOptions:
    """Options of :func:`build_insertion`.

    Attributes
    ----------
    order : {"random", "morton", "input"}
        Insertion order (see the module docstring): a seeded shuffle (default: the
        best trees), Morton order of the box centres, or the mesh's own order.
    seed : int
        Seed of the ``"random"`` order (0..2**32-1).
    search : {"branch_and_bound", "greedy"}
        The optimal sibling for the induced cost by branch and bound (default: much
        better trees on scenes with mixed primitive sizes), or Goldsmith & Salmon's
        greedy descent (faster).
    max_visits : int
        Most nodes one insertion's search may evaluate (1..2**30); the best one so
        far is taken when it runs out. Bounds the build time on adversarial inputs
        (boxes nested around one centre, primitives sorted along a line) where the
        search would otherwise grow with the tree; on the benchmark scenes the
        branch and bound evaluates at most ~300 nodes per insertion.
    max_leaf_size : int
        Largest leaf the final SAH collapse may form (1..64).
    traversal_cost, intersection_cost : float
        SAH constants of the leaf collapse.
    """

    order: str = "random"
    seed: int = 0
    search: str = "branch_and_bound"
    max_visits: int = 1024
    max_leaf_size: int = 8
    traversal_cost: float = 1.2
    intersection_cost: float = 1.0

    def __post_init__(self) -> None:
        if self.order not in ORDERS:
            raise InvalidInputError(f"order: expected one of {ORDERS}, got {self.order!r}")
        if self.search not in SEARCHES:
            raise InvalidInputError(f"search: expected one of {SEARCHES}, got {self.search!r}")
        if not 1 <= self.max_visits <= 2**30:
            raise InvalidInputError(f"max_visits: expected 1..2**30, got {self.max_visits}")
        if not 0 <= self.seed < 2**32:
            raise InvalidInputError(f"seed: expected 0..2**32-1, got {self.seed}")
        check_leaf_costs(self.max_leaf_size, self.traversal_cost, self.intersection_cost)


@cpu_inline
def _greedy_sibling(root, leaf, left, right, lo, hi, max_visits):
    """Goldsmith & Salmon's descent: the cheapest sibling on the path of least growth."""
    leaf_area = node_half_area(lo, hi, leaf)
    best = np.inf
    best_node = root
    induced = 0.0
    x = root
    for _ in range(max_visits):
        merged = union_half_area(lo, hi, x, leaf)
        # Make the leaf X's sibling here?
        if induced + merged < best:
            best = induced + merged
            best_node = x
        if left[x] < 0:
            break
        # Going down enlarges X; nothing below can cost less than induced + A(leaf).
        induced += merged - node_half_area(lo, hi, x)
        if induced + leaf_area >= best:
            break
        # Follow the child that grows least (ties: smaller merged box, then left).
        a = left[x]
        b = right[x]
        merged_a = union_half_area(lo, hi, a, leaf)
        merged_b = union_half_area(lo, hi, b, leaf)
        grow_a = merged_a - node_half_area(lo, hi, a)
        grow_b = merged_b - node_half_area(lo, hi, b)
        if grow_b < grow_a or (grow_b == grow_a and merged_b < merged_a):
            x = b
        else:
            x = a
    return best_node


@cpu_kernel()
def _insert_kernel(search, max_visits, left, right, parent, lo, hi):
    """Insert leaves ``n−1 .. 2n−2`` in id order (inner nodes ``0 .. n−2``); return the root."""
    n = (left.shape[0] + 1) // 2
    root = n - 1
    parent[root] = -1
    # Each evaluated node pushes at most two children: the budget bounds the heap.
    heap = min(2 * left.shape[0], 2 * max_visits) + 2 if search == BRANCH_AND_BOUND else 1
    h_cost = np.empty(heap, dtype=np.float64)
    h_node = np.empty(heap, dtype=np.int32)
    for k in range(1, n):
        leaf = n - 1 + k
        # Find the sibling, then splice inner node k−1 above it and refit upwards.
        if search == BRANCH_AND_BOUND:
            x = find_best_sibling(root, leaf, left, right, lo, hi, h_cost, h_node, max_visits)
        else:
            x = _greedy_sibling(root, leaf, left, right, lo, hi, max_visits)
        root = attach_sibling(root, k - 1, x, leaf, parent, left, right, lo, hi)
    return root


def insertion_order(prim_lo: np.ndarray, prim_hi: np.ndarray, order: str, seed: int) -> np.ndarray:
    """Return the ``(n,)`` int32 order in which references are inserted."""
    n = prim_lo.shape[0]
    ids = np.arange(n, dtype=np.int32)
    if order == "random":
        return np.random.default_rng(seed).permutation(ids).astype(np.int32)
    if order == "morton":
        codes = morton_codes(prim_lo, prim_hi, 21)
        return np.ascontiguousarray(radix_sort(codes, ids, 63)[1], dtype=np.int32)
    return ids


def build_insertion_refs(
    prim_lo: np.ndarray,
    prim_hi: np.ndarray,
    prim_id: np.ndarray,
    n_prims: int,
    opt: InsertionOptions,
) -> Bvh2:
    """Build an insertion tree over reference boxes (``prim_id`` maps references to primitives)."""
    n = prim_lo.shape[0]
    order = insertion_order(prim_lo, prim_hi, opt.order, opt.seed)
    n_nodes = 2 * n - 1
    # Leaf n−1+k holds the k-th reference inserted; inner ids 0..n−2 are handed out in turn.
    lo = np.empty((n_nodes, 3), dtype=np.float32)
    hi = np.empty((n_nodes, 3), dtype=np.float32)
    lo[n - 1 :] = prim_lo[order]
    hi[n - 1 :] = prim_hi[order]
    first = np.zeros(n_nodes, dtype=np.int32)
    first[n - 1 :] = np.arange(n, dtype=np.int32)
    count = np.zeros(n_nodes, dtype=np.int32)
    count[n - 1 :] = 1
    left = np.full(n_nodes, -1, dtype=np.int32)
    right = np.full(n_nodes, -1, dtype=np.int32)
    parent = np.full(n_nodes, -1, dtype=np.int32)
    search = BRANCH_AND_BOUND if opt.search == "branch_and_bound" else GREEDY
    root = int(
        _insert_kernel(np.int32(search), np.int32(opt.max_visits), left, right, parent, lo, hi)
    )
    prim_index = np.ascontiguousarray(prim_id[order], dtype=np.int32)
    tree = LinkedTree(left, right, lo, hi, first, count, prim_index)
    return collapsed_to_canonical(tree, root, n_prims, opt)


@register("builder", "bvh2.insertion")
def build_insertion(
    mesh: TriangleMesh, options: InsertionOptions | None = None, refs: BuildRefs | None = None
) -> Bvh2:
    """Build by insertion: add primitives one by one where the SAH grows least, SAH collapse.

    See the module docstring.

    The tree's depth is at most ``MAX_DEPTH``.

    References
    ----------
    Goldsmith & Salmon 1987, Automatic Creation of Object Hierarchies for Ray Tracing.
    """
    opt = options or InsertionOptions()
    prim_lo, prim_hi, prim_id = reference_boxes(mesh, refs, "bvh2.insertion")
    return build_insertion_refs(prim_lo, prim_hi, prim_id, mesh.n_triangles, opt)
