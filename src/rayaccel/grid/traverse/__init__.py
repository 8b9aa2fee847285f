"""Grid traversals: the 3D-DDA (Amanatides & Woo 1987), plain or skipping empty space.

``grid.dda`` walks every cell a ray pierces; ``grid.skip`` jumps over the empty region
the grid stores for an empty cell (a cube from the distance field, a macro region).
Both return the oracle's hits.
"""
