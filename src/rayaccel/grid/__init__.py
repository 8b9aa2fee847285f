"""Grids: the uniform grid, its empty-space skipping variants, and their 3D-DDA traversals.

The third family of the thesis (§3.3, §4.1.3, §5.4.4) after BVHs and kd-trees. Space
is cut into equal cells; each cell lists the triangles that overlap it, and a ray walks
the cells it pierces in order (Amanatides & Woo 1987), testing their triangles, until a
hit lies in the cell it is in. Builds are cheap and data-parallel (a count, a prefix
sum, a fill and one sort), at the price of cells that are empty or crowded.

Chapters: :mod:`~rayaccel.grid.layouts` (the canonical ``grid`` structure and the
traversal layout), :mod:`~rayaccel.grid.builders` (``grid.uniform`` and the skipping
variants ``grid.distance``, ``grid.macro_regions``, ``grid.mipmap``; ``grid.two_level``
and ``grid.irregular``) and
:mod:`~rayaccel.grid.traverse` (``grid.dda``, ``grid.skip``). Float64 meshes:
:mod:`~rayaccel.grid.precision` (why the cell margins already hold them).
"""
