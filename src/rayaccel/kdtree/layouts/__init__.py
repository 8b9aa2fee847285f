"""kd-tree layouts: the canonical tree every builder emits and what traversals derive from it.

:mod:`rayaccel.kdtree.layouts.kdtree` holds :class:`KdTree` (compact 8-byte inner
nodes with adjacent children, leaves as ranges of a primitive-reference array, the
scene box kept beside the tree) and the trace layout all kd traversals read
(triangles copied in leaf order). Node boxes and parent links (``kdtree.backtrack``)
and ropes (``kdtree.ropes``) are derived next to the traversals that need them.
"""
