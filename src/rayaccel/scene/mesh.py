"""Triangle meshes: the one geometry type every structure is built over.

A :class:`TriangleMesh` holds a float32 ``(V, 3)`` vertex array and an int32
``(F, 3)`` face array, both C-contiguous, validated once at construction:
non-finite vertices are rejected with the offending index, and so are coordinates
beyond the range the precision traces (``|x| <= 2^30`` in float32, ``2^62`` in
float64: :mod:`rayaccel.validation`, docs/reliability.md "Numbers"); face indices must lie
in ``[0, V)``, and a mesh must have at least one triangle. Zero-area triangles
are kept (a correct ray/triangle test never reports a hit on them).

Precision. ``precision="float64"`` (for scenes with huge coordinates: geospatial, CAD)
keeps the float64 positions in :attr:`TriangleMesh.vertices64`; :meth:`hit_rows`, which
the intersection kernels test, are then float64 and traversals compile float64
specialisations (rays and hits in float64 too). Builders still build over the float32
rounding in :attr:`TriangleMesh.vertices`, and the BVH's boxes are then widened to
contain the float64 triangles (:mod:`rayaccel.bvh.precision`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from rayaccel.config import parallel_section
from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray, RealArray, check_precision
from rayaccel.errors import InvalidInputError
from rayaccel.kernels import triangle_rows
from rayaccel.validation import (
    NORMAL_FLOOR,
    check_coordinates,
    check_finite_rows,
    check_real,
    rows_of_three,
)


def _coerce_vertices(
    vertices: object, precision: str
) -> tuple[FloatArray, npt.NDArray[np.float64] | None]:
    """Return the float32 vertices and, for a float64 mesh, the float64 ones.

    Both are checked against the numeric range of ``precision``
    (:data:`rayaccel.validation.COORDINATE_LIMIT`); a float64 mesh's range lies within
    float32's, so its float32 rounding (what builders bound) is finite too.
    """
    array = rows_of_three("vertices", vertices, "V", "float")
    check_real("vertices", array)
    check_finite_rows("vertices", array, "vertex", "vertices")
    with np.errstate(over="ignore"):  # beyond float32's range: refused below
        coerced = np.ascontiguousarray(array, dtype=REAL)
    exact = None
    if precision == "float64":
        exact = np.ascontiguousarray(array, dtype=np.float64)
        check_coordinates("vertices", array, exact, precision, "vertex")
    else:
        check_coordinates("vertices", array, coerced, precision, "vertex")
    return coerced, exact


def _coerce_faces(faces: object, n_vertices: int) -> IntArray:
    array = rows_of_three("faces", faces, "F", "int")
    if array.shape[0] == 0:
        raise InvalidInputError("faces: the mesh is empty (0 triangles)")
    if np.issubdtype(array.dtype, np.floating):
        if not np.all(np.isfinite(array)) or not np.all(array == np.round(array)):
            raise InvalidInputError("faces: expected integer vertex indices, got non-integers")
    elif not np.issubdtype(array.dtype, np.integer):
        raise InvalidInputError(f"faces: expected an int array, got dtype {array.dtype}")
    low, high = array.min(), array.max()
    if low < 0 or high >= n_vertices:
        bad_mask = (array < 0) | (array >= n_vertices)
        face = int(np.argwhere(bad_mask.any(axis=1))[0, 0])
        raise InvalidInputError(
            f"faces: face {face} has vertex index out of range [0, {n_vertices}): "
            f"{array[face].tolist()}"
        )
    return np.ascontiguousarray(array, dtype=INDEX)


@dataclass(frozen=True, slots=True, eq=False, init=False)
class TriangleMesh:
    """An indexed triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) array_like of float
        Vertex positions; coerced once to C-contiguous float32. Every vertex must be finite.
    faces : (F, 3) array_like of int
        Vertex indices of each triangle; coerced to int32, each in ``[0, V)``; ``F >= 1``.
    name : str, optional
        A label used in reports.
    precision : {"float32", "float64"}
        ``"float64"`` also keeps the vertices in float64 (:attr:`vertices64`): the
        triangles are then intersected in float64 and the accel traces float64 rays
        (BVH builders only; see the module docstring).

    Attributes
    ----------
    vertices : (V, 3) float32
        The positions builders bound: the float32 rounding of :attr:`vertices64` for a
        float64 mesh.
    vertices64 : (V, 3) float64 or None
        The exact positions of a float64 mesh; None for a float32 mesh.

    Raises
    ------
    InvalidInputError
        Wrong shapes, non-finite vertices (the index is named), coordinates beyond
        ``2^30`` (``2^62`` for a float64 mesh; the vertex and the range are named),
        out-of-range indices (the face is named), an empty face list or an unknown
        precision.
    """

    vertices: FloatArray
    faces: IntArray
    name: str
    precision: str
    vertices64: npt.NDArray[np.float64] | None
    #: :meth:`digest`, once computed (the arrays are read-only, so it never changes).
    _digest: str | None = field(default=None, repr=False)

    def __init__(
        self,
        vertices: npt.ArrayLike,
        faces: npt.ArrayLike,
        name: str = "mesh",
        *,
        precision: str = "float32",
    ) -> None:
        check_precision(precision)
        coerced, exact = _coerce_vertices(vertices, precision)
        self._set(coerced, exact, _coerce_faces(faces, coerced.shape[0]), name, precision)

    def _set(
        self,
        vertices: FloatArray,
        exact: npt.NDArray[np.float64] | None,
        faces: IntArray,
        name: str,
        precision: str,
    ) -> None:
        """Set every field once (the dataclass is frozen) and make the arrays read-only."""
        for array in (vertices, exact, faces):
            if array is not None:
                array.flags.writeable = False
        object.__setattr__(self, "precision", precision)
        object.__setattr__(self, "vertices64", exact)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "_digest", None)

    def with_vertices(self, vertices: npt.ArrayLike) -> TriangleMesh:
        """Return this mesh with new vertex positions: same faces, name and precision.

        The positions are checked as the constructor checks them; the faces were checked
        when this mesh was made and are shared, not checked again (a refit's frame of an
        animation).

        Raises
        ------
        InvalidInputError
            Wrong shape, another vertex count, or a vertex the constructor refuses.
        """
        coerced, exact = _coerce_vertices(vertices, self.precision)
        if coerced.shape[0] != self.n_vertices:
            raise InvalidInputError(
                f"vertices: expected {self.n_vertices} vertices (the mesh's count), "
                f"got {coerced.shape[0]}"
            )
        mesh = object.__new__(TriangleMesh)
        mesh._set(coerced, exact, self.faces, self.name, self.precision)
        return mesh

    @property
    def n_triangles(self) -> int:
        """Number of triangles ``F``."""
        return int(self.faces.shape[0])

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``V``."""
        return int(self.vertices.shape[0])

    def triangles(self) -> FloatArray:
        """Return the ``(F, 3, 3)`` float32 corner positions of every triangle."""
        with parallel_section():
            corners: FloatArray = triangle_rows.triangle_corners(self.vertices, self.faces)
        return corners

    def triangles64(self) -> npt.NDArray[np.float64]:
        """Return the ``(F, 3, 3)`` float64 corners of a float64 mesh's triangles.

        Raises
        ------
        InvalidInputError
            The mesh is float32 (it keeps no float64 positions).
        """
        if self.vertices64 is None:
            raise InvalidInputError(f"{self.name}: not a float64 mesh")
        with parallel_section():
            corners: npt.NDArray[np.float64] = triangle_rows.triangle_corners(
                self.vertices64, self.faces
            )
        return corners

    def hit_rows(self) -> RealArray:
        """Return the ``(F, 9)`` corner rows the intersection kernels test.

        float32, or float64 (from :attr:`vertices64`) for a float64 mesh.

        A triangle whose area is exactly zero in float64 (repeated corners, collinear
        corners) is collapsed to its first corner. The watertight test then computes
        three edge functions that are exactly zero and rejects it, whereas the sheared
        corners of a collinear triangle can round off their line and give a bogus hit.
        Bounding boxes are built from :meth:`triangles`, so they still enclose the
        original corners.

        So is a triangle too small for the rows' precision: one whose doubled area (the
        sum of the cross product's magnitudes, in float64) is below the smallest normal
        number (``2^-126`` for float32 rows, edges under about ``1e-19``). The test's
        determinant is at most that sum, so its reciprocal would overflow: the test
        would miss it, or report ``t = -inf`` when ``tmin = -inf``. It is zero-area by
        definition instead (docs/reliability.md, "Numbers"); a float64 mesh hits it.
        """
        positions = self.vertices if self.vertices64 is None else self.vertices64
        with parallel_section():
            rows: RealArray = triangle_rows.hit_rows(
                positions, self.faces, float(NORMAL_FLOOR[self.precision])
            )
        return rows

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        """Return ``(lo, hi)``, the float32 bounding box of the referenced vertices."""
        lo: FloatArray
        hi: FloatArray
        with parallel_section():
            lo, hi = triangle_rows.corner_bounds(self.vertices, self.faces)
        return lo, hi

    def areas(self) -> FloatArray:
        """Return the ``(F,)`` float32 triangle areas (computed in float64)."""
        tri = self.triangles().astype(np.float64)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        areas: FloatArray = (0.5 * np.linalg.norm(cross, axis=1)).astype(REAL)
        return areas

    def normals(self) -> FloatArray:
        """Return ``(F, 3)`` float32 unit geometric normals (zero for zero-area triangles)."""
        tri = self.triangles().astype(np.float64)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(cross, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = np.where(length > 0, cross / np.where(length > 0, length, 1.0), 0.0)
        return unit.astype(REAL)

    def digest(self) -> str:
        """Return the SHA-256 (hex) of the vertex and face arrays: the scene's identity.

        Recorded ray sets carry it, so a study refuses rays recorded on another scene.
        The name is not part of it. Computed once per mesh (27 ms for the kitchen's
        1.44 M triangles), since a study asks for it in every cell.
        """
        if self._digest is None:
            h = hashlib.sha256()
            arrays: list[np.ndarray] = [self.vertices, self.faces]
            if self.vertices64 is not None:
                arrays.append(self.vertices64)
            for array in arrays:
                h.update(f"{array.dtype.str}{array.shape}".encode())
                h.update(np.ascontiguousarray(array).tobytes())
            object.__setattr__(self, "_digest", h.hexdigest())
        assert self._digest is not None
        return self._digest

    def __repr__(self) -> str:
        extra = "" if self.precision == "float32" else f", precision={self.precision!r}"
        return (
            f"TriangleMesh(name={self.name!r}, n_triangles={self.n_triangles}, "
            f"n_vertices={self.n_vertices}{extra})"
        )
