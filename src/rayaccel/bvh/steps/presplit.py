"""Triangle pre-splitting, as a build step run before any builder (``+presplit``).

Large or long diagonal triangles have boxes much bigger than themselves, and one such
box inflates every node above it. Pre-splitting hands the builder several smaller
boxes per such triangle instead (:class:`~rayaccel.bvh.builders.refs.BuildRefs`), each
naming the whole triangle: traversal still intersects the original triangle, so hits
are exact, while leaves get tighter. Unlike SBVH (Stich et al. 2009) the splits are
decided before and independently of the tree, so any builder can use them
(``bvh2.lbvh+presplit``, ``bvh2.binned_sah+presplit``). Two methods:

``"evh"`` — edge volume heuristic (Dammertz & Keller 2008, "The Edge Volume
Heuristic – Robust Triangle Subdivision for Improved BVH Performance", IEEE RT):
while the largest box volume of a (sub-)triangle's edges exceeds ``V_scene /
2^t``, split the triangle at that edge's midpoint into two triangles, and recurse
(at most ``max_depth`` levels). Sub-triangle vertices are kept in float64 (midpoints
of float32 values are exact there) and boxes are rounded outward to float32. Edges in
an axis-aligned plane have zero box volume, so triangles lying in such planes (walls,
floors) are never split. Reported: up to 10× faster on problematic scenes with +16%
references. No bound on the total number of references.

``"median"`` — spatial-median pre-splitting (Karras & Aila 2013, "Fast Parallel
Construction of High-Quality Bounding Volume Hierarchies", HPG, §5.9). The spatial
median planes of the scene box form a hierarchy: level 1 halves an axis, level 2
quarters it, and so on. A triangle's priority is ``p = (X^-l · (A_aabb −
A_tri))^Y``, where ``l`` is the level of the most important plane crossing its box,
``A_aabb`` the box's surface area and ``A_tri`` the triangle's area (the paper's
``A_ideal``, the area its pieces' boxes tend to, is approximated by ``A_tri`` as in
ALGORITHMS.md §5.6 and madmann91/bvh's splitter). A global scale ``D`` is found
by bisection (serial, O(N) per halving) so that the extra references ``Σ floor(D·p)``
stay within ``budget · N``; each triangle is then split recursively into
``1 + floor(D·p)`` pieces, always at the most important median plane crossing the
current box on its longest axis, the pieces' boxes coming from clipping the triangle
exactly against the plane and intersecting with the current box (as SBVH does); the
remaining count is shared between the halves in proportion to their longest extents.

Both methods run in parallel over chunks of triangles in two passes (count the
pieces, then write them at prefix-summed offsets), so the output does not depend on
the thread count. Pieces of one triangle that land in the same leaf are merged after
building (Karras & Aila §5.9; :func:`rayaccel.bvh.builders.refs.remove_leaf_duplicates`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import prange

from rayaccel._jit import cpu_inline, cpu_kernel
from rayaccel._variant import register
from rayaccel.bvh.builders.refs import BuildRefs
from rayaccel.dtypes import INDEX, REAL
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.clip import split_triangle_bounds
from rayaccel.kernels.triangle import cross3, triangle_edges64
from rayaccel.scene.mesh import TriangleMesh

#: Finest spatial-median level searched (2^-32 of the scene extent is below float32 precision).
MAX_LEVEL = 32
#: Deepest EVH recursion allowed by ``max_depth``.
MAX_EVH_DEPTH = 16
#: Triangles per parallel work item (each item allocates its own recursion stacks).
CHUNK = 2048
#: Entries of the median recursion stack: the larger half is pushed, so it holds
#: at most ``log2(pieces) + 1`` entries, and pieces < 2^62.
_MEDIAN_STACK = 64


@dataclass(frozen=True, slots=True)
class PresplitOptions:
    """Options of the ``+presplit`` step.

    Attributes
    ----------
    method : {"median", "evh"}
        ``"median"`` (Karras & Aila 2013, default): the reference count is bounded by
        ``budget`` and diagonal triangles in axis-aligned planes are split too.
        ``"evh"`` (Dammertz & Keller 2008): no budget, split by edge box volume.
    threshold_exponent : float
        EVH ``t``: split while an edge's box volume exceeds ``V_scene / 2^t`` (0..64;
        14 as in the open implementation; larger splits more).
    max_depth : int
        EVH recursion depth (0..16): a triangle becomes at most ``2^max_depth`` parts.
    budget : float
        Median: extra references as a fraction of the triangle count (0..4);
        0.3 gives at most 1.3·N references (Karras & Aila use 30–50%).
    priority_base, priority_exponent : float
        Median: ``X`` (>= 1) and ``Y`` (in (0, 4]) of the priority ``(X^-l ·
        (A_aabb − A_tri))^Y`` (paper: X = 2, Y = 1/3).
    """

    method: str = "median"
    threshold_exponent: float = 14.0
    max_depth: int = 8
    budget: float = 0.3
    priority_base: float = 2.0
    priority_exponent: float = 1.0 / 3.0

    def __post_init__(self) -> None:
        if self.method not in ("median", "evh"):
            raise InvalidInputError(f"method: expected 'median' or 'evh', got {self.method!r}")
        if not 0 <= self.threshold_exponent <= 64:
            raise InvalidInputError(
                f"threshold_exponent: expected 0..64, got {self.threshold_exponent}"
            )
        if not (float(self.max_depth).is_integer() and 0 <= self.max_depth <= MAX_EVH_DEPTH):
            raise InvalidInputError(
                f"max_depth: expected an integer 0..{MAX_EVH_DEPTH}, got {self.max_depth}"
            )
        if not 0 <= self.budget <= 4:
            raise InvalidInputError(f"budget: expected 0..4, got {self.budget}")
        if not (1 <= self.priority_base < math.inf):
            raise InvalidInputError(f"priority_base: expected >= 1, got {self.priority_base}")
        if not 0 < self.priority_exponent <= 4:
            raise InvalidInputError(
                f"priority_exponent: expected (0, 4], got {self.priority_exponent}"
            )


# -- shared helpers ----------------------------------------------------------------------------


@cpu_inline
def _round_down(x):
    """Largest float32 ``<= x`` (float64 ``x``)."""
    f = np.float32(x)
    if np.float64(f) > x:
        f = np.nextafter(f, np.float32(-np.inf))
    return f


@cpu_inline
def _round_up(x):
    """Smallest float32 ``>= x`` (float64 ``x``)."""
    f = np.float32(x)
    if np.float64(f) < x:
        f = np.nextafter(f, np.float32(np.inf))
    return f


def _pieces(counts: np.ndarray) -> tuple[np.ndarray, BuildRefs]:
    """Return exclusive offsets of ``counts`` and empty reference arrays of their total."""
    offsets = np.zeros(counts.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    m = int(offsets[-1])
    return offsets, BuildRefs(
        np.empty((m, 3), dtype=REAL), np.empty((m, 3), dtype=REAL), np.empty(m, dtype=INDEX)
    )


# -- edge volume heuristic (Dammertz & Keller 2008) --------------------------------------------


@cpu_kernel(parallel=True)
def _evh_kernel(tri, threshold, max_depth, fill, offsets, out_lo, out_hi, out_prim):
    """Count (``fill`` False: ``offsets[t] = pieces``) or write the EVH pieces of ``tri``.

    Parameters
    ----------
    tri : (F, 3, 3) float32
    threshold : float64
        Split while the largest edge box volume exceeds this.
    max_depth : int
    fill : bool
    offsets : (F + 1,) int64
        Output (counting) or input (filling): first piece slot of each triangle.
    out_lo, out_hi : (m, 3) float32; out_prim : (m,) int32
        Written when filling (``m = offsets[F]``).
    """
    n = tri.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    for c in prange(n_chunks):
        # One stack per work item: a pop pushes two children, so depth + 1 entries suffice.
        verts = np.empty((max_depth + 2, 9), dtype=np.float64)
        level = np.empty(max_depth + 2, dtype=np.int32)
        for t in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            for v in range(3):
                for a in range(3):
                    verts[0, 3 * v + a] = tri[t, v, a]
            level[0] = 0
            sp = 1
            slot = offsets[t] if fill else 0
            while sp > 0:
                sp -= 1
                # The edge with the largest box volume decides.
                best = -1.0
                e = 0
                for k in range(3):
                    f = (k + 1) % 3
                    vol = 1.0
                    for a in range(3):
                        vol *= abs(verts[sp, 3 * f + a] - verts[sp, 3 * k + a])
                    if vol > best:
                        best = vol
                        e = k
                if best > threshold and level[sp] < max_depth:
                    # Split edge (e, f) at its midpoint m: children (e, m, g) and (m, f, g).
                    f = (e + 1) % 3
                    g = 3 - e - f
                    d = level[sp] + 1
                    for a in range(3):
                        mid = 0.5 * (verts[sp, 3 * e + a] + verts[sp, 3 * f + a])
                        verts[sp + 1, 3 * e + a] = mid
                        verts[sp + 1, 3 * f + a] = verts[sp, 3 * f + a]
                        verts[sp + 1, 3 * g + a] = verts[sp, 3 * g + a]
                        verts[sp, 3 * f + a] = mid
                    level[sp] = d
                    level[sp + 1] = d
                    sp += 2
                    continue
                # A final piece: its box, rounded outward to float32.
                if fill:
                    for a in range(3):
                        x0 = verts[sp, a]
                        x1 = verts[sp, 3 + a]
                        x2 = verts[sp, 6 + a]
                        out_lo[slot, a] = _round_down(min(x0, min(x1, x2)))
                        out_hi[slot, a] = _round_up(max(x0, max(x1, x2)))
                    out_prim[slot] = t
                slot += 1
            if not fill:
                offsets[t] = slot


def presplit_evh(tri: np.ndarray, threshold: float, max_depth: int) -> BuildRefs:
    """Return the EVH pieces of ``tri (F, 3, 3)`` (see the module docstring)."""
    n = tri.shape[0]
    counts = np.zeros(n + 1, dtype=np.int64)
    empty = np.empty((0, 3), dtype=REAL)
    no_prim = np.empty(0, dtype=INDEX)
    _evh_kernel(tri, np.float64(threshold), max_depth, False, counts, empty, empty, no_prim)
    offsets, refs = _pieces(counts[:n])
    _evh_kernel(tri, np.float64(threshold), max_depth, True, offsets, *refs)
    return refs


# -- spatial-median pre-splitting (Karras & Aila 2013) -----------------------------------------


@cpu_inline
def _median_plane(lo, hi, s_lo, s_ext):
    """Return ``(level, pos)`` of the most important median plane strictly inside ``(lo, hi)``.

    Planes of level ``l`` sit at odd multiples of ``2^-l`` of the scene extent
    ``s_ext`` from ``s_lo``; ``pos`` is a float32 value. ``(0, 0.0)`` when none is
    found down to :data:`MAX_LEVEL` (flat box or flat scene axis).
    """
    if not (s_ext > 0 and hi > lo):
        return 0, 0.0
    u_lo = (np.float64(lo) - s_lo) / s_ext
    u_hi = (np.float64(hi) - s_lo) / s_ext
    cell = 0.5
    for level in range(1, MAX_LEVEL + 1):
        # The last grid plane strictly below u_hi; inside if it is above u_lo.
        u = (math.ceil(u_hi / cell) - 1.0) * cell
        if u > u_lo:
            pos = np.float64(np.float32(s_lo + u * s_ext))
            if lo < pos < hi:
                return level, pos
        cell *= 0.5
    return 0, 0.0


@cpu_inline
def _longest_extent(box):
    """Return ``(axis, extent)`` of the longest axis of ``box[0:6]`` (float64 extent)."""
    axis = 0
    ext = np.float64(box[3]) - box[0]
    for a in range(1, 3):
        e = np.float64(box[3 + a]) - box[a]
        if e > ext:
            ext = e
            axis = a
    return axis, ext


@cpu_kernel(parallel=True)
def _median_priorities(tri, s_lo, s_ext, base, exponent):
    """Return the ``(F,)`` float64 priority ``(X^-l · (A_aabb − A_tri))^Y`` of each triangle."""
    n = tri.shape[0]
    p = np.zeros(n, dtype=np.float64)
    for t in prange(n):
        # Box extents, and the most important plane crossing the box on any axis.
        best = 0
        ex = 0.0
        ey = 0.0
        ez = 0.0
        for a in range(3):
            lo = np.float64(min(tri[t, 0, a], min(tri[t, 1, a], tri[t, 2, a])))
            hi = np.float64(max(tri[t, 0, a], max(tri[t, 1, a], tri[t, 2, a])))
            level, _ = _median_plane(lo, hi, s_lo[a], s_ext[a])
            if level > 0 and (best == 0 or level < best):
                best = level
            if a == 0:
                ex = hi - lo
            elif a == 1:
                ey = hi - lo
            else:
                ez = hi - lo
        if best == 0:
            continue
        a_box = 2.0 * (ex * ey + ey * ez + ez * ex)
        # Triangle area (A_ideal of the paper approximated by A_tri).
        e1x, e1y, e1z, e2x, e2y, e2z = triangle_edges64(tri, t)
        cx, cy, cz = cross3(e1x, e1y, e1z, e2x, e2y, e2z)
        a_tri = 0.5 * math.sqrt(cx * cx + cy * cy + cz * cz)
        gain = max(a_box - a_tri, 0.0)
        p[t] = (base ** (-best) * gain) ** exponent
    return p


@cpu_inline
def _extra(p, scale, cap):
    """Extra pieces of a triangle of priority ``p``: ``min(floor(scale·p), cap)``."""
    x = scale * p
    if x >= cap:
        return cap
    return np.int64(math.floor(x))


@cpu_kernel()
def _solve_scale(p, cap):
    """Return the largest scale ``D`` (to float64 bisection) with ``Σ extra(D·p) <= cap``.

    Serial: the sum is over the triangles with ``p > 0`` only and the bracket starts
    at ``cap / Σp`` (where the sum is about ``cap``), so 40 halvings suffice.
    """
    n = p.shape[0]
    live = np.empty(n, dtype=np.float64)
    m = 0
    total_p = 0.0
    p_max = 0.0
    for t in range(n):
        if p[t] > 0:
            live[m] = p[t]
            m += 1
            total_p += p[t]
            p_max = max(p_max, p[t])
    if m == 0 or cap <= 0:
        return 0.0
    # Σ floor(D·p) <= D·Σp, so D = cap/Σp fits; D = (cap + m)/Σp overshoots unless capped.
    lo = cap / total_p
    hi = max((cap + m + 1.0) / total_p, (cap + 1.0) / p_max)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        total = np.int64(0)
        for i in range(m):
            total += _extra(live[i], mid, cap)
            if total > cap:
                break
        if total <= cap:
            lo = mid
        else:
            hi = mid
    return lo


@cpu_kernel(parallel=True)
def _median_kernel(tri, p, scale, cap, s_lo, s_ext, fill, offsets, out_lo, out_hi, out_prim):
    """Count (``fill`` False) or write the median-split pieces of every triangle.

    Parameters
    ----------
    tri : (F, 3, 3) float32
    p : (F,) float64
        Priorities; triangle ``t`` gets ``1 + min(floor(scale·p[t]), cap)`` pieces at
        most (fewer when a box becomes too thin to split).
    s_lo, s_ext : (3,) float64
        Scene box origin and extent (the median-plane hierarchy).
    fill : bool
    offsets : (F + 1,) int64
        Output (counting) or input (filling): first piece slot of each triangle.
    out_lo, out_hi : (m, 3) float32; out_prim : (m,) int32
        Written when filling.
    """
    n = tri.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    for c in prange(n_chunks):
        s_box = np.empty((_MEDIAN_STACK, 6), dtype=np.float32)
        s_cnt = np.empty(_MEDIAN_STACK, dtype=np.int64)
        cur = np.empty(6, dtype=np.float32)
        left = np.empty(6, dtype=np.float32)
        right = np.empty(6, dtype=np.float32)
        for t in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            for a in range(3):
                s_box[0, a] = min(tri[t, 0, a], min(tri[t, 1, a], tri[t, 2, a]))
                s_box[0, 3 + a] = max(tri[t, 0, a], max(tri[t, 1, a], tri[t, 2, a]))
            s_cnt[0] = 1 + _extra(p[t], scale, cap)
            sp = 1
            slot = offsets[t] if fill else 0
            while sp > 0:
                sp -= 1
                for k in range(6):
                    cur[k] = s_box[sp, k]
                cnt = s_cnt[sp]
                while True:
                    # Split at the most important plane on the longest axis (else the middle).
                    pos = 0.0
                    axis, ext = _longest_extent(cur)
                    if cnt > 1 and ext > 0:
                        level, pos = _median_plane(
                            cur[axis], cur[3 + axis], s_lo[axis], s_ext[axis]
                        )
                        if level == 0:
                            pos = np.float64(
                                np.float32(0.5 * (np.float64(cur[axis]) + cur[3 + axis]))
                            )
                            if not (cur[axis] < pos < cur[3 + axis]):
                                pos = 0.0
                                cnt = 1
                    else:
                        cnt = 1
                    if cnt <= 1:
                        if fill:
                            for a in range(3):
                                out_lo[slot, a] = cur[a]
                                out_hi[slot, a] = cur[3 + a]
                            out_prim[slot] = t
                        slot += 1
                        break
                    split_triangle_bounds(tri, t, cur, axis, pos, left, right)
                    # Share the count by longest extent; keep the smaller half, push the larger.
                    _, e_l = _longest_extent(left)
                    _, e_r = _longest_extent(right)
                    n_l = cnt // 2
                    if e_l + e_r > 0:
                        n_l = np.int64(math.floor(cnt * e_l / (e_l + e_r) + 0.5))
                    n_l = min(max(n_l, 1), cnt - 1)
                    n_r = cnt - n_l
                    if n_l >= n_r:
                        for k in range(6):
                            s_box[sp, k] = left[k]
                            cur[k] = right[k]
                        s_cnt[sp] = n_l
                        cnt = n_r
                    else:
                        for k in range(6):
                            s_box[sp, k] = right[k]
                            cur[k] = left[k]
                        s_cnt[sp] = n_r
                        cnt = n_l
                    sp += 1
            if not fill:
                offsets[t] = slot


def presplit_median(tri: np.ndarray, budget: float, base: float, exponent: float) -> BuildRefs:
    """Return the spatial-median pieces of ``tri (F, 3, 3)`` (see the module docstring)."""
    n = tri.shape[0]
    flat = tri.reshape(-1, 3)
    s_lo = flat.min(axis=0).astype(np.float64)
    s_ext = flat.max(axis=0).astype(np.float64) - s_lo
    p = _median_priorities(tri, s_lo, s_ext, np.float64(base), np.float64(exponent))
    cap = np.int64(int(budget * n))
    scale = _solve_scale(p, cap)
    counts = np.zeros(n + 1, dtype=np.int64)
    empty = np.empty((0, 3), dtype=REAL)
    no_prim = np.empty(0, dtype=INDEX)
    args = (tri, p, np.float64(scale), cap, s_lo, s_ext)
    _median_kernel(*args, False, counts, empty, empty, no_prim)
    offsets, refs = _pieces(counts[:n])
    _median_kernel(*args, True, offsets, *refs)
    return refs


@register("step", "bvh2+presplit", stage="before")
def presplit(mesh: TriangleMesh, options: PresplitOptions | None = None) -> BuildRefs:
    """Split large triangles into smaller boxes before building (spatial median or EVH).

    Return the pre-split references of ``mesh`` (see the module docstring).

    Parameters
    ----------
    mesh : TriangleMesh
    options : PresplitOptions, optional

    Returns
    -------
    BuildRefs
        At least one reference per triangle, pieces of triangle ``t`` contiguous and
        in triangle order; ``n_refs <= (1 + budget) · N`` for ``"median"``.

    References
    ----------
    Karras & Aila 2013, Fast Parallel Construction of High-Quality BVHs, §5.9;
    Dammertz & Keller 2008, The Edge Volume Heuristic.
    """
    opt = options or PresplitOptions()
    tri = np.ascontiguousarray(mesh.triangles(), dtype=REAL)
    if opt.method == "evh":
        flat = tri.reshape(-1, 3)
        extent = flat.max(axis=0).astype(np.float64) - flat.min(axis=0)
        volume = float(np.prod(extent))
        threshold = volume * 2.0 ** (-float(opt.threshold_exponent))
        return presplit_evh(tri, threshold, int(opt.max_depth))
    return presplit_median(
        tri, float(opt.budget), float(opt.priority_base), float(opt.priority_exponent)
    )
