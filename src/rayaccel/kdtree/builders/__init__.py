"""kd-tree builders: the event sweep of Wald & Havran 2006 and a spatial-median baseline.

Both run the same top-down kernel (:mod:`rayaccel.kdtree.builders.sweep`): sorted
split events per node, classification of each triangle against the chosen plane,
and splicing of the children's event lists without re-sorting. ``kdtree.sah``
chooses the plane by the surface area heuristic over every event; ``kdtree.median``
cuts the longest axis of the cell in half.
"""
