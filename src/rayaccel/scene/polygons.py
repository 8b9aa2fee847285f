"""What every scene-file reader checks before it hands geometry to :class:`TriangleMesh`.

The readers (:mod:`~rayaccel.scene.io` for OBJ, glTF and GLB,
:mod:`~rayaccel.scene.ply`, :mod:`~rayaccel.scene.stl`) each produce vertices,
polygon sizes and flat corner indices. The checks here run on that output, so a
bad value is reported the same way whatever the format, with the file and, where
the reader knows it, the line or byte where the value sits:

* a vertex that is NaN, infinite or beyond float32's range is refused with the
  wording :class:`~rayaccel.scene.mesh.TriangleMesh` uses (``vertices: vertex 7
  is not finite``), plus its location;
* a polygon with fewer than 3 corners, or a corner index outside ``[0, V)``, is
  refused with the polygon's number in the file (not the number of a triangle
  after triangulation) and its location;
* polygons are then fan-triangulated as ``(0, k, k + 1)``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from rayaccel.errors import SceneFileError

F64Array = npt.NDArray[np.float64]
I64Array = npt.NDArray[np.int64]
#: The parameters of the binary-capable readers (PLY, STL).
READER_PARAMETERS = """\
Parameters
----------
data : bytes
    The whole file.
source : str
    Name used in error messages, normally the path.
"""
#: ``where(row)`` names the location of row ``row`` in the file, e.g. ``"line 12"``.
Locator = Callable[[int], str]

_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _at(where: Locator | None, row: int) -> str:
    return f" at {where(row)}" if where is not None else ""


def check_vertices(xyz: F64Array, source: str, where: Locator | None = None) -> F64Array:
    """Refuse non-finite vertices and vertices beyond float32's range.

    Parameters
    ----------
    xyz : (V, 3) float64 ndarray
        Vertex positions as read.
    source : str
        The file, named in the error.
    where : callable, optional
        Maps a vertex number to its location in the file.

    Returns
    -------
    (V, 3) float64 ndarray
        ``xyz`` itself.

    Raises
    ------
    SceneFileError
        ``source: vertices: vertex k is not finite ([...]) at line n`` for the first
        bad vertex (``overflows float32`` for finite values beyond its range).
    """
    inside = (np.abs(xyz) <= _FLOAT32_MAX).all(axis=1)  # False for NaN too
    if not inside.all():
        row = int(np.flatnonzero(~inside)[0])
        what = "is not finite" if not np.isfinite(xyz[row]).all() else "overflows float32"
        raise SceneFileError(
            f"{source}: vertices: vertex {row} {what} ({xyz[row].tolist()}){_at(where, row)}"
        )
    return xyz


def check_polygons(
    counts: I64Array,
    index: I64Array,
    n_vertices: int,
    source: str,
    where: Locator | None = None,
) -> None:
    """Refuse polygons with fewer than 3 corners and corner indices outside ``[0, V)``.

    Parameters
    ----------
    counts : (P,) int64 ndarray
        Corners of each polygon.
    index : (sum(counts),) int64 ndarray
        Zero-based vertex index of every corner, polygon after polygon.
    n_vertices : int
        ``V``.
    source : str
        The file, named in the error.
    where : callable, optional
        Maps a polygon number to its location in the file.

    Raises
    ------
    SceneFileError
        ``source: face p has 2 vertices; a face needs at least 3 (at byte n)`` or
        ``source: face p has vertex index 9 out of range [0, 5) (at line n)``.
    """
    short = counts < 3
    if short.any():
        row = int(np.flatnonzero(short)[0])
        raise SceneFileError(
            f"{source}: face {row} has {int(counts[row])} vertices; a face needs at least 3"
            f"{_at(where, row)}"
        )
    bad = (index < 0) | (index >= n_vertices)
    if bad.any():
        corner, row = first_corner(bad, counts)
        raise SceneFileError(
            f"{source}: face {row} has vertex index {int(index[corner])} out of range "
            f"[0, {n_vertices}) ({n_vertices} vertices){_at(where, row)}"
        )


def first_corner(bad: npt.NDArray[np.bool_], counts: I64Array) -> tuple[int, int]:
    """Return ``(corner, polygon)``: the first corner where ``bad`` holds, and its polygon.

    ``bad`` has one entry per corner, polygon after polygon; ``counts`` gives each
    polygon's corners. At least one corner must be bad.
    """
    corner = int(np.flatnonzero(bad)[0])
    return corner, int(np.searchsorted(np.cumsum(counts), corner, side="right"))


def fan_triangulate(counts: I64Array, index: I64Array) -> I64Array:
    """Triangulate polygons given as flat corner indices: ``(0, k, k + 1)`` fans.

    Parameters
    ----------
    counts : (P,) int64 ndarray
        Corners of each polygon, each at least 3.
    index : (sum(counts),) int64 ndarray
        Vertex index of every corner, polygon after polygon.

    Returns
    -------
    (sum(counts - 2), 3) int64 ndarray
        The triangles, in polygon order.
    """
    if (counts == 3).all():
        return index.reshape(-1, 3)
    n_tris = counts - 2
    first = np.cumsum(counts) - counts
    owner = np.repeat(np.arange(counts.shape[0]), n_tris)
    k = np.arange(int(n_tris.sum())) - np.repeat(np.cumsum(n_tris) - n_tris, n_tris)
    base = first[owner]
    return np.stack([index[base], index[base + k + 1], index[base + k + 2]], axis=1)


__all__ = ["check_polygons", "check_vertices", "fan_triangulate", "first_corner"]
