"""Procedural test scenes: deterministic meshes built from a few numbers.

Each function returns a :class:`~rayaccel.scene.mesh.TriangleMesh` that is
byte-identical on every call and platform (float64 construction, one final
float32 rounding; random scenes use numpy's PCG64 with a fixed seed).

- :func:`cornell_box` -- the Cornell box as measured at Cornell University's
  Program of Computer Graphics (Goral et al. 1984; data published with the
  Cornell Box page): room, ceiling light, short and tall blocks; Y up, millimetres.
- :func:`triangle_soup` -- uniformly scattered small triangles in the unit cube,
  the no-structure baseline.
- :func:`sphereflake` -- Haines' Standard Procedural Databases "balls" scene
  (Haines 1987): a sphere that sprouts nine spheres of a third of its radius,
  recursively, over a square floor; Z up. Spheres are tessellated icospheres.
- :func:`teapot` -- Newell's Utah teapot, tessellated from its 32 bicubic Bézier
  patches (Newell 1975; data in :mod:`rayaccel.scene.teapot_data`); Z up.
- :func:`teapot_in_stadium` -- the teapot on the floor of a closed box a thousand
  times wider: the scale disparity that defeats uniform grids (Haines 1988).

References
----------
C. M. Goral, K. E. Torrance, D. P. Greenberg, B. Battaile, "Modeling the
Interaction of Light Between Diffuse Surfaces", SIGGRAPH 1984.
E. Haines, "A Proposal for Standard Graphics Environments", IEEE Computer
Graphics and Applications 7(11), 1987, pp. 3-5.
E. Haines, "Spline Surface Rendering, and What's Wrong with Octrees", Ray Tracing
News 1(2), 1988 (the "teapot in a stadium" problem).
M. E. Newell, "The Utilization of Procedure Models in Digital Image Synthesis",
PhD thesis, University of Utah, 1975.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import numpy.typing as npt

from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.scene.teapot_data import NEWELL_PATCHES, NEWELL_VERTICES

F64Array = npt.NDArray[np.float64]
I64Array = npt.NDArray[np.int64]


def _int_in_range(name: str, value: object, low: int, high: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InvalidInputError(f"{name}: expected an int in [{low}, {high}], got {value!r}")
    if not low <= value <= high:
        raise InvalidInputError(f"{name}: expected an int in [{low}, {high}], got {value}")
    return int(value)


def _positive_float(name: str, value: object, high: float = math.inf) -> float:
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: expected a float, got {value!r}") from exc
    if not (0.0 < number <= high and math.isfinite(number)):
        raise InvalidInputError(f"{name}: expected a float in (0, {high}], got {number}")
    return number


def _label(base: str, **params: object) -> str:
    """Return ``base`` followed by the non-default parameters, e.g. ``sphereflake(level=3)``."""
    shown = ", ".join(f"{key}={value}" for key, value in params.items() if value is not None)
    return f"{base}({shown})" if shown else base


def _quads_to_triangles(quads: F64Array) -> tuple[F64Array, I64Array]:
    """Split ``(n, 4, 3)`` quads ``abcd`` into triangles ``abc`` and ``acd``."""
    vertices = quads.reshape(-1, 3)
    base = 4 * np.arange(quads.shape[0], dtype=np.int64)[:, None]
    faces = np.concatenate(
        [base + np.array([0, 1, 2]), base + np.array([0, 2, 3])], axis=1
    ).reshape(-1, 3)
    return vertices, faces


# ------------------------------------------------------------------- Cornell box

# Quads of the measured Cornell box (corners listed counter-clockwise seen from the
# side the surface faces: into the room for walls, outwards for the blocks).
_CORNELL_QUADS = np.array(
    [
        # floor
        [[552.8, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 559.2], [549.6, 0.0, 559.2]],
        # light (0.1 below the ceiling, so no triangle is coplanar with it)
        [[343.0, 548.7, 227.0], [343.0, 548.7, 332.0], [213.0, 548.7, 332.0],
         [213.0, 548.7, 227.0]],
        # ceiling
        [[556.0, 548.8, 0.0], [556.0, 548.8, 559.2], [0.0, 548.8, 559.2], [0.0, 548.8, 0.0]],
        # back wall
        [[549.6, 0.0, 559.2], [0.0, 0.0, 559.2], [0.0, 548.8, 559.2], [556.0, 548.8, 559.2]],
        # right wall (green, x = 0)
        [[0.0, 0.0, 559.2], [0.0, 0.0, 0.0], [0.0, 548.8, 0.0], [0.0, 548.8, 559.2]],
        # left wall (red, x = 556)
        [[552.8, 0.0, 0.0], [549.6, 0.0, 559.2], [556.0, 548.8, 559.2], [556.0, 548.8, 0.0]],
        # short block
        [[130.0, 165.0, 65.0], [82.0, 165.0, 225.0], [240.0, 165.0, 272.0],
         [290.0, 165.0, 114.0]],
        [[290.0, 0.0, 114.0], [290.0, 165.0, 114.0], [240.0, 165.0, 272.0],
         [240.0, 0.0, 272.0]],
        [[130.0, 0.0, 65.0], [130.0, 165.0, 65.0], [290.0, 165.0, 114.0], [290.0, 0.0, 114.0]],
        [[82.0, 0.0, 225.0], [82.0, 165.0, 225.0], [130.0, 165.0, 65.0], [130.0, 0.0, 65.0]],
        [[240.0, 0.0, 272.0], [240.0, 165.0, 272.0], [82.0, 165.0, 225.0], [82.0, 0.0, 225.0]],
        # tall block
        [[423.0, 330.0, 247.0], [265.0, 330.0, 296.0], [314.0, 330.0, 456.0],
         [472.0, 330.0, 406.0]],
        [[423.0, 0.0, 247.0], [423.0, 330.0, 247.0], [472.0, 330.0, 406.0],
         [472.0, 0.0, 406.0]],
        [[472.0, 0.0, 406.0], [472.0, 330.0, 406.0], [314.0, 330.0, 456.0],
         [314.0, 0.0, 456.0]],
        [[314.0, 0.0, 456.0], [314.0, 330.0, 456.0], [265.0, 330.0, 296.0],
         [265.0, 0.0, 296.0]],
        [[265.0, 0.0, 296.0], [265.0, 330.0, 296.0], [423.0, 330.0, 247.0],
         [423.0, 0.0, 247.0]],
    ],
    dtype=np.float64,
)  # fmt: skip

#: Named parts of :func:`cornell_box`: ``part -> slice`` of its triangle list.
CORNELL_BOX_PARTS: dict[str, slice] = {
    "floor": slice(0, 2),
    "light": slice(2, 4),
    "ceiling": slice(4, 6),
    "back_wall": slice(6, 8),
    "right_wall": slice(8, 10),
    "left_wall": slice(10, 12),
    "short_block": slice(12, 22),
    "tall_block": slice(22, 32),
}


def cornell_box() -> TriangleMesh:
    """Return the Cornell box: a closed room open at the front, two blocks, a light.

    Returns
    -------
    TriangleMesh
        32 triangles named ``"cornell-box"``: floor, ceiling, back, left and right
        walls (2 each), the ceiling light quad (2), and the short and tall blocks
        (5 quads each, no bottom). Units are millimetres as measured; Y is up; the
        room spans about ``[0, 556] x [0, 548.8] x [0, 559.2]`` and is open towards
        ``-z``, where the original camera stands at ``(278, 273, -800)``.
        :data:`CORNELL_BOX_PARTS` maps part names to triangle ranges.

    Notes
    -----
    Walls face into the room and blocks face outwards. The light is lowered by
    0.1 mm below the ceiling so no two triangles are coplanar and overlapping,
    which would make the closest hit ambiguous.

    References
    ----------
    Cornell University Program of Computer Graphics, "Cornell Box Data"
    (measurements of the physical box); Goral et al., SIGGRAPH 1984.
    """
    vertices, faces = _quads_to_triangles(_CORNELL_QUADS)
    return TriangleMesh(vertices, faces, name="cornell-box")


# ----------------------------------------------------------------- triangle soup


def triangle_soup(
    n_triangles: int = 10_000, *, seed: int = 0, size: float | None = None
) -> TriangleMesh:
    """Return ``n_triangles`` random triangles inside the unit cube.

    Parameters
    ----------
    n_triangles : int
        Number of triangles, at least 1.
    seed : int
        Seed of numpy's ``default_rng`` (PCG64); equal seeds give equal meshes.
    size : float, optional
        Edge of the cube each triangle's corners are drawn from, in ``(0, 1]``.
        Default ``n_triangles ** (-1/3)``: the cube split into ``n`` cells, so a
        ray crosses a slowly growing number (about ``n ** (1/3) / 4``) of
        triangles whatever ``n`` is.

    Returns
    -------
    TriangleMesh
        ``n_triangles`` unshared triangles (``3 n`` vertices) named ``"soup"``.
        Each triangle's three corners are uniform in a cube of edge ``size``
        whose centre is uniform in ``[size/2, 1 - size/2]^3``, so every vertex
        lies in ``[0, 1]^3``.
    """
    n = _int_in_range("n_triangles", n_triangles, 1, 2**31 // 3 - 1)
    edge = n ** (-1.0 / 3.0) if size is None else _positive_float("size", size, 1.0)
    rng = np.random.default_rng(_int_in_range("seed", seed, 0, 2**63 - 1))
    half = 0.5 * edge
    centres = rng.uniform(half, 1.0 - half, size=(n, 1, 3))
    corners = centres + rng.uniform(-half, half, size=(n, 3, 3))
    vertices = np.clip(corners, 0.0, 1.0).reshape(-1, 3)
    faces = np.arange(3 * n, dtype=np.int64).reshape(n, 3)
    label = _label("soup", n_triangles=None if n == 10_000 else n,
                   seed=None if seed == 0 else seed, size=size)  # fmt: skip
    return TriangleMesh(vertices, faces, name=label)


# ------------------------------------------------------------------- icospheres


@functools.cache
def _icosphere(subdivisions: int) -> tuple[F64Array, I64Array]:
    """Return the unit icosphere: ``20 * 4**subdivisions`` outward (counter-clockwise) triangles."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    vertices = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
         [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        dtype=np.float64,
    )  # fmt: skip
    faces = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
         [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
         [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
         [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
        dtype=np.int64,
    )  # fmt: skip
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    for _ in range(subdivisions):
        # Split every edge once (shared edges get one midpoint), then each face in four.
        n_vertices = vertices.shape[0]
        edges = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1)
        lo, hi = edges.min(axis=2), edges.max(axis=2)
        keys, inverse = np.unique(lo * n_vertices + hi, return_inverse=True)
        midpoints = vertices[keys // n_vertices] + vertices[keys % n_vertices]
        midpoints /= np.linalg.norm(midpoints, axis=1, keepdims=True)
        mid = n_vertices + inverse.reshape(-1, 3)  # midpoints of edges ab, bc, ca
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
        faces = np.stack(
            [np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
             np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)],
            axis=1,
        ).reshape(-1, 3)  # fmt: skip
        vertices = np.concatenate([vertices, midpoints])
    vertices.flags.writeable = False
    faces.flags.writeable = False
    return vertices, faces


def _instance_spheres(
    centres: F64Array, radii: F64Array, subdivisions: int
) -> tuple[F64Array, I64Array]:
    """Place one icosphere per ``(centre, radius)``; spheres stay in input order."""
    unit_vertices, unit_faces = _icosphere(subdivisions)
    vertices = centres[:, None, :] + radii[:, None, None] * unit_vertices[None]
    offsets = unit_vertices.shape[0] * np.arange(centres.shape[0], dtype=np.int64)
    faces = unit_faces[None] + offsets[:, None, None]
    return vertices.reshape(-1, 3), faces.reshape(-1, 3)


# ------------------------------------------------------------------- sphereflake


def _rotations_from_z(directions: F64Array) -> F64Array:
    """``(n, 3, 3)`` rotations taking ``+z`` to each unit direction about ``z x d``."""
    x, y, z = directions[:, 0], directions[:, 1], directions[:, 2]
    # Rodrigues with v = z x d = (-y, x, 0), c = z . d: R = I + [v]x + [v]x^2 / (1 + c).
    cross = np.zeros((directions.shape[0], 3, 3))
    cross[:, 0, 2], cross[:, 1, 2] = x, y
    cross[:, 2, 0], cross[:, 2, 1] = -x, -y
    flipped = z < -1.0 + 1e-12
    scale = np.where(flipped, 0.0, 1.0 / np.where(flipped, 1.0, 1.0 + z))
    rotations = np.eye(3) + cross + (cross @ cross) * scale[:, None, None]
    rotations[flipped] = np.diag([-1.0, 1.0, -1.0])  # half turn about Y, as SPD does
    return rotations


@functools.cache
def _spd_child_directions() -> F64Array:
    """Return the nine unit offsets of SPD ``balls.c`` for a sphere whose up axis is ``+z``.

    Six lie on the equator 60 degrees apart and three on the upper hemisphere at
    ``asin(2 / sqrt 6)`` elevation, 120 degrees apart; the lower hemisphere is
    left free because that is where the sphere rests on its parent.
    """
    s = 1.0 / math.sqrt(2.0)
    trio = np.array([[s, s, 0.0], [s, 0.0, -s], [0.0, s, -s]])
    # Tilt the trio about (1, -1, 0) so their mean points up, then copy it at 0/120/240 deg.
    axis = np.array([1.0, -1.0, 0.0]) / math.sqrt(2.0)
    angle = math.asin(2.0 / math.sqrt(6.0))
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    tilt = np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)
    trio = trio @ tilt.T
    sets = []
    for turn in range(3):
        phi = turn * 2.0 * math.pi / 3.0
        spin = np.array(
            [[math.cos(phi), -math.sin(phi), 0.0], [math.sin(phi), math.cos(phi), 0.0],
             [0.0, 0.0, 1.0]]
        )  # fmt: skip
        sets.append(trio @ spin.T)
    directions = np.concatenate(sets)
    directions.flags.writeable = False
    return directions


def sphereflake_spheres(level: int = 2) -> tuple[F64Array, F64Array]:
    """Return the centres and radii of Haines' sphereflake of SPD size ``level``.

    Parameters
    ----------
    level : int
        Recursion depth, the SPD ``size_factor``: ``(9**(level + 1) - 1) / 8``
        spheres (1, 10, 91, 820, 7381, ... for level 0, 1, 2, 3, 4).

    Returns
    -------
    centres : (n, 3) float64 ndarray
    radii : (n,) float64 ndarray
        Level by level (the root first, then its 9 children, then their 81 ...).
        The root has radius 0.5 at the origin; a child has a third of its
        parent's radius and touches it, centre at distance ``4/3 r``.
    """
    depth = _int_in_range("level", level, 0, 7)
    offsets = _spd_child_directions()
    centres = [np.zeros((1, 3))]
    radii = [np.full(1, 0.5)]
    ups = np.array([[0.0, 0.0, 1.0]])
    for _ in range(depth):
        # Spawn the nine children of every sphere of the current generation.
        turned = np.einsum("nij,kj->nki", _rotations_from_z(ups), offsets)
        parent_r = radii[-1]
        centres.append((centres[-1][:, None, :] + (parent_r * 4.0 / 3.0)[:, None, None]
                        * turned).reshape(-1, 3))  # fmt: skip
        radii.append(np.repeat(parent_r / 3.0, 9))
        ups = turned.reshape(-1, 3)
    return np.concatenate(centres), np.concatenate(radii)


def sphereflake(
    level: int = 2, *, sphere_subdivisions: int = 2, ground: bool = True
) -> TriangleMesh:
    """Return Haines' sphereflake ("balls") tessellated into triangles.

    Parameters
    ----------
    level : int
        SPD size factor, 0 to 7: ``(9**(level + 1) - 1) / 8`` spheres.
    sphere_subdivisions : int
        Icosphere refinement of every sphere, 0 to 6: ``20 * 4**k`` triangles
        per sphere (default 2: 320, visibly round).
    ground : bool
        Add SPD's square floor, ``[-12, 12]^2`` at ``z = -0.5`` (2 triangles),
        on which the root sphere rests.

    Returns
    -------
    TriangleMesh
        ``spheres * 20 * 4**k (+ 2)`` triangles: 29,122 with the defaults,
        262,402 at level 3. Z is up; the flake fits in a unit-radius sphere
        about the origin. SPD's view is ``eye (2.1, 1.3, 1.7)``, target the
        origin, 45 degree field of view.

    References
    ----------
    E. Haines, "A Proposal for Standard Graphics Environments", IEEE CG&A 7(11),
    1987; SPD ``balls.c``.
    """
    subdivisions = _int_in_range("sphere_subdivisions", sphere_subdivisions, 0, 6)
    centres, radii = sphereflake_spheres(level)
    vertices, faces = _instance_spheres(centres, radii, subdivisions)
    if ground:
        floor = np.array([[[12.0, 12.0, -0.5], [-12.0, 12.0, -0.5], [-12.0, -12.0, -0.5],
                           [12.0, -12.0, -0.5]]])  # fmt: skip
        floor_vertices, floor_faces = _quads_to_triangles(floor)
        faces = np.concatenate([faces, floor_faces + vertices.shape[0]])
        vertices = np.concatenate([vertices, floor_vertices])
    label = _label("sphereflake", level=None if level == 2 else level,
                   sphere_subdivisions=None if subdivisions == 2 else subdivisions,
                   ground=None if ground else False)  # fmt: skip
    return TriangleMesh(vertices, faces, name=label)


# ------------------------------------------------------------------------ teapot


def _bernstein(t: F64Array) -> F64Array:
    """``(n, 4)`` cubic Bernstein basis values at parameters ``t``."""
    s = 1.0 - t
    return np.stack([s**3, 3.0 * t * s**2, 3.0 * t**2 * s, t**3], axis=1)


def _teapot_arrays(subdivisions: int) -> tuple[F64Array, I64Array]:
    """Evaluate, triangulate and weld the 32 patches on ``(s + 1)^2`` grids."""
    s = subdivisions
    control = np.asarray(NEWELL_VERTICES, dtype=np.float64)
    patches = np.asarray(NEWELL_PATCHES, dtype=np.int64) - 1  # published 1-based
    grid = control[patches].reshape(-1, 4, 4, 3)
    basis = _bernstein(np.linspace(0.0, 1.0, s + 1))
    # Tensor-product evaluation: P(u, v) = sum_ij B_i(u) B_j(v) G_ij.
    points = np.einsum("ui,pijc,vj->puvc", basis, grid, basis).reshape(-1, 3)
    row = s + 1
    u, v = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    corner = (u * row + v).reshape(-1)
    # Corners counter-clockwise seen from outside (the published patches face outwards).
    quads = np.stack([corner, corner + 1, corner + row + 1, corner + row], axis=1)
    cells = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], axis=1).reshape(-1, 3)
    offsets = row * row * np.arange(patches.shape[0], dtype=np.int64)
    faces = (cells[None] + offsets[:, None, None]).reshape(-1, 3)
    # Weld: patch seams share control points, so equal float32 positions are one vertex.
    rounded = points.astype(np.float32)
    _, first, inverse = np.unique(rounded, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    welded = points[first[order]]
    return welded, rank[inverse.reshape(-1)][faces]


def teapot(subdivisions: int = 8) -> TriangleMesh:
    """Return the Utah teapot tessellated from Newell's 32 bicubic Bézier patches.

    Parameters
    ----------
    subdivisions : int
        Segments per patch edge, 1 to 64: each patch is evaluated on an
        ``(s + 1) x (s + 1)`` grid and split into ``2 s^2`` triangles.

    Returns
    -------
    TriangleMesh
        ``64 s^2`` triangles (4,096 by default), named ``"teapot"``, with the
        published coordinates: Z up, standing on ``z = 0``, spout towards
        ``+x``; bounds about ``[-3, -2, 0] .. [3.434, 2, 3.15]``. Vertices at
        equal float32 positions are welded, so patch seams are shared edges.

    Notes
    -----
    The lid's and bottom's patches collapse a whole edge into their centre
    point, so each gives ``s`` zero-area triangles; they are kept (like the
    shared scenes' zero-area triangles), so the count stays ``64 s^2``.
    The teapot is not closed: the body is open under the lid and the spout
    and handle pierce the body without being trimmed.

    References
    ----------
    M. E. Newell, PhD thesis, University of Utah, 1975; F. C. Crow, "The Origins
    of the Teapot", IEEE CG&A 7(1), 1987.
    """
    s = _int_in_range("subdivisions", subdivisions, 1, 64)
    vertices, faces = _teapot_arrays(s)
    return TriangleMesh(vertices, faces, name=_label("teapot", subdivisions=None if s == 8 else s))


def _box_inward(lo: F64Array, hi: F64Array) -> tuple[F64Array, I64Array]:
    """Return the six faces of an axis-aligned box as 12 triangles facing inwards."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    quads = np.array(
        [
            [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]],  # floor (z0)
            [[x0, y0, z1], [x0, y1, z1], [x1, y1, z1], [x1, y0, z1]],  # ceiling (z1)
            [[x0, y0, z0], [x0, y1, z0], [x0, y1, z1], [x0, y0, z1]],  # x0 wall
            [[x1, y0, z0], [x1, y0, z1], [x1, y1, z1], [x1, y1, z0]],  # x1 wall
            [[x0, y0, z0], [x0, y0, z1], [x1, y0, z1], [x1, y0, z0]],  # y0 wall
            [[x0, y1, z0], [x1, y1, z0], [x1, y1, z1], [x0, y1, z1]],  # y1 wall
        ],
        dtype=np.float64,
    )
    return _quads_to_triangles(quads)


def teapot_in_stadium(subdivisions: int = 8, *, stadium_scale: float = 1000.0) -> TriangleMesh:
    """Return a small teapot on the floor of a huge closed room.

    Parameters
    ----------
    subdivisions : int
        Teapot tessellation, as for :func:`teapot`.
    stadium_scale : float
        Width of the room over the teapot's width (default 1000). The room's
        height is half its width.

    Returns
    -------
    TriangleMesh
        The teapot's ``64 s^2`` triangles (first, same vertices as
        :func:`teapot`) followed by the room's 12, facing inwards. The room is
        centred on the teapot in x and y; its floor lies 0.01 below the
        teapot's base so no triangle is coplanar with it. Z is up.

    Notes
    -----
    A uniform grid sized from the triangle count spreads its cells over the
    whole room and puts the teapot into one or two cells; an adaptive structure
    (BVH, kd-tree, hierarchical grid) does not care. This is Haines' "teapot in
    a stadium" (Ray Tracing News, 1988).
    """
    s = _int_in_range("subdivisions", subdivisions, 1, 64)
    scale = _positive_float("stadium_scale", stadium_scale)
    vertices, faces = _teapot_arrays(s)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    half_width = 0.5 * scale * float(np.max(hi[:2] - lo[:2]))
    centre = 0.5 * (lo + hi)
    room_lo = np.array([centre[0] - half_width, centre[1] - half_width, lo[2] - 0.01])
    room_hi = np.array([centre[0] + half_width, centre[1] + half_width, lo[2] + half_width])
    room_vertices, room_faces = _box_inward(room_lo, room_hi)
    label = _label("teapot-in-stadium", subdivisions=None if s == 8 else s,
                   stadium_scale=None if scale == 1000.0 else scale)  # fmt: skip
    return TriangleMesh(
        np.concatenate([vertices, room_vertices]),
        np.concatenate([faces, room_faces + vertices.shape[0]]),
        name=label,
    )


__all__ = [
    "CORNELL_BOX_PARTS",
    "cornell_box",
    "sphereflake",
    "sphereflake_spheres",
    "teapot",
    "teapot_in_stadium",
    "triangle_soup",
]
