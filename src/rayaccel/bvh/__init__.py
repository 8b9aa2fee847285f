"""Bounding volume hierarchies: the canonical binary layout, its builders and traversals."""
