"""kd-tree traversals: front to back with a stack, and the stackless variants of the GPU papers.

Every traversal walks the ray's segment through the cells front to back and tests
the triangles of each leaf it meets with the shared watertight test
(:mod:`rayaccel.trace.leaf`), so its hits are the oracle's bit for bit. A node is
split at ``t_split = (split − o[axis])·inv[axis]``: the child the ray's direction
points away from on that axis is *near* (it holds the segment before
``t_split``), the other *far*; a ray lying in the plane (``t_split`` NaN) needs
both.

Cells are closed and triangles are not clipped, so two rules keep every hit: (1) a
triangle hit beyond the current leaf is kept, and later leaves are skipped only when
they begin beyond the closest hit; (2) the stack traversal visits a child whenever
its part of the segment is non-empty within the culling pad of
:func:`rayaccel.kernels.aabb.culling_pad` (the slack that covers the triangle test's
rounding), so a triangle touching a split plane, listed on one side only, is found
from either side.

``kdtree.stack`` (default) keeps the far child on a stack (Slusallek's lecture;
``order="position"`` picks the first child by the ray origin, the thesis's
KD_positional). ``kdtree.restart``, ``kdtree.backtrack`` (Foley & Sugerman 2005)
and ``kdtree.short_stack`` (Horn et al. 2007) visit the same leaves in the same
order without the stack, finding the next subtree from the root, from an ancestor
by parent links, or from a short ring of far children
(:mod:`rayaccel.kdtree.traverse.stackless`); ``kdtree.ropes`` (Popov et al. 2007)
walks from leaf to leaf through the neighbour links of the leaf faces.
"""
