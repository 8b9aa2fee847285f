"""A strict reader for STL files, binary and ASCII.

Binary STL is an 80-byte header, a little-endian ``uint32`` triangle count and
50 bytes per triangle (normal, three corners, a 16-bit attribute), so its size is
exactly ``84 + 50 * count``. ASCII STL is ``solid [name]``, then per triangle
``facet normal nx ny nz``, ``outer loop``, three ``vertex x y z`` lines,
``endloop``, ``endfacet``, and finally ``endsolid [name]``; several solids may
follow one another.

Many exporters write ``solid`` at the start of a *binary* header, so the size
decides: a file whose size matches its binary count is binary; otherwise a file
of ASCII text that starts with ``solid`` is ASCII; anything else is refused with
the count, the size it implies and the file's real size. (trimesh 5.2 instead
falls back to other readers and fails on a missing optional module.)

Every corner becomes its own vertex (no merging), as trimesh does with
``process=False``: triangle ``t`` is vertices ``3t, 3t + 1, 3t + 2``.
"""

from __future__ import annotations

import re

import numpy as np

from rayaccel._docstrings import with_sections
from rayaccel.errors import SceneFileError
from rayaccel.scene.polygons import (
    READER_PARAMETERS,
    F64Array,
    I64Array,
    Locator,
    check_vertices,
)

_HEADER = 84
_RECORD = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
# One triangle of ASCII STL, for the fast path over rigidly formatted files.
_FACET = re.compile(
    r"facet\s+normal(?:\s+\S+){3}\s+outer\s+loop"
    r"\s+vertex\s+(\S+)\s+(\S+)\s+(\S+)"
    r"\s+vertex\s+(\S+)\s+(\S+)\s+(\S+)"
    r"\s+vertex\s+(\S+)\s+(\S+)\s+(\S+)"
    r"\s+endloop\s+endfacet\s+"
)
_FACETS = re.compile(f"(?:{_FACET.pattern})*")
_FLOAT32_MAX = float(np.finfo(np.float32).max)


@with_sections(READER_PARAMETERS)
def parse_stl(data: bytes, *, source: str = "<stl>") -> tuple[F64Array, I64Array]:
    """Parse a binary or ASCII STL file into vertex and triangle arrays.

    Returns
    -------
    vertices : (3F, 3) float64 ndarray
        The corners of every triangle, in file order.
    faces : (F, 3) int64 ndarray
        ``[[0, 1, 2], [3, 4, 5], ...]``.

    Raises
    ------
    SceneFileError
        A binary count that disagrees with the file's size, a malformed ASCII
        line (its number is named), a corner that is not a finite float32, or no
        triangles at all.
    """
    if len(data) >= _HEADER:
        count = int.from_bytes(data[80:84], "little")
        if len(data) == _HEADER + 50 * count:
            return _binary(data, count, source)
    if data.lstrip()[:5].lower() == b"solid" and data.isascii():
        return _ascii(data.decode("ascii"), source)
    if len(data) < _HEADER:
        raise SceneFileError(
            f"{source}: not an STL file: {len(data)} bytes is shorter than a binary STL "
            f"header ({_HEADER} bytes) and the file is not ASCII STL (text starting with "
            "'solid')"
        )
    raise SceneFileError(
        f"{source}: binary STL header declares {count} triangles, which take "
        f"{_HEADER + 50 * count} bytes, but the file has {len(data)} bytes (and it is not "
        "ASCII STL: text starting with 'solid')"
    )


def _binary(data: bytes, count: int, source: str) -> tuple[F64Array, I64Array]:
    if count == 0:
        raise SceneFileError(f"{source}: the file holds no triangles (binary STL, count 0)")
    records = np.frombuffer(data, dtype=_RECORD, count=count, offset=_HEADER)
    vertices = records["corners"].reshape(-1, 3).astype(np.float64)
    check_vertices(vertices, source, lambda v: f"byte {_HEADER + 50 * (v // 3) + 12 * (1 + v % 3)}")
    return vertices, np.arange(3 * count, dtype=np.int64).reshape(-1, 3)


def _ascii(text: str, source: str) -> tuple[F64Array, I64Array]:
    vertices = _ascii_fast(text)
    where: Locator | None = None
    if vertices is None or not (np.abs(vertices) <= _FLOAT32_MAX).all():
        # The line-by-line reader finds the first error's line (and each corner's line).
        vertices, where = _ascii_lines(text, source)
    if vertices.shape[0] == 0:
        raise SceneFileError(f"{source}: the file holds no triangles (no 'facet' in ASCII STL)")
    check_vertices(vertices, source, where)
    return vertices, np.arange(vertices.shape[0], dtype=np.int64).reshape(-1, 3)


def _ascii_fast(text: str) -> F64Array | None:
    """Return the corners of one solid whose facets all match the rigid pattern, or ``None``."""
    stripped = text.lstrip()
    head = text.find("\n", len(text) - len(stripped))  # end of the 'solid' line
    tail = text.rfind("endsolid")
    if head < 0 or tail <= head or "\n" in text[tail:].rstrip():
        return None
    body = text[head + 1 : tail].lstrip()
    if _FACETS.fullmatch(body) is None:
        return None
    try:
        return np.asarray(_FACET.findall(body), dtype=np.float64).reshape(-1, 3)
    except ValueError:
        return None


def _ascii_lines(text: str, source: str) -> tuple[F64Array, Locator]:
    """Line-by-line state machine: slower, but names the line of the first error."""
    expected = "solid"
    corners: list[list[float]] = []
    corner_lines: list[int] = []
    in_loop = 0
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    number = 0
    for number, raw in enumerate(lines, start=1):
        fields = raw.split()
        if not fields:
            continue
        keyword = fields[0].lower()
        where = f"{source}: line {number}"
        if keyword == "vertex" and expected == "vertex":
            if len(fields) != 4:
                raise SceneFileError(
                    f"{where}: 'vertex' needs 3 coordinates, got {len(fields) - 1}"
                )
            try:
                corners.append([float(v) for v in fields[1:]])
            except ValueError:
                raise SceneFileError(
                    f"{where}: cannot parse a coordinate of {raw.strip()[:80]!r}"
                ) from None
            corner_lines.append(number)
            in_loop += 1
            expected = "vertex" if in_loop < 3 else "endloop"
            continue
        if expected == "solid":
            if keyword != "solid":
                raise SceneFileError(f"{where}: expected 'solid', got {fields[0][:40]!r}")
            expected = "facet|endsolid"
        elif expected == "facet|endsolid":
            if keyword == "endsolid":
                expected = "solid"
            elif keyword == "facet" and len(fields) == 5 and fields[1].lower() == "normal":
                expected = "outer"
            else:
                raise SceneFileError(f"{where}: expected 'facet normal nx ny nz' or 'endsolid'")
        elif expected == "outer":
            if [f.lower() for f in fields] != ["outer", "loop"]:
                raise SceneFileError(f"{where}: expected 'outer loop'")
            expected, in_loop = "vertex", 0
        elif expected == "vertex":
            raise SceneFileError(
                f"{where}: expected 'vertex x y z' ({in_loop} of 3 corners read), got "
                f"{fields[0][:40]!r}"
            )
        elif expected == "endloop":
            if keyword != "endloop":
                raise SceneFileError(f"{where}: expected 'endloop' after 3 vertices")
            expected = "endfacet"
        elif expected == "endfacet":
            if keyword != "endfacet":
                raise SceneFileError(f"{where}: expected 'endfacet'")
            expected = "facet|endsolid"
    if expected != "solid":
        raise SceneFileError(
            f"{source}: the file ends at line {number} inside a solid (expected "
            f"{expected.replace('|', ' or ')!r})"
        )
    vertices = np.asarray(corners, dtype=np.float64).reshape(-1, 3)
    line_of = np.asarray(corner_lines, dtype=np.int64)
    return vertices, lambda v: f"line {int(line_of[v])}"


__all__ = ["parse_stl"]
