"""Releasing a binary BVH's node boxes once the default queries no longer read them.

The default queries (``bvh2.wide`` for single rays, ``bvh2.packet`` for coherent
batches) read the 8-wide rows and the packed layout's triangles only: once those are
derived, the canonical tree's boxes (24 bytes per node, a quarter of what a ready BVH
holds) serve nothing they do. Issue 21 asks that derived data no query needs is not
kept, so an :class:`~rayaccel.api.Accel` drops them after its first default query and
recomputes them on the first use that reads its tree (another traversal, the geometry
queries, ``save``, ``refit``, pickling), keeping them from then on; ``info()``
recomputes them for its SAH without keeping them.

Dropping is only allowed when recomputing gives the same bits: every leaf box must be
the union of its triangles' corner boxes and every inner box the union of its
children's (:func:`boxes_are_unions`). Min and max are exact, so a bottom-up refit
(:func:`rayaccel.bvh.builders.refit_vertices.refit_bvh2`, Karras 2012 §4) then writes
the very boxes the builder wrote. Trees whose boxes are tighter than their triangles'
(SBVH and pre-split references, whose boxes are clipped triangles) or wider
(float64 meshes, whose boxes are widened by an ulp) fail the test and keep their
boxes.

Without its boxes a tree keeps its topology and its triangle order
(``node_first``, ``node_count``, ``prim_index``); its ``node_lo`` and ``node_hi`` are
``(0, 3)`` arrays, and every layout that refers to the tree (the packed layout's
``source``, the wide rows' ``packed``) is re-pointed at the box-less tree so that the
old boxes are really freed, and back again when they are restored.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numba import prange

from rayaccel._jit import cpu_kernel
from rayaccel.bvh.builders.refit_vertices import refit_bvh2
from rayaccel.bvh.layouts.bvh2 import Bvh2, PackedBvh2
from rayaccel.bvh.layouts.wide import WideBvh
from rayaccel.config import parallel_section
from rayaccel.dtypes import REAL, FloatArray, IntArray
from rayaccel.trace.run import LAYOUT_MS

#: What the default queries derive and read: with exactly these in an accel's cache the
#: boxes may go.
DEFAULT_LAYOUTS = frozenset({"bvh2.packed", "bvh2.wide8"})
#: The traversals that, with their default options, read only :data:`DEFAULT_LAYOUTS`.
TRAVERSALS = frozenset({"bvh2.wide", "bvh2.packet"})


@cpu_kernel(parallel=True)
def _mismatches(node_lo, node_hi, node_first, node_count, prim_index, vertices, faces):
    """Count the nodes whose box is not the union of its triangles' or its children's boxes."""
    n = node_count.shape[0]
    bad = 0
    for i in prange(n):
        u = np.uint64(i)
        first = node_first[u]
        count = node_count[u]
        lx = ly = lz = np.float32(np.inf)
        hx = hy = hz = np.float32(-np.inf)
        if count > 0:
            for j in range(first, first + count):
                face = np.uint64(prim_index[np.uint64(j)])
                for c in range(3):
                    v = np.uint64(faces[face, c])
                    lx = min(lx, vertices[v, 0])
                    ly = min(ly, vertices[v, 1])
                    lz = min(lz, vertices[v, 2])
                    hx = max(hx, vertices[v, 0])
                    hy = max(hy, vertices[v, 1])
                    hz = max(hz, vertices[v, 2])
        else:
            a = np.uint64(first)
            b = a + np.uint64(1)
            lx = min(node_lo[a, 0], node_lo[b, 0])
            ly = min(node_lo[a, 1], node_lo[b, 1])
            lz = min(node_lo[a, 2], node_lo[b, 2])
            hx = max(node_hi[a, 0], node_hi[b, 0])
            hy = max(node_hi[a, 1], node_hi[b, 1])
            hz = max(node_hi[a, 2], node_hi[b, 2])
        same = (
            lx == node_lo[u, 0] and ly == node_lo[u, 1] and lz == node_lo[u, 2]
            and hx == node_hi[u, 0] and hy == node_hi[u, 1] and hz == node_hi[u, 2]
        )  # fmt: skip
        if not same:
            bad += 1
    return bad


def boxes_are_unions(bvh: Bvh2, vertices: FloatArray, faces: IntArray) -> bool:
    """Return whether a refit over ``vertices`` and ``faces`` gives back ``bvh``'s boxes exactly.

    One parallel pass over the nodes, each checked against its triangles (a leaf) or
    its two children (an inner node): if every node passes, the bottom-up refit
    reproduces every box bit for bit.
    """
    if vertices.dtype != REAL or bvh.node_lo.shape[0] != bvh.n_nodes:
        return False
    with parallel_section():
        bad = _mismatches(
            bvh.node_lo, bvh.node_hi, bvh.node_first, bvh.node_count, bvh.prim_index,
            vertices, faces,
        )  # fmt: skip
    return int(bad) == 0


def releasable(cache: dict[str, Any]) -> bool:
    """Whether ``cache`` holds exactly the layouts of the default queries, and nothing else."""
    return set(cache) - {LAYOUT_MS} == DEFAULT_LAYOUTS


def without_boxes(bvh: Bvh2, cache: dict[str, Any]) -> Bvh2:
    """Return ``bvh`` without its boxes, and re-point ``cache``'s layouts at it."""
    empty = np.empty((0, 3), dtype=REAL)
    boxless = dataclasses.replace(bvh, node_lo=empty, node_hi=empty)
    _repoint(cache, bvh, boxless)
    return boxless


def with_boxes(boxless: Bvh2, vertices: FloatArray, faces: IntArray, cache: dict[str, Any]) -> Bvh2:
    """Return ``boxless`` with its boxes recomputed, and re-point ``cache``'s layouts at it."""
    full = refit_bvh2(boxless, vertices, faces)
    _repoint(cache, boxless, full)
    return full


def _repoint(cache: dict[str, Any], old: Bvh2, new: Bvh2) -> None:
    """Replace every cached layout that refers to ``old`` by one referring to ``new``."""
    packed = {}
    for name, layout in cache.items():
        if isinstance(layout, PackedBvh2) and layout.source is old:
            packed[id(layout)] = dataclasses.replace(layout, source=new)
            cache[name] = packed[id(layout)]
    for name, layout in cache.items():
        if isinstance(layout, WideBvh) and id(layout.packed) in packed:
            cache[name] = dataclasses.replace(layout, packed=packed[id(layout.packed)])
