"""Grid builders: the sort-based uniform grid and the empty-space skipping data built on it.

``grid.uniform`` (Kalojanov & Slusallek 2009: count, prefix sum, fill, sort by cell,
cell ranges; the cell/triangle test is exact, Akenine-Möller 2001), ``grid.distance``
(a chessboard distance field over the empty cells), ``grid.macro_regions``
(Devillers 1989: maximal empty boxes, grown with a summed-volume table) and
``grid.mipmap`` (an occupancy mip-map), besides ``grid.two_level`` (Kalojanov et al.
2011) and ``grid.irregular`` (Pérard-Gayot et al. 2017).
"""
