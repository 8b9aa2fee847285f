"""Tree rotations (Kensler 2008), as a step (``+rotate``): hill climbing or simulated annealing.

Kensler 2008, "Tree Rotations for Improving Bounding Volume Hierarchies" (IEEE
Symposium on Interactive Ray Tracing). At an inner node N with children L and R, six
local moves exchange two subtrees: L with RL or RR, R with LL or LR (rotations), and
LL with RL or RR (grandchild swaps). N covers the same primitives afterwards, so only
the boxes of L and/or R change and ancestors are untouched; leaves never change, so
the SAH cost changes by ``C_inner·ΔA/A(root)``, where ΔA is the change of the one or
two child areas. The move choice therefore does not depend on the SAH constants.

- Hill climbing (``method="hill"``): post-order passes; at each inner node apply the
  move with the largest area decrease, if any; repeat until a pass finds no
  improving move (or ``max_passes``).
- Simulated annealing (``method="anneal"``): each pass proposes one random
  applicable move per inner node (post-order) and accepts it when it lowers the
  cost, otherwise with probability ``exp(−ΔA / (A(N)·T))``: the increase is measured
  relative to the area of N, so one temperature suits the top and the bottom of the
  tree. ``T`` falls linearly from a peak to near zero in ``steps_per_cycle`` passes;
  ``cycles`` such cycles run with peaks falling linearly from
  ``initial_temperature``. The best tree seen is kept, then hill climbing finishes
  it (and the final tree); the cheaper result is returned.

Serial and deterministic (annealing draws from numba's generator seeded with
``seed`` inside the kernel). A pass costs O(n). Kensler reports better SAH and
up to ~15% faster rendering in architectural scenes; the Devillers thesis finds it
about two orders of magnitude slower than reinsertion (``+reinsert``) for similar
quality. The depth guard of :func:`rayaccel.bvh.layouts.linked_tree.linked_to_canonical` keeps the
result within ``MAX_DEPTH``; should it rebalance (raising the cost), the input tree
is returned instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import linked_to_canonical, to_linked
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.sah import node_half_area, union_half_area
from rayaccel.scene.mesh import TriangleMesh

METHODS = ("hill", "anneal")

#: Moves at N: L↔RL, L↔RR, R↔LL, R↔LR, LL↔RL, LL↔RR.
N_MOVES = 6

#: A hill-climbing move must lower the area by this fraction of A(N): rounding in the
#: area differences can then never make two moves undo each other forever.
MIN_GAIN = 1e-9


@dataclass(frozen=True, slots=True)
class RotateOptions:
    """Options of the ``+rotate`` step.

    Attributes
    ----------
    method : {"hill", "anneal"}
        Hill climbing (fast, stops in the nearest local minimum) or simulated
        annealing followed by hill climbing (slower, can escape local minima).
    max_passes : int
        Upper bound on hill-climbing passes over the tree (each pass O(n)).
    initial_temperature : float
        Annealing: first peak temperature, in units of a move's area increase
        relative to the area of the node it is applied at (0.1: a move that grows
        the children by 10% of A(N) is accepted with probability 1/e).
    cycles : int
        Annealing: number of cooling cycles; the peaks fall linearly to
        ``initial_temperature / cycles``.
    steps_per_cycle : int
        Annealing: passes per cycle; the temperature falls linearly within a cycle.
    seed : int
        Annealing: seed of the move proposals and acceptance draws (0..2**32-1).
    """

    method: str = "hill"
    max_passes: int = 200
    initial_temperature: float = 0.1
    cycles: int = 4
    steps_per_cycle: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InvalidInputError(f"method: expected one of {METHODS}, got {self.method!r}")
        if self.max_passes < 1:
            raise InvalidInputError(f"max_passes: expected >= 1, got {self.max_passes}")
        if not (self.initial_temperature > 0 and np.isfinite(self.initial_temperature)):
            raise InvalidInputError(
                f"initial_temperature: expected a finite value > 0, got {self.initial_temperature}"
            )
        if self.cycles < 1:
            raise InvalidInputError(f"cycles: expected >= 1, got {self.cycles}")
        if self.steps_per_cycle < 1:
            raise InvalidInputError(f"steps_per_cycle: expected >= 1, got {self.steps_per_cycle}")
        if not 0 <= self.seed < 2**32:
            raise InvalidInputError(f"seed: expected 0..2**32-1, got {self.seed}")


@cpu_inline
def move_delta(node, move, left, right, lo, hi):
    """Return the change of the inner-node area sum if ``move`` is applied at ``node``.

    Parameters
    ----------
    node : int
        An inner node of the linked tree ``left``/``right`` (``-1``: leaf).
    move : int
        ``0..N_MOVES-1``: L with RL or RR (0, 1), R with LL or LR (2, 3), LL with RL or
        RR (4, 5) (Kensler 2008, Fig. 2).
    left, right : (n,) int32 ndarray
    lo, hi : (n, 3) float32 ndarray
        Node boxes.

    Returns
    -------
    float64
        ``ΔA``, the change of the half areas of N's children (the only boxes the move
        changes); ``inf`` when the move needs a grandchild that is a leaf. The SAH cost
        changes by ``C_inner·ΔA/A(root)``.
    """
    a = left[node]
    b = right[node]
    if move < 2:
        # L with a child of R: R's box becomes L ∪ (R's other child).
        if left[b] < 0:
            return np.inf
        other = right[b] if move == 0 else left[b]
        return union_half_area(lo, hi, a, other) - node_half_area(lo, hi, b)
    if move < 4:
        # R with a child of L: L's box becomes R ∪ (L's other child).
        if left[a] < 0:
            return np.inf
        other = right[a] if move == 2 else left[a]
        return union_half_area(lo, hi, b, other) - node_half_area(lo, hi, a)
    # LL with RL or RR: both child boxes change.
    if left[a] < 0 or left[b] < 0:
        return np.inf
    ll = left[a]
    lr = right[a]
    rl = left[b]
    rr = right[b]
    old = node_half_area(lo, hi, a) + node_half_area(lo, hi, b)
    if move == 4:
        return union_half_area(lo, hi, rl, lr) + union_half_area(lo, hi, ll, rr) - old
    return union_half_area(lo, hi, rr, lr) + union_half_area(lo, hi, rl, ll) - old


@cpu_inline
def _refit_node(x, left, right, lo, hi):
    """Set the box of inner node ``x`` to the union of its children's."""
    a = left[x]
    b = right[x]
    for k in range(3):
        lo[x, k] = min(lo[a, k], lo[b, k])
        hi[x, k] = max(hi[a, k], hi[b, k])


@cpu_inline
def apply_move(node, move, left, right, lo, hi):
    """Apply ``move`` at ``node`` in place: exchange two subtrees and refit N's children.

    Parameters are those of :func:`move_delta`; ``move`` must be possible there (a finite
    delta). ``left``, ``right``, ``lo`` and ``hi`` are updated; no other node changes.
    """
    a = left[node]
    b = right[node]
    if move == 0:  # L <-> RL
        left[node] = left[b]
        left[b] = a
        _refit_node(b, left, right, lo, hi)
    elif move == 1:  # L <-> RR
        left[node] = right[b]
        right[b] = a
        _refit_node(b, left, right, lo, hi)
    elif move == 2:  # R <-> LL
        right[node] = left[a]
        left[a] = b
        _refit_node(a, left, right, lo, hi)
    elif move == 3:  # R <-> LR
        right[node] = right[a]
        right[a] = b
        _refit_node(a, left, right, lo, hi)
    elif move == 4:  # LL <-> RL
        ll = left[a]
        left[a] = left[b]
        left[b] = ll
        _refit_node(a, left, right, lo, hi)
        _refit_node(b, left, right, lo, hi)
    else:  # LL <-> RR
        ll = left[a]
        left[a] = right[b]
        right[b] = ll
        _refit_node(a, left, right, lo, hi)
        _refit_node(b, left, right, lo, hi)


@cpu_inline
def _post_order(root, left, right, order, stack):
    """Write the inner nodes below ``root`` in post-order into ``order``; return their count."""
    # A pre-order walk that visits the right child first, reversed, is a post-order.
    m = 0
    sp = 1
    stack[0] = root
    while sp > 0:
        sp -= 1
        x = stack[sp]
        if left[x] < 0:
            continue
        order[m] = x
        m += 1
        stack[sp] = left[x]
        stack[sp + 1] = right[x]
        sp += 2
    for i in range(m // 2):
        order[i], order[m - 1 - i] = order[m - 1 - i], order[i]
    return m


@cpu_inline
def _hill_pass(order, m, left, right, lo, hi):
    """Apply the best improving move at every node of ``order``; return the moves made."""
    moves = 0
    for t in range(m):
        node = order[t]
        best_move = -1
        best_delta = -MIN_GAIN * node_half_area(lo, hi, node)
        for move in range(N_MOVES):
            delta = move_delta(node, move, left, right, lo, hi)
            if delta < best_delta:
                best_delta = delta
                best_move = move
        if best_move >= 0:
            apply_move(node, best_move, left, right, lo, hi)
            moves += 1
    return moves


@cpu_inline
def _inner_area(order, m, lo, hi):
    total = 0.0
    for t in range(m):
        total += node_half_area(lo, hi, order[t])
    return total


@cpu_kernel()
def _hill_climb(root, left, right, lo, hi, max_passes):
    """Hill-climb in place until no move improves (Kensler 2008 §3); return the passes run."""
    n = left.shape[0]
    order = np.empty(n, dtype=np.int32)
    stack = np.empty(n + 2, dtype=np.int32)
    passes = 0
    while passes < max_passes:
        m = _post_order(root, left, right, order, stack)
        passes += 1
        if _hill_pass(order, m, left, right, lo, hi) == 0:
            break
    return passes


@cpu_kernel()
def _anneal(root, left, right, lo, hi, best_left, best_right, best_lo, best_hi, schedule, seed):
    """Anneal the tree in place (Kensler 2008 §4); the best tree seen goes to ``best_*``.

    ``schedule`` holds the temperature of every pass. Returns the best inner-area sum.
    """
    # numba's generator (per thread, seeded here), not numpy's global state.
    np.random.seed(seed)  # noqa: NPY002
    n = left.shape[0]
    order = np.empty(n, dtype=np.int32)
    stack = np.empty(n + 2, dtype=np.int32)
    valid = np.empty(N_MOVES, dtype=np.int32)
    m = _post_order(root, left, right, order, stack)
    best = _inner_area(order, m, lo, hi)
    best_left[:] = left
    best_right[:] = right
    best_lo[:] = lo
    best_hi[:] = hi
    for s in range(schedule.shape[0]):
        temperature = schedule[s]
        m = _post_order(root, left, right, order, stack)
        for t in range(m):
            node = order[t]
            area = node_half_area(lo, hi, node)
            if not area > 0.0:
                continue
            # Propose one applicable move uniformly at random (moves 0-1 need an inner
            # R, 2-3 an inner L, 4-5 both).
            l_inner = left[left[node]] >= 0
            r_inner = left[right[node]] >= 0
            n_valid = 0
            for move in range(N_MOVES):
                if (r_inner or 2 <= move < 4) and (l_inner or move < 2):
                    valid[n_valid] = move
                    n_valid += 1
            if n_valid == 0:
                continue
            move = valid[min(int(np.random.random() * n_valid), n_valid - 1)]  # noqa: NPY002
            delta = move_delta(node, move, left, right, lo, hi)
            # Metropolis: always downhill, uphill with probability exp(-ΔA / (A(N)·T)).
            u = np.random.random()  # noqa: NPY002
            if delta < 0.0 or u < np.exp(-delta / (area * temperature)):
                apply_move(node, move, left, right, lo, hi)
        total = _inner_area(order, m, lo, hi)
        if total < best:
            best = total
            best_left[:] = left
            best_right[:] = right
            best_lo[:] = lo
            best_hi[:] = hi
    return best


@cpu_kernel()
def _tree_inner_area(root, left, right, lo, hi):
    n = left.shape[0]
    order = np.empty(n, dtype=np.int32)
    stack = np.empty(n + 2, dtype=np.int32)
    m = _post_order(root, left, right, order, stack)
    return _inner_area(order, m, lo, hi)


def annealing_schedule(opt: RotateOptions) -> np.ndarray:
    """Return the temperature of every annealing pass (float64, ``cycles·steps_per_cycle``)."""
    peaks = opt.initial_temperature * (opt.cycles - np.arange(opt.cycles)) / opt.cycles
    fall = (opt.steps_per_cycle - np.arange(opt.steps_per_cycle)) / opt.steps_per_cycle
    return np.ascontiguousarray(np.outer(peaks, fall).ravel(), dtype=np.float64)


@register("step", "bvh2+rotate")
def rotate(bvh: Bvh2, mesh: TriangleMesh, options: RotateOptions | None = None) -> Bvh2:
    """Tree rotations: hill climbing or simulated annealing on local subtree swaps.

    Return ``bvh`` improved by tree rotations (see the module docstring).

    Parameters
    ----------
    bvh : Bvh2
    mesh : TriangleMesh
        Unused (leaves and their boxes do not change).
    options : RotateOptions, optional

    Returns
    -------
    Bvh2
        Same leaves; SAH cost no higher than the input's.

    References
    ----------
    Kensler 2008, Tree Rotations for Improving Bounding Volume Hierarchies.
    """
    opt = options or RotateOptions()
    if bvh.n_nodes < 5:
        return bvh
    tree, _ = to_linked(bvh)
    root = np.int32(0)
    passes = np.int32(opt.max_passes)
    if opt.method == "anneal":
        # Anneal from the hill-climbing optimum, so annealing can only do better.
        _hill_climb(root, tree.left, tree.right, tree.lo, tree.hi, passes)
        best = (tree.left.copy(), tree.right.copy(), tree.lo.copy(), tree.hi.copy())
        _anneal(root, tree.left, tree.right, tree.lo, tree.hi, *best,
                annealing_schedule(opt), np.int64(opt.seed))  # fmt: skip
        # Finish both the final and the best tree seen by hill climbing; keep the cheaper.
        _hill_climb(root, tree.left, tree.right, tree.lo, tree.hi, passes)
        _hill_climb(root, *best, passes)
        if _tree_inner_area(root, *best) < _tree_inner_area(
            root, tree.left, tree.right, tree.lo, tree.hi
        ):
            tree = tree._replace(left=best[0], right=best[1], lo=best[2], hi=best[3])
    else:
        _hill_climb(root, tree.left, tree.right, tree.lo, tree.hi, passes)
    out = linked_to_canonical(tree, 0, bvh.n_prims, collapse=False)
    # The depth guard may rebalance a deep subtree, which can cost more than the input.
    return out if out.sah_cost() <= bvh.sah_cost() else bvh
