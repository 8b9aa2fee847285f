"""BVH traversals: each walks a layout derived from ``bvh2`` and registers as ``bvh2.<method>``.

The ordered stack (``bvh2.stack``) and the 8-wide stack (``bvh2.wide``) traversals, and
the stackless ones (skip pointers, parent links, bitstack, restart trail, perfect
hashing), all return exactly the hits of the stack traversal.
"""
