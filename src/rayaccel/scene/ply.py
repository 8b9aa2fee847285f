"""A strict reader for PLY files (ASCII and binary, either byte order).

PLY (Greg Turk, *The PLY Polygon File Format*, 1994) is a header listing
elements (``element vertex 8``) and their properties (``property float x``,
``property list uchar int vertex_indices``), then the elements' rows in header
order. rayaccel reads it itself instead of through trimesh because trimesh 5.2
trusts the header's counts: a binary file whose faces mix triangles, quads and
pentagons is refused as "unexpected length", and an ASCII file whose counts
disagree with its rows loads as a different mesh.

Here the header's counts are checked against the data before anything of the
declared size is allocated (every row takes at least a known number of bytes or
a line, so a header declaring two billion rows over a few bytes fails at once),
every row is checked to hold exactly its properties, and nothing may follow the
last element. Errors name the file and the line (ASCII) or byte offset
(binary) of the fault.

Mesh content: the ``vertex`` element's ``x``, ``y``, ``z`` and the ``face``
element's ``vertex_indices`` (or ``vertex_index``) list, polygons fan-triangulated;
other elements and properties are read for validation and dropped.

Cost: binary files whose face rows all have one size, and ASCII files whose rows
of each element have one length, are read with numpy in a few vectorised steps
(the 1.44 M-triangle kitchen in a fraction of a second); mixed polygon sizes in
binary files are walked row by row in Python (2 to 3 seconds per million faces).
"""

from __future__ import annotations

import io
import re
import warnings
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from rayaccel._docstrings import with_sections
from rayaccel.errors import SceneFileError
from rayaccel.scene.polygons import (
    READER_PARAMETERS,
    F64Array,
    I64Array,
    Locator,
    check_polygons,
    check_vertices,
    fan_triangulate,
    first_corner,
)

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_INDEX_NAMES = ("vertex_indices", "vertex_index")
_COUNT = re.compile(r"[+]?[0-9]+")


@dataclass(frozen=True)
class _Property:
    name: str
    dtype: np.dtype  # value type (list items for a list), native byte order
    count_dtype: np.dtype | None  # list length type; None for a scalar property

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


@dataclass
class _Element:
    name: str
    count: int
    line: int  # header line declaring it
    properties: list[_Property]


@dataclass
class _Rows:
    """Where each property of each row of an element sits in the data.

    ``where[name]`` is, per row, the byte offset (binary) or the index into the flat
    value array (ASCII) of a scalar's value or of a list's length; ``length[name]``
    is a list's length per row. Binary rows that all share one layout are described
    instead by ``stride`` (bytes per row), ``first`` (the offset of each property in
    row 0) and ``uniform_length`` (each list's length), without per-row arrays.
    """

    element: str
    n: int
    where: dict[str, I64Array] = field(default_factory=dict)
    length: dict[str, I64Array] = field(default_factory=dict)
    stride: int = 0
    first: dict[str, int] = field(default_factory=dict)
    uniform_length: dict[str, int] = field(default_factory=dict)


@with_sections(READER_PARAMETERS)
def parse_ply(data: bytes, *, source: str = "<ply>") -> tuple[F64Array, I64Array]:
    """Parse a PLY file into vertex and triangle arrays.

    Returns
    -------
    vertices : (V, 3) float64 ndarray
        The ``vertex`` element's ``x y z``, in file order.
    faces : (F, 3) int64 ndarray
        The ``face`` element's polygons, fan-triangulated ``(0, k, k + 1)``.

    Raises
    ------
    SceneFileError
        A malformed header (the line is named), counts that disagree with the
        data, a truncated or over-long body, a malformed row (its line or byte
        offset is named), a vertex that is not a finite float32, a face with
        fewer than 3 vertices or an index out of range, or no faces at all.
    """
    elements, byte_order, body_start, header_lines = _parse_header(data, source)
    vertex = next((e for e in elements if e.name == "vertex"), None)
    face = next((e for e in elements if e.name == "face"), None)
    if face is None or face.count == 0:
        raise SceneFileError(f"{source}: the file holds no triangles (no 'face' rows)")
    if vertex is None:
        raise SceneFileError(f"{source}: the header declares faces but no 'vertex' element")
    missing = [axis for axis in "xyz" if axis not in {p.name for p in vertex.properties}]
    if missing:
        raise SceneFileError(
            f"{source}: header line {vertex.line}: element 'vertex' has no property "
            f"{', '.join(missing)}"
        )
    for prop in vertex.properties:
        if prop.name in "xyz" and prop.is_list:
            raise SceneFileError(
                f"{source}: header line {vertex.line}: vertex property {prop.name!r} is a list"
            )
    index_prop = next((p for p in face.properties if p.name in _INDEX_NAMES), None)
    if index_prop is None or not index_prop.is_list:
        raise SceneFileError(
            f"{source}: header line {face.line}: element 'face' has no list property "
            "'vertex_indices' (or 'vertex_index')"
        )
    if index_prop.dtype.kind not in "iu":
        raise SceneFileError(
            f"{source}: header line {face.line}: face property {index_prop.name!r} holds "
            f"{index_prop.dtype.name} values; vertex indices must be integers"
        )
    reader: _AsciiBody | _BinaryBody
    if byte_order is None:
        reader = _AsciiBody(data, body_start, header_lines, source)
    else:
        reader = _BinaryBody(data, body_start, byte_order, source)
    rows = {e.name: reader.element(e, keep=e.name in ("vertex", "face")) for e in elements}
    reader.finish(elements)

    vertex_rows = rows["vertex"]
    by_name = {p.name: p for p in vertex.properties}
    xyz = np.stack([reader.scalar(vertex_rows, by_name[axis]) for axis in "xyz"], axis=1)
    check_vertices(xyz, source, reader.locator(vertex_rows, "x"))
    face_rows = rows["face"]
    counts = reader.counts(face_rows, index_prop)
    index = reader.list_values(face_rows, index_prop)
    check_polygons(counts, index, xyz.shape[0], source, reader.locator(face_rows, index_prop.name))
    return xyz, fan_triangulate(counts, index)


# ------------------------------------------------------------------------------ header


def _parse_header(data: bytes, source: str) -> tuple[list[_Element], str | None, int, int]:
    """Return the elements, the byte order (``None`` for ASCII), body offset and header lines."""
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise SceneFileError(f"{source}: not a PLY file (it does not start with a 'ply' line)")
    elements: list[_Element] = []
    byte_order: str | None = None
    seen_format = False
    pos = 0
    line_no = 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            if data[pos:].strip() != b"end_header":
                raise SceneFileError(
                    f"{source}: the header has no 'end_header' line (it ends at line {line_no + 1})"
                )
            end = len(data) - 1 if data.endswith(b"\r") else len(data)  # at the end, no data
        line_no += 1
        raw = data[pos:end].rstrip(b"\r")
        pos = min(end + 1, len(data))
        if line_no == 1:
            continue
        text = raw.decode("latin-1")
        fields = text.split()
        if not fields:
            continue
        keyword = fields[0]
        where = f"{source}: header line {line_no}"
        if keyword in ("comment", "obj_info"):
            continue
        if keyword == "end_header":
            if len(fields) > 1:
                raise SceneFileError(f"{where}: unexpected text after 'end_header'")
            break
        if keyword == "format":
            if seen_format:
                raise SceneFileError(f"{where}: a second 'format' line")
            if len(fields) != 3 or fields[1] not in _FORMATS or fields[2] != "1.0":
                raise SceneFileError(
                    f"{where}: unsupported format {' '.join(fields[1:])!r}; expected "
                    "'ascii 1.0', 'binary_little_endian 1.0' or 'binary_big_endian 1.0'"
                )
            seen_format = True
            byte_order = _FORMATS[fields[1]]
        elif keyword == "element":
            elements.append(_parse_element(fields, elements, where, line_no))
        elif keyword == "property":
            if not elements:
                raise SceneFileError(f"{where}: 'property' before any 'element'")
            elements[-1].properties.append(_parse_property(fields, elements[-1], where))
        else:
            raise SceneFileError(f"{where}: unknown header keyword {keyword[:40]!r}")
    if not seen_format:
        raise SceneFileError(f"{source}: the header has no 'format' line")
    return elements, byte_order, pos, line_no


def _parse_element(fields: list[str], elements: list[_Element], where: str, line: int) -> _Element:
    if len(fields) != 3:
        raise SceneFileError(f"{where}: expected 'element <name> <count>'")
    name, count = fields[1], fields[2]
    if any(e.name == name for e in elements):
        raise SceneFileError(f"{where}: element {name!r} declared twice")
    if not _COUNT.fullmatch(count):
        if count.startswith("-") and _COUNT.fullmatch(count[1:]):
            raise SceneFileError(f"{where}: element {name!r} has a negative count ({count})")
        raise SceneFileError(f"{where}: element {name!r} count {count[:40]!r} is not a number")
    return _Element(name, int(count), line, [])


def _parse_property(fields: list[str], element: _Element, where: str) -> _Property:
    def dtype(token: str) -> np.dtype:
        if token not in _TYPES:
            raise SceneFileError(f"{where}: unknown property type {token[:40]!r}")
        return np.dtype(_TYPES[token])

    if len(fields) >= 2 and fields[1] == "list":
        if len(fields) != 5:
            raise SceneFileError(f"{where}: expected 'property list <count type> <type> <name>'")
        count_dtype = dtype(fields[2])
        if count_dtype.kind not in "iu":
            raise SceneFileError(f"{where}: a list's count type must be an integer type")
        prop = _Property(fields[4], dtype(fields[3]), count_dtype)
    else:
        if len(fields) != 3:
            raise SceneFileError(f"{where}: expected 'property <type> <name>'")
        prop = _Property(fields[2], dtype(fields[1]), None)
    if any(p.name == prop.name for p in element.properties):
        raise SceneFileError(
            f"{where}: property {prop.name!r} declared twice in element {element.name!r}"
        )
    return prop


# ------------------------------------------------------------------------------ binary


class _BinaryBody:
    """Walks binary rows; offsets are byte offsets into the whole file."""

    def __init__(self, data: bytes, start: int, byte_order: str, source: str) -> None:
        self.data = data
        self.pos = start
        self.byteorder: Literal["little", "big"] = "little" if byte_order == "<" else "big"
        self.source = source

    def element(self, element: _Element, keep: bool) -> _Rows:
        """Locate the element's rows from the current offset on and move past them."""
        props = element.properties
        rows = _Rows(element.name, element.count)
        if not props:
            return rows
        fixed = sum(p.dtype.itemsize for p in props if not p.is_list)
        least = fixed + sum(p.count_dtype.itemsize for p in props if p.count_dtype is not None)
        # Every row takes at least `least` bytes: check before allocating anything per row.
        if self.pos + element.count * least > len(self.data):
            raise SceneFileError(
                f"{self.source}: the header declares {element.count} rows of element "
                f"{element.name!r} (at least {least} bytes each, from byte {self.pos}) but "
                f"the file ends at byte {len(self.data)}"
            )
        if not self._uniform(element, rows):
            self._walk(element, rows, keep)
        return rows

    def _count_at(self, prop: _Property, offset: int) -> int:
        assert prop.count_dtype is not None
        size = prop.count_dtype.itemsize
        return int.from_bytes(
            self.data[offset : offset + size], self.byteorder, signed=prop.count_dtype.kind == "i"
        )

    def _strided(
        self, offset: int, dtype: np.dtype, shape: tuple[int, ...], strides: tuple[int, ...]
    ) -> npt.NDArray[Any]:
        """Return a read-only view of ``dtype`` values at ``offset`` with the given byte strides."""
        if 0 in shape:
            return np.zeros(shape, dtype=dtype)
        view: npt.NDArray[Any] = np.ndarray(
            shape,
            dtype=dtype.newbyteorder(self.byteorder),
            buffer=self.data,
            offset=offset,
            strides=strides,
        )
        return view

    def _uniform(self, element: _Element, rows: _Rows) -> bool:
        """Fill ``rows`` if every row is laid out like the first (lists of one length)."""
        n = element.count
        at = 0
        first: dict[str, int] = {}
        lengths: dict[str, int] = {}
        for prop in element.properties:
            first[prop.name] = at
            if prop.count_dtype is None:
                at += prop.dtype.itemsize
                continue
            if self.pos + at + prop.count_dtype.itemsize > len(self.data):
                return False
            length = self._count_at(prop, self.pos + at)
            if length < 0:
                return False
            lengths[prop.name] = length
            at += prop.count_dtype.itemsize + length * prop.dtype.itemsize
        stride = at
        if self.pos + n * stride > len(self.data):
            return False
        for prop in element.properties:
            if prop.count_dtype is not None:
                found = self._strided(
                    self.pos + first[prop.name], prop.count_dtype, (n,), (stride,)
                )
                if not (found == lengths[prop.name]).all():
                    return False
        rows.stride = stride
        rows.first = {name: self.pos + offset for name, offset in first.items()}
        rows.uniform_length = lengths
        self.pos += n * stride
        return True

    def _walk(self, element: _Element, rows: _Rows, keep: bool) -> None:
        """Read rows one at a time (lists of varying lengths)."""
        n = element.count if keep else 0
        size = len(self.data)
        where = {p.name: np.empty(n, dtype=np.int64) for p in element.properties}
        length = {p.name: np.empty(n, dtype=np.int64) for p in element.properties if p.is_list}
        plan = [
            (
                where[p.name] if keep else None,
                length.get(p.name) if keep else None,
                p.dtype.itemsize,
                0 if p.count_dtype is None else p.count_dtype.itemsize,
                p.count_dtype is not None and p.count_dtype.kind == "i",
            )
            for p in element.properties
        ]
        data = self.data
        byteorder = self.byteorder
        pos = self.pos
        for row in range(element.count):
            row_start = pos
            for offsets, lengths, item, count_size, signed in plan:
                if offsets is not None:
                    offsets[row] = pos
                if not count_size:
                    pos += item
                    continue
                if pos + count_size > size:
                    raise self._ends(element, row, row_start)
                count = int.from_bytes(data[pos : pos + count_size], byteorder, signed=signed)
                if count < 0:
                    raise SceneFileError(
                        f"{self.source}: byte {pos}: row {row} of element {element.name!r} "
                        f"has a negative list count ({count})"
                    )
                if lengths is not None:
                    lengths[row] = count
                pos += count_size + count * item
                if pos > size:
                    raise self._ends(element, row, row_start)
            if pos > size:
                raise self._ends(element, row, row_start)
        self.pos = pos
        rows.where = where
        rows.length = length

    def _ends(self, element: _Element, row: int, offset: int) -> SceneFileError:
        return SceneFileError(
            f"{self.source}: the file ends at byte {len(self.data)}, inside row {row} of "
            f"element {element.name!r} (the row starts at byte {offset}; the header declares "
            f"{element.count} rows)"
        )

    def finish(self, elements: list[_Element]) -> None:
        """Refuse bytes after the last element."""
        if self.pos != len(self.data):
            raise SceneFileError(
                f"{self.source}: {len(self.data) - self.pos} bytes of unexpected data after "
                f"the last element, from byte {self.pos} (the header declares "
                f"{', '.join(f'{e.count} {e.name}' for e in elements)})"
            )

    def _gather(self, offsets: I64Array, dtype: np.dtype) -> npt.NDArray[Any]:
        """Return the values of ``dtype`` starting at each byte offset."""
        # A view in which element j is the value starting at byte j.
        sliding = self._strided(0, dtype, (len(self.data) - dtype.itemsize + 1,), (1,))
        return sliding[offsets]

    def scalar(self, rows: _Rows, prop: _Property) -> F64Array:
        """Return the property's value in every row, as float64."""
        if rows.stride:
            values = self._strided(rows.first[prop.name], prop.dtype, (rows.n,), (rows.stride,))
        else:
            values = self._gather(rows.where[prop.name], prop.dtype)
        return values.astype(np.float64)

    def list_values(self, rows: _Rows, prop: _Property) -> I64Array:
        """Return every row's list items, concatenated, as int64."""
        assert prop.count_dtype is not None
        start = prop.count_dtype.itemsize
        if rows.stride:
            length = rows.uniform_length[prop.name]
            shape, strides = (rows.n, length), (rows.stride, prop.dtype.itemsize)
            table = self._strided(rows.first[prop.name] + start, prop.dtype, shape, strides)
            return table.astype(np.int64).reshape(-1)
        counts = rows.length[prop.name]
        offsets = np.repeat(rows.where[prop.name] + start, counts)
        offsets += _ramp(counts) * prop.dtype.itemsize
        return self._gather(offsets, prop.dtype).astype(np.int64)

    def counts(self, rows: _Rows, prop: _Property) -> I64Array:
        """Return every row's list length."""
        if rows.stride:
            return np.full(rows.n, rows.uniform_length[prop.name], dtype=np.int64)
        return rows.length[prop.name]

    def locator(self, rows: _Rows, name: str) -> Locator:
        """Return a function naming the byte offset of property ``name`` in a row."""
        if rows.stride:
            first, stride = rows.first[name], rows.stride
            return lambda row: f"byte {first + row * stride}"
        offsets = rows.where[name]
        return lambda row: f"byte {int(offsets[row])}"


def _ramp(counts: I64Array) -> I64Array:
    """``0 .. c - 1`` for each count ``c``, concatenated."""
    ramp = np.arange(int(counts.sum()), dtype=np.int64)
    return ramp - np.repeat(np.cumsum(counts) - counts, counts)


# ------------------------------------------------------------------------------ ASCII


class _AsciiBody:
    """Reads ASCII rows, one per non-blank line; offsets index a flat array of values."""

    def __init__(self, data: bytes, start: int, header_lines: int, source: str) -> None:
        self.source = source
        body = data[start:]
        if not body.isascii():
            bad = next(i for i, b in enumerate(body) if b > 127)
            line = header_lines + 1 + body.count(b"\n", 0, bad)
            raise SceneFileError(f"{source}: line {line}: non-ASCII byte in an ASCII PLY body")
        text = body.decode("ascii")
        if "\r" in text:
            text = text.replace("\r\n", "\n").replace("\r", "\n")
        lines = [line.strip() for line in text.split("\n")]
        keep = [i for i, line in enumerate(lines) if line]
        self.lines = [lines[i] for i in keep]
        self.numbers = np.asarray(keep, dtype=np.int64) + header_lines + 1
        self.next = 0  # first unread row line
        self.flat: dict[str, F64Array] = {}  # per element: all of its values
        self.element_lines: dict[str, I64Array] = {}

    def element(self, element: _Element, keep: bool) -> _Rows:
        """Parse the element's rows, one line each, and check each holds its properties."""
        result = _Rows(element.name, element.count)
        if not element.properties:
            return result  # rows without values are blank lines, which are skipped
        first = self.next
        available = len(self.lines) - first
        if element.count > available:
            last = int(self.numbers[-1]) if self.lines else "the header's last"
            raise SceneFileError(
                f"{self.source}: the header declares {element.count} rows of element "
                f"{element.name!r} but the data ends after {available} of them "
                f"(at line {last})"
            )
        n = element.count
        self.next += n
        rows = self.lines[first : first + n]
        numbers = self.numbers[first : first + n]
        self.element_lines[element.name] = numbers
        flat, starts, widths = self._values(rows, numbers)
        self.flat[element.name] = flat
        ends = starts + widths
        pos = starts.copy()
        where: dict[str, I64Array] = {}
        length: dict[str, I64Array] = {}

        def refuse(row: int, detail: str) -> SceneFileError:
            """Return the error naming row ``row`` and its line; ``detail`` follows."""
            return SceneFileError(
                f"{self.source}: line {int(numbers[row])}: row {row} of element "
                f"{element.name!r}{detail}"
            )

        for prop in element.properties:
            short = pos >= ends
            if short.any():
                row = int(np.flatnonzero(short)[0])
                raise refuse(
                    row, f" has {int(widths[row])} values; property {prop.name!r} is missing"
                )
            where[prop.name] = pos.copy()
            if not prop.is_list:
                pos += 1
                continue
            count = flat[pos]
            bad = ~np.isfinite(count) | (count < 0) | (count != np.floor(count))
            bad |= count > (ends - pos - 1)
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise refuse(
                    row,
                    f": list {prop.name!r} declares {flat[pos[row]]:g} values "
                    f"but {int(ends[row] - pos[row] - 1)} follow",
                )
            counts = count.astype(np.int64)
            length[prop.name] = counts
            pos += 1 + counts
        extra = pos != ends
        if extra.any():
            row = int(np.flatnonzero(extra)[0])
            raise refuse(row, f" has {int(ends[row] - pos[row])} values more than its properties")
        result.where, result.length = where, length
        return result

    def _values(self, rows: list[str], numbers: I64Array) -> tuple[F64Array, I64Array, I64Array]:
        """All values of the rows, flat, with each row's first index and value count."""
        n = len(rows)
        table = _loadtxt("\n".join(rows))
        if table is not None and table.shape[0] == n:
            width = table.shape[1]
            starts = np.arange(n, dtype=np.int64) * width
            return table.reshape(-1), starts, np.full(n, width, dtype=np.int64)
        # Rows of different lengths: count each row's values, then parse them all as one
        # line with numpy's C reader, or value by value where it cannot (exact errors).
        widths = np.fromiter((len(row.split()) for row in rows), dtype=np.int64, count=n)
        line = _loadtxt(" ".join(rows))
        if line is not None and line.size == int(widths.sum()):
            flat = line.reshape(-1)
        else:
            flat = np.empty(int(widths.sum()), dtype=np.float64)
            k = 0
            for row, text in enumerate(rows):
                for token in text.split():
                    try:
                        flat[k] = float(token)
                    except ValueError:
                        raise SceneFileError(
                            f"{self.source}: line {int(numbers[row])}: cannot parse number "
                            f"{token[:40]!r}"
                        ) from None
                    k += 1
        return flat, np.cumsum(widths) - widths, widths

    def finish(self, elements: list[_Element]) -> None:
        if self.next < len(self.lines):
            raise SceneFileError(
                f"{self.source}: line {int(self.numbers[self.next])}: unexpected data after "
                f"the last element (the header declares "
                f"{', '.join(f'{e.count} {e.name}' for e in elements)})"
            )

    def scalar(self, rows: _Rows, prop: _Property) -> F64Array:
        """Return the property's value in every row."""
        return self.flat[rows.element][rows.where[prop.name]]

    def counts(self, rows: _Rows, prop: _Property) -> I64Array:
        """Return every row's list length."""
        return rows.length[prop.name]

    def list_values(self, rows: _Rows, prop: _Property) -> I64Array:
        """Return every row's list items, concatenated; each must be an integer."""
        counts = rows.length[prop.name]
        flat = self.flat[rows.element]
        values = flat[np.repeat(rows.where[prop.name] + 1, counts) + _ramp(counts)]
        bad = ~np.isfinite(values) | (values != np.floor(values)) | (np.abs(values) >= 2.0**62)
        if bad.any():
            corner, row = first_corner(bad, counts)
            raise SceneFileError(
                f"{self.source}: line {int(self.element_lines[rows.element][row])}: face {row} has "
                f"vertex index {values[corner]:g}, not an integer"
            )
        index: I64Array = values.astype(np.int64)
        return index

    def locator(self, rows: _Rows, name: str) -> Locator:
        """Return a function naming the line of a row."""
        numbers = self.element_lines[rows.element]
        return lambda row: f"line {int(numbers[row])}"


def _loadtxt(body: str) -> F64Array | None:
    """Parse whitespace-separated columns with numpy's C reader; ``None`` if it cannot."""
    if not body:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            table: F64Array = np.loadtxt(
                io.StringIO(body), dtype=np.float64, ndmin=2, comments=None
            )
            return table
    except (ValueError, Warning):
        return None
