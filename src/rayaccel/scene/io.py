r"""Reading scene files into a :class:`~rayaccel.scene.mesh.TriangleMesh`.

:func:`load_mesh` reads Wavefront OBJ with its own parser and PLY, STL, GLB and
glTF through trimesh (``trimesh.load(..., force="mesh", process=False)``, so
multi-object files are concatenated and no vertex is merged or dropped). Any of
these except glTF may be gzip-compressed (``kitchen.ply.gz``).

OBJ gets its own reader because trimesh 5.2 silently drops ``v`` lines whose
fields are separated by tabs and then returns an empty or wrong mesh. The reader
follows the OBJ specification (Wavefront Technologies, *Advanced Visualizer*
manual, Appendix B1, "Object Files (.obj)"), geometry only: ``v x y z [w]``
(``w`` and trailing vertex colours are ignored), ``f`` with ``a``, ``a/b``,
``a//c`` and ``a/b/c`` references, negative (relative) indices, polygons
fan-triangulated as ``(0, k, k + 1)``, ``\`` line continuation, any mix of
spaces and tabs, CRLF line ends, ``#`` comments. Grouping, material, texture and
normal statements are skipped; free-form geometry and unknown statements are
errors, because dropping them would return a wrong mesh silently. Every error
names the file and the line (``scene.obj:12: face index 40 out of range (31
vertices)``). Unreferenced vertices are kept, so indices match the file.

Cost: a well-formed file is parsed with ``numpy.loadtxt``'s C reader over all
``v`` and all ``f`` lines at once (a second or two per million lines); anything the fast
path cannot vouch for is re-read line by line, which is slower but reports the
exact line of the first error.
"""

from __future__ import annotations

import gzip
import io
import os
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from rayaccel.errors import BackendUnavailableError, InvalidInputError, SceneFileError
from rayaccel.scene.mesh import TriangleMesh

F64Array = npt.NDArray[np.float64]
I64Array = npt.NDArray[np.int64]

#: Formats :func:`load_mesh` reads, by file suffix (a further ``.gz`` is allowed
#: for every one except ``.gltf``, whose buffers live in separate files).
MESH_SUFFIXES: tuple[str, ...] = (".obj", ".ply", ".stl", ".glb", ".gltf")
#: Every full suffix :func:`load_mesh` accepts, compressed ones included.
SUPPORTED_SUFFIXES: tuple[str, ...] = (
    *MESH_SUFFIXES,
    *(suffix + ".gz" for suffix in MESH_SUFFIXES if suffix != ".gltf"),
)

# Statements that carry no triangle geometry and are skipped.
_OBJ_IGNORED = frozenset(
    {
        "vt", "vn", "vp", "o", "g", "s", "mg", "usemtl", "mtllib", "l", "p",
        "lod", "maplib", "usemap", "bevel", "c_interp", "d_interp",
        "shadow_obj", "trace_obj",
    }
)  # fmt: skip
# Free-form curve and surface statements: geometry we cannot tessellate.
_OBJ_FREEFORM = frozenset(
    {
        "cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm", "trim",
        "hole", "scrv", "sp", "end", "con", "ctech", "stech",
    }
)  # fmt: skip
_VERTEX_COLUMNS = (3, 4, 6, 7)  # x y z, + w, + r g b, + w r g b
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_INDEX_LIMIT = 2**62  # larger references cannot be valid and would overflow int64


def scene_stem(path: str | os.PathLike[str]) -> str:
    """Return a scene file's name without its supported suffix.

    Parameters
    ----------
    path : str or path-like
        A file name or path, e.g. ``"scenes/kitchen.ply.gz"``.

    Returns
    -------
    str
        ``"kitchen"`` for ``kitchen.ply.gz``; the plain stem for other names.
    """
    name = Path(path).name
    lowered = name.lower()
    for suffix in sorted(SUPPORTED_SUFFIXES, key=len, reverse=True):
        if lowered.endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return Path(name).stem


def _file_format(path: Path) -> tuple[str, bool]:
    """Return ``(format, gzipped)`` for a path, e.g. ``("ply", True)``."""
    lowered = path.name.lower()
    for suffix in sorted(SUPPORTED_SUFFIXES, key=len, reverse=True):
        if lowered.endswith(suffix):
            compressed = suffix.endswith(".gz")
            return suffix.removesuffix(".gz").lstrip("."), compressed
    raise SceneFileError(
        f"{path}: unsupported scene format {''.join(path.suffixes) or '(no suffix)'!r}; "
        f"supported: {', '.join(SUPPORTED_SUFFIXES)}"
    )


def load_mesh(path: str | os.PathLike[str], *, name: str | None = None) -> TriangleMesh:
    """Load a triangle mesh from an OBJ, PLY, STL, GLB or glTF file.

    Parameters
    ----------
    path : str or path-like
        The file. The format follows the suffix (case-insensitive): ``.obj``,
        ``.ply``, ``.stl``, ``.glb``, ``.gltf``, each but ``.gltf`` optionally
        followed by ``.gz``.
    name : str, optional
        The mesh's label; defaults to the file name without its suffix.

    Returns
    -------
    TriangleMesh
        All triangles of the file (polygons fan-triangulated, multi-object
        files concatenated), vertices in file order.

    Raises
    ------
    SceneFileError
        The file is missing, unreadable, of an unsupported format, malformed
        (the message names the path, and the line for OBJ), or holds no
        triangles or a non-finite vertex.
    BackendUnavailableError
        A non-OBJ format was asked for and trimesh is not installed.
    """
    file_path = Path(path)
    file_format, compressed = _file_format(file_path)
    if not file_path.exists():
        raise SceneFileError(f"{file_path}: no such file")
    if not file_path.is_file():
        raise SceneFileError(f"{file_path}: not a regular file")
    label = scene_stem(file_path) if name is None else name
    if file_format == "obj":
        vertices, faces = parse_obj(_read_bytes(file_path, compressed), source=str(file_path))
    else:
        vertices, faces = _load_with_trimesh(file_path, file_format, compressed)
    try:
        return TriangleMesh(vertices, faces, name=label)
    except InvalidInputError as exc:
        raise SceneFileError(f"{file_path}: {exc}") from exc


def _read_bytes(path: Path, compressed: bool) -> bytes:
    try:
        if compressed:
            with gzip.open(path, "rb") as handle:
                return handle.read()
        return path.read_bytes()
    except (OSError, EOFError, zlib.error) as exc:
        raise SceneFileError(f"{path}: cannot read file ({exc})") from exc


def _load_with_trimesh(path: Path, file_format: str, compressed: bool) -> tuple[F64Array, I64Array]:
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - trimesh is a core dependency
        raise BackendUnavailableError(
            f"{path}: reading {file_format.upper()} needs trimesh (pip install trimesh)"
        ) from exc
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if compressed:
                source = io.BytesIO(_read_bytes(path, compressed=True))
                loaded = trimesh.load(source, file_type=file_format, force="mesh", process=False)
            else:
                loaded = trimesh.load(str(path), file_type=file_format, force="mesh", process=False)
    except SceneFileError:
        raise
    except Exception as exc:  # trimesh raises many unrelated types on bad input
        raise SceneFileError(
            f"{path}: trimesh cannot read it as {file_format.upper()} ({type(exc).__name__}: {exc})"
        ) from exc
    faces = getattr(loaded, "faces", None)
    vertices = getattr(loaded, "vertices", None)
    if faces is None or vertices is None or len(faces) == 0:
        raise SceneFileError(f"{path}: the file holds no triangles (0 faces loaded)")
    face_array = np.asarray(faces)
    if face_array.ndim != 2 or face_array.shape[1] != 3:
        raise SceneFileError(f"{path}: expected triangles, got faces of shape {face_array.shape}")
    return np.asarray(vertices, dtype=np.float64), face_array.astype(np.int64, copy=False)


# --------------------------------------------------------------------------- OBJ


def parse_obj(data: str | bytes, *, source: str = "<obj>") -> tuple[F64Array, I64Array]:
    """Parse Wavefront OBJ text into vertex and triangle arrays.

    Parameters
    ----------
    data : str or bytes
        The file's contents (bytes are decoded as UTF-8, undecodable bytes
        replaced; only names can contain them).
    source : str
        Name used in error messages, normally the path.

    Returns
    -------
    vertices : (V, 3) float64 ndarray
        Every ``v`` statement's ``x y z``, in file order.
    faces : (F, 3) int64 ndarray
        Zero-based vertex indices; a polygon of ``n`` vertices becomes the fan
        ``(0, k, k + 1)``, ``k = 1 .. n - 2``, in file order.

    Raises
    ------
    SceneFileError
        ``source:line: reason`` for the first malformed line: an unparsable
        number, a vertex with fewer than 3 coordinates or a non-finite one, a
        face with fewer than 3 vertices, index 0, an index out of range,
        free-form geometry or an unknown statement; ``source: ...`` when the
        file has no faces.

    Notes
    -----
    Relative index ``-k`` refers to the ``k``-th most recent vertex defined
    *before* the face; positive indices may refer to any vertex of the file.
    """
    text = data.decode("utf-8", errors="replace") if isinstance(data, bytes) else data
    text = text.removeprefix("\ufeff")
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    lines = text.split("\n")
    line_numbers: list[int] | None = None
    if "\\\n" in text or text.endswith("\\"):
        lines, line_numbers = _join_continued_lines(lines)

    def number(i: int) -> int:
        return line_numbers[i] if line_numbers is not None else i + 1

    # Sort statements: vertices and faces by their first two characters, the rest by keyword.
    v_lines: list[int] = []
    f_lines: list[int] = []
    for i, raw in enumerate(lines):
        line = raw.strip()
        if not line:
            continue
        lines[i] = line
        head, sep = line[0], line[1:2]
        if sep in (" ", "\t"):
            if head == "v":
                v_lines.append(i)
                continue
            if head == "f":
                f_lines.append(i)
                continue
        if head == "#":
            continue
        keyword = line.split(None, 1)[0].partition("#")[0]
        if not keyword or keyword in _OBJ_IGNORED:
            continue
        if keyword in ("v", "f"):
            what = "vertex" if keyword == "v" else "face"
            raise SceneFileError(f"{source}:{number(i)}: {what} statement without data")
        if keyword in _OBJ_FREEFORM:
            raise SceneFileError(
                f"{source}:{number(i)}: free-form geometry ({keyword!r}) is not supported"
            )
        raise SceneFileError(f"{source}:{number(i)}: unknown OBJ statement {keyword!r}")

    vertices = _parse_vertices(lines, v_lines, number, source)
    if not f_lines:
        raise SceneFileError(f"{source}: the file holds no faces (0 triangles)")
    counts, refs = _parse_faces(lines, f_lines, number, source)

    # Resolve 1-based and relative indices against the vertices defined so far.
    face_of_ref = np.repeat(np.arange(len(f_lines)), counts)
    n_before = np.searchsorted(np.asarray(v_lines, dtype=np.int64), np.asarray(f_lines))
    n_vertices = vertices.shape[0]
    index = np.where(refs > 0, refs - 1, refs + n_before[face_of_ref])
    bad = (refs == 0) | (index < 0) | (index >= n_vertices)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        line_no, ref = number(f_lines[face_of_ref[k]]), int(refs[k])
        if ref == 0:
            raise SceneFileError(f"{source}:{line_no}: face index 0 is invalid (OBJ is 1-based)")
        if ref < 0:
            raise SceneFileError(
                f"{source}:{line_no}: relative face index {ref} out of range "
                f"({int(n_before[face_of_ref[k]])} vertices defined before this line)"
            )
        raise SceneFileError(
            f"{source}:{line_no}: face index {ref} out of range ({n_vertices} vertices)"
        )
    return vertices, _fan_triangulate(counts, index)


def _join_continued_lines(lines: list[str]) -> tuple[list[str], list[int]]:
    """Merge lines ending in a backslash with the next; return lines and their first numbers."""
    joined: list[str] = []
    numbers: list[int] = []
    pending: list[str] = []
    start = 0
    for i, line in enumerate(lines):
        if not pending:
            start = i
        if line.endswith("\\"):
            pending.append(line[:-1])
            continue
        pending.append(line)
        joined.append(" ".join(pending))
        numbers.append(start + 1)
        pending = []
    if pending:
        joined.append(" ".join(pending))
        numbers.append(start + 1)
    return joined, numbers


def _loadtxt(body: str, dtype: type) -> npt.NDArray[np.generic] | None:
    """Parse whitespace-separated columns with numpy's C reader; ``None`` if it cannot."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            return np.loadtxt(io.StringIO(body), dtype=dtype, ndmin=2, comments=None)
    except (ValueError, Warning):
        return None


def _parse_vertices(
    lines: list[str], v_lines: list[int], number: Callable[[int], int], source: str
) -> F64Array:
    if not v_lines:
        return np.zeros((0, 3), dtype=np.float64)
    bodies = [lines[i][2:] for i in v_lines]
    body = "\n".join(bodies)
    table = _loadtxt(body, np.float64) if "#" not in body else None
    if table is not None and table.shape[0] == len(v_lines) and table.shape[1] in _VERTEX_COLUMNS:
        xyz = np.ascontiguousarray(table[:, :3])
    else:
        xyz = np.empty((len(v_lines), 3), dtype=np.float64)
        for row, (i, text) in enumerate(zip(v_lines, bodies, strict=True)):
            fields = text.partition("#")[0].split()
            if len(fields) < 3:
                raise SceneFileError(
                    f"{source}:{number(i)}: vertex needs 3 coordinates, got {len(fields)}"
                )
            if len(fields) not in _VERTEX_COLUMNS:
                raise SceneFileError(
                    f"{source}:{number(i)}: vertex has {len(fields)} values; expected "
                    "x y z, x y z w, x y z r g b or x y z w r g b"
                )
            values = []
            for field in fields:
                try:
                    values.append(float(field))
                except ValueError:
                    raise SceneFileError(
                        f"{source}:{number(i)}: cannot parse number {field!r}"
                    ) from None
            xyz[row] = values[:3]
    finite = np.isfinite(xyz).all(axis=1) & (np.abs(xyz) <= _FLOAT32_MAX).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise SceneFileError(
            f"{source}:{number(v_lines[row])}: vertex {row + 1} is not a finite float32 "
            f"({xyz[row].tolist()})"
        )
    return xyz


def _parse_faces(
    lines: list[str], f_lines: list[int], number: Callable[[int], int], source: str
) -> tuple[I64Array, I64Array]:
    """Return per-face vertex counts and the flat raw (1-based or negative) references."""
    bodies = [lines[i][2:] for i in f_lines]
    fast = _parse_faces_fast(bodies)
    if fast is not None:
        return fast
    counts = np.empty(len(f_lines), dtype=np.int64)
    refs: list[int] = []
    for row, (i, text) in enumerate(zip(f_lines, bodies, strict=True)):
        tokens = text.partition("#")[0].split()
        if len(tokens) < 3:
            raise SceneFileError(
                f"{source}:{number(i)}: face needs at least 3 vertices, got {len(tokens)}"
            )
        for token in tokens:
            parts = token.split("/")
            if len(parts) > 3 or not parts[0]:
                raise SceneFileError(
                    f"{source}:{number(i)}: malformed face vertex {token!r} "
                    "(expected a, a/b, a//c or a/b/c)"
                )
            for k, part in enumerate(parts):
                if k > 0 and not part:
                    continue
                try:
                    value = int(part)
                except ValueError:
                    raise SceneFileError(
                        f"{source}:{number(i)}: cannot parse index {part!r} in face vertex "
                        f"{token!r}"
                    ) from None
                if k == 0:
                    if abs(value) >= _INDEX_LIMIT:
                        raise SceneFileError(
                            f"{source}:{number(i)}: face index {value} out of range"
                        )
                    refs.append(value)
        counts[row] = len(tokens)
    return counts, np.asarray(refs, dtype=np.int64)


def _parse_faces_fast(bodies: list[str]) -> tuple[I64Array, I64Array] | None:
    """Vectorised face parsing for files whose faces all share one size and one form.

    Returns ``None`` whenever it cannot prove the result equals the line-by-line
    parse; the caller then falls back to it (which also finds the error line).
    """
    body = "\n".join(bodies)
    if "#" in body or not body.isascii():
        return None
    first = bodies[0].split(None, 1)[0]
    double = "//" in first
    parts = 2 if double else first.count("/") + 1
    if parts > 3:
        return None
    if double:
        flat = body.replace("//", " ")
        if "/" in flat:
            return None
    else:
        flat = body.replace("/", " ") if parts > 1 else body
        if parts == 1 and "/" in body:
            return None
    table = _loadtxt(flat, np.int64)
    if table is None or table.shape[0] != len(bodies) or table.shape[1] % parts:
        return None
    n_corners = table.shape[1] // parts
    if n_corners < 3:
        return None
    if parts > 1 and not _tokens_are_uniform(
        body, len(bodies), n_corners, 2 if double else parts - 1
    ):
        return None
    refs = np.ascontiguousarray(table[:, ::parts]).reshape(-1)
    return np.full(len(bodies), n_corners, dtype=np.int64), refs


def _tokens_are_uniform(body: str, n_lines: int, n_tokens: int, n_slashes: int) -> bool:
    """Check every line has ``n_tokens`` tokens, each with exactly ``n_slashes`` slashes.

    Together with a column count of ``n_tokens * parts`` per line (no empty
    parts), this pins each token to the expected ``a/b``, ``a//c`` or ``a/b/c``
    form, so column ``k * parts`` is the vertex index of corner ``k``.
    """
    chars = np.frombuffer(body.encode("ascii"), dtype=np.uint8)
    space = chars <= 32  # loadtxt accepted the text, so every control byte is a separator
    # A token starts at a non-space character that follows a space (or the start).
    starts = np.flatnonzero(space[:-1] & ~space[1:]) + 1
    if not space[0]:
        starts = np.concatenate(([0], starts))
    if starts.shape[0] != n_lines * n_tokens:
        return False
    end = np.array([chars.shape[0]])
    line_breaks = np.concatenate(([-1], np.flatnonzero(chars == 10), end))
    if not (np.diff(np.searchsorted(starts, line_breaks)) == n_tokens).all():
        return False
    slashes = np.flatnonzero(chars == 47)
    per_token = np.diff(np.searchsorted(slashes, np.concatenate((starts, end))))
    return bool((per_token == n_slashes).all())


def _fan_triangulate(counts: I64Array, index: I64Array) -> I64Array:
    """Triangulate polygons given as flat corner indices: ``(0, k, k + 1)`` fans."""
    if (counts == 3).all():
        return index.reshape(-1, 3)
    n_tris = counts - 2
    first = np.cumsum(counts) - counts
    owner = np.repeat(np.arange(counts.shape[0]), n_tris)
    k = np.arange(int(n_tris.sum())) - np.repeat(np.cumsum(n_tris) - n_tris, n_tris)
    base = first[owner]
    return np.stack([index[base], index[base + k + 1], index[base + k + 2]], axis=1)


__all__ = ["MESH_SUFFIXES", "SUPPORTED_SUFFIXES", "load_mesh", "parse_obj", "scene_stem"]
