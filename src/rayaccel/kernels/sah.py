"""Surface area heuristic: box half-areas and the cost of a split (MacDonald & Booth 1990).

MacDonald & Booth 1990, "Heuristics for ray tracing using space subdivision" (The
Visual Computer 6(3)): a ray that hits a convex box also hits a convex box inside it
with probability ``A(inner) / A(outer)``, so splitting a node of area ``A`` into
children of areas ``A_L``, ``A_R`` holding ``N_L``, ``N_R`` primitives costs

    ``C_trav + C_prim · (A_L·N_L + A_R·N_R) / A``

against ``C_prim · N`` for keeping it a leaf. Every top-down builder (binned, sweep and
spatial-split BVHs, kd-trees) and every tree optimizer compares such costs, and only
ratios of areas matter, so the helpers return the *half* area ``xy + yz + zx``.

Areas are evaluated in float64 from float32 bounds (the extents are exact there), and
each helper states its exact operation order: the builders' trees depend on these
roundings, so the same helper must serve every copy.

The ``*_py`` functions are plain Python (the oracles, and the source of the CUDA
versions); the unsuffixed names are their inlined CPU forms.
"""

from __future__ import annotations

import numpy as np

from rayaccel._jit import cpu_inline


def box_half_area_py(lo_x, lo_y, lo_z, hi_x, hi_y, hi_z):
    """Return the half surface area ``ex·ey + ey·ez + ez·ex`` of a box, in float64.

    Parameters
    ----------
    lo_x, lo_y, lo_z, hi_x, hi_y, hi_z : float32 or float64
        Box corners; an empty box (``hi < lo``) gives a meaningless value.

    Returns
    -------
    float64
    """
    ex = np.float64(hi_x) - lo_x
    ey = np.float64(hi_y) - lo_y
    ez = np.float64(hi_z) - lo_z
    return ex * ey + ey * ez + ez * ex


def bounds_half_area_py(bounds):
    """Return :func:`box_half_area_py` of a 6-tuple box ``(lo.x, lo.y, lo.z, hi.x, hi.y, hi.z)``.

    The form for a box grown in registers (:func:`rayaccel.kernels.box_grow.union_bounds`).
    """
    return box_half_area(bounds[0], bounds[1], bounds[2], bounds[3], bounds[4], bounds[5])


def node_half_area_py(lo, hi, i):
    """Return the half surface area of box ``i`` of ``lo``/``hi`` (``(n, 3)`` float32), in float64.

    ``i`` must be ``>= 0`` (it is used unsigned, so no wraparound code is emitted).
    """
    u = np.uint64(i)
    ex = np.float64(hi[u, 0]) - lo[u, 0]
    ey = np.float64(hi[u, 1]) - lo[u, 1]
    ez = np.float64(hi[u, 2]) - lo[u, 2]
    return ex * ey + ey * ez + ez * ex


def union_half_area_py(lo, hi, i, j):
    """Return the half surface area of the union of boxes ``i`` and ``j`` of ``lo``/``hi``."""
    ex = np.float64(max(hi[i, 0], hi[j, 0])) - min(lo[i, 0], lo[j, 0])
    ey = np.float64(max(hi[i, 1], hi[j, 1])) - min(lo[i, 1], lo[j, 1])
    ez = np.float64(max(hi[i, 2], hi[j, 2])) - min(lo[i, 2], lo[j, 2])
    return ex * ey + ey * ez + ez * ex


def sah_split_cost_py(trav_cost, isect_cost, area_left, n_left, area_right, n_right, inv_area):
    """Return the SAH cost of a split: ``C_trav + C_prim·(A_L·N_L + A_R·N_R)·(1/A)``.

    Parameters
    ----------
    trav_cost, isect_cost : float
        ``C_trav`` (one inner node) and ``C_prim`` (one primitive test).
    area_left, area_right : float64
        Half areas of the children's boxes.
    n_left, n_right : int
        Primitives (references) on each side.
    inv_area : float64
        ``1 / A`` of the node's half area (0 for a flat node, which makes every split
        cost ``C_trav``).

    Returns
    -------
    float64
        Evaluated in exactly this order, ``trav + (isect·(A_L·N_L + A_R·N_R))·inv``.
    """
    return trav_cost + isect_cost * (area_left * n_left + area_right * n_right) * inv_area


def sah_split_cost_scaled_py(trav_cost, cost_scale, area_left, n_left, area_right, n_right):
    """Return the SAH cost of a split with ``C_prim / A`` folded into one per-node factor.

    ``C_trav + cost_scale·(A_L·N_L + A_R·N_R)`` with ``cost_scale = C_prim·(1/A)``
    computed once per node: the form for a sweep evaluating every split of a node
    (``bvh2.sweep_sah``), one multiply fewer per candidate than
    :func:`sah_split_cost_py`. The two agree up to rounding (exactly when
    ``C_prim = 1``); each builder keeps one form, since its trees depend on it.
    """
    return trav_cost + cost_scale * (area_left * n_left + area_right * n_right)


box_half_area = cpu_inline(box_half_area_py)
bounds_half_area = cpu_inline(bounds_half_area_py)
node_half_area = cpu_inline(node_half_area_py)
union_half_area = cpu_inline(union_half_area_py)
sah_split_cost = cpu_inline(sah_split_cost_py)
sah_split_cost_scaled = cpu_inline(sah_split_cost_scaled_py)
