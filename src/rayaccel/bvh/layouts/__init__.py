"""BVH layouts: the canonical binary tree builders emit, and the forms derived from it.

``bvh2`` is the canonical binary BVH (:class:`rayaccel.bvh.layouts.bvh2.Bvh2`); the
packed, pairs, wide, link and hash layouts are derived from it for particular
traversals (tinybvh's ``ConvertFrom``); the linked tree is the working form the
bottom-up builders and the optimisation steps edit.
"""
