"""BVH build steps chained to a builder key: ``bvh2.lbvh+reinsert``, ``bvh2.sbvh+presplit``.

A step of stage ``"after"`` post-processes a built ``bvh2`` (reinsertion, rotations,
treelet restructuring, leaf collapsing); the ``"before"`` step pre-splits triangles
into the references the builder builds over.
"""
