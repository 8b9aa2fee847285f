"""kd-trees: axis-aligned space subdivision with compact nodes (the second family of the thesis).

A kd-tree cuts space, not primitives: every inner node splits its cell by one
axis-aligned plane, the leaves tile the scene box, and a triangle is listed in every
leaf cell it overlaps (Havran 2000; Wald & Havran 2006). The chapters:

- :mod:`rayaccel.kdtree.layouts` — the canonical :class:`~rayaccel.kdtree.layouts.kdtree.KdTree`
  (8-byte inner nodes, leaves as ranges of a reference array) and the traversal
  layouts derived from it (triangles in leaf order; node boxes and parent links;
  ropes).
- :mod:`rayaccel.kdtree.builders` — ``kdtree.sah``, the O(N log N) event sweep of
  Wald & Havran 2006 with perfect splits, and ``kdtree.median``, the spatial-median
  baseline.
- :mod:`rayaccel.kdtree.traverse` — ``kdtree.stack`` (front to back with a stack),
  ``kdtree.restart`` and ``kdtree.backtrack`` (Foley & Sugerman 2005),
  ``kdtree.short_stack`` (Horn et al. 2007) and ``kdtree.ropes`` (Popov et al. 2007).
- :mod:`rayaccel.kdtree.precision` — float64 meshes: the tree's leaves list every float64
  triangle they touch.
"""
