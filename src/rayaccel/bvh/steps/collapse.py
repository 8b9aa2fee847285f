"""Leaf collapsing by the SAH, as a build step (``+collapse``).

Walks the tree bottom-up and replaces every subtree of at most ``max_leaf_size``
references by a single leaf when the surface area heuristic says the leaf costs no
more than the subtree: ``C_prim·A(n)·N(n) <= C_inner·A(n) + cost(left) + cost(right)``
(Meister & Bittner 2018 §4.4; Karras & Aila 2013 §4.4 do the same after treelet
restructuring). Useful after steps that work on one-primitive leaves and after
builders whose own leaves are small. Leaves are never split, so the tree's SAH cost
can only go down. Cost O(n), one refit pass and one emission pass
(:mod:`rayaccel.bvh.layouts.linked_tree`).
"""

from __future__ import annotations

from dataclasses import dataclass

from rayaccel._variant import register
from rayaccel.bvh.builders.lbvh import check_leaf_costs
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.layouts.linked_tree import collapsed_to_canonical, to_linked
from rayaccel.scene.mesh import TriangleMesh


@dataclass(frozen=True, slots=True)
class CollapseOptions:
    """Options of the ``+collapse`` step.

    Attributes
    ----------
    max_leaf_size : int
        Largest leaf a collapse may form (1..64).
    traversal_cost, intersection_cost : float
        SAH constants of the decision (1.2 and 1, Karras & Aila 2013).
    """

    max_leaf_size: int = 8
    traversal_cost: float = 1.2
    intersection_cost: float = 1.0

    def __post_init__(self) -> None:
        check_leaf_costs(self.max_leaf_size, self.traversal_cost, self.intersection_cost)


@register("step", "bvh2+collapse")
def collapse_leaves(bvh: Bvh2, mesh: TriangleMesh, options: CollapseOptions | None = None) -> Bvh2:
    """Merge subtrees into leaves where the SAH prefers a leaf.

    Return ``bvh`` with SAH leaf collapsing applied (see the module docstring).

    References
    ----------
    Meister & Bittner 2018, Parallel Locally-Ordered Clustering ..., §4.4.
    """
    opt = options or CollapseOptions()
    tree, _ = to_linked(bvh)
    return collapsed_to_canonical(tree, 0, bvh.n_prims, opt)
