"""BVH builders: each turns a mesh (or pre-split references) into the canonical ``bvh2``.

Top-down builders (binned SAH, sweep SAH, SBVH) supply a split function to the shared
top-down scheduler; bottom-up builders (LBVH, PLOC) and the insertion build make a
linked tree and convert it. Each registers under ``bvh2.<algorithm>``.
"""
