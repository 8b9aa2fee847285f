"""Grid traversals: the 3D-DDA (Amanatides & Woo 1987), plain or skipping empty space.

``grid.dda`` walks every cell a ray pierces; ``grid.skip`` jumps over the empty region
the grid stores for an empty cell (a cube from the distance field, a macro region, a
mip-map block). A two-level grid is walked DDA in DDA, an irregular grid cell by cell
through its expanded boxes (:mod:`~rayaccel.grid.traverse.irregular`); the steps all
walks share are in :mod:`~rayaccel.grid.traverse.walk`. All return the oracle's hits.
"""
