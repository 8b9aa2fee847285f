r"""Reading scene files into a :class:`~rayaccel.scene.mesh.TriangleMesh`.

:func:`load_mesh` reads Wavefront OBJ, PLY (:mod:`~rayaccel.scene.ply`) and STL
(:mod:`~rayaccel.scene.stl`) with its own strict readers, and GLB and glTF through
trimesh (``trimesh.load(..., force="mesh", process=False)``, so multi-object files
are concatenated and no vertex is merged or dropped) after checking the GLB
container and the glTF buffers itself. Any of these except glTF may be
gzip-compressed (``kitchen.ply.gz``).

Every malformed file is refused with a :class:`~rayaccel.errors.SceneFileError`
naming the file and the fault (with its line or byte offset where known); the
contract is tabled in ``docs/reliability.md``. Nothing is allocated beyond a bound:
a file, or what a ``.gz`` file decompresses to, may hold at most ``max_bytes``
bytes (default :data:`DEFAULT_MAX_SCENE_BYTES`, 2 GiB, or the environment variable
``RAYACCEL_MAX_SCENE_BYTES``); ``.gz`` files are decompressed in 1 MiB chunks and
refused as soon as they exceed it. The readers then allocate in proportion to the
bytes actually present, never to a count a header declares.

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
import json
import os
import urllib.parse
import warnings
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rayaccel.errors import BackendUnavailableError, InvalidInputError, SceneFileError
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.scene.ply import parse_ply
from rayaccel.scene.polygons import F64Array, I64Array, check_polygons, check_vertices
from rayaccel.scene.polygons import fan_triangulate as _fan_triangulate
from rayaccel.scene.stl import parse_stl

#: Environment variable holding the largest scene file, in bytes, :func:`load_mesh` reads.
MAX_SCENE_BYTES_VAR = "RAYACCEL_MAX_SCENE_BYTES"
#: Default of that limit: 2 GiB, as a file or decompressed (a binary PLY of about
#: 80 million triangles, an OBJ of about 20 million).
DEFAULT_MAX_SCENE_BYTES = 2**31
_CHUNK = 2**20  # decompression step

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


def load_mesh(
    path: str | os.PathLike[str], *, name: str | None = None, max_bytes: int | None = None
) -> TriangleMesh:
    """Load a triangle mesh from an OBJ, PLY, STL, GLB or glTF file.

    Parameters
    ----------
    path : str or path-like
        The file. The format follows the suffix (case-insensitive): ``.obj``,
        ``.ply``, ``.stl``, ``.glb``, ``.gltf``, each but ``.gltf`` optionally
        followed by ``.gz``.
    name : str, optional
        The mesh's label; defaults to the file name without its suffix.
    max_bytes : int, optional
        The most bytes the file may hold, or decompress to for ``.gz``; larger
        files are refused before (or while) reading. Defaults to the environment
        variable ``RAYACCEL_MAX_SCENE_BYTES``, else 2 GiB.

    Returns
    -------
    TriangleMesh
        All triangles of the file (polygons fan-triangulated, multi-object
        files concatenated), vertices in file order.

    Raises
    ------
    SceneFileError
        The file is missing, not a regular file, unreadable, empty, larger than
        ``max_bytes``, of an unsupported format, malformed (the message names the
        path and the line or byte offset where known), or holds no triangles, a
        vertex that is not a finite float32 or a vertex index out of range.
    InvalidInputError
        ``max_bytes`` (or ``RAYACCEL_MAX_SCENE_BYTES``) is not a positive integer.
    BackendUnavailableError
        A GLB or glTF file was asked for and trimesh is not installed.
    """
    file_path = Path(path)
    limit = _byte_limit(max_bytes)
    file_format, compressed = _file_format(file_path)
    if not file_path.exists():
        raise SceneFileError(f"{file_path}: no such file")
    if not file_path.is_file():
        raise SceneFileError(f"{file_path}: not a regular file")
    label = scene_stem(file_path) if name is None else name
    data = _read_bytes(file_path, compressed, limit, max_bytes is None)
    source = str(file_path)
    if file_format == "obj":
        vertices, faces = parse_obj(data, source=source)
    elif file_format == "ply":
        vertices, faces = parse_ply(data, source=source)
    elif file_format == "stl":
        vertices, faces = parse_stl(data, source=source)
    else:
        vertices, faces = _load_gltf(data, file_path, file_format, limit)
    try:
        return TriangleMesh(vertices, faces, name=label)
    except InvalidInputError as exc:
        raise SceneFileError(f"{file_path}: {exc}") from exc


def _byte_limit(max_bytes: int | None) -> int:
    """Return the size limit from the argument, else the environment, else the default."""
    if max_bytes is None:
        text = os.environ.get(MAX_SCENE_BYTES_VAR, "").strip()
        if not text:
            return DEFAULT_MAX_SCENE_BYTES
        try:
            value = int(text)
        except ValueError:
            value = 0
        if value <= 0:
            raise InvalidInputError(
                f"{MAX_SCENE_BYTES_VAR}: expected a positive number of bytes, got {text!r}"
            )
        return value
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, int | np.integer):
        raise InvalidInputError(
            f"max_bytes: expected a positive int, got {type(max_bytes).__name__} {max_bytes!r}"
        )
    if max_bytes <= 0:
        raise InvalidInputError(f"max_bytes: expected a positive int, got {max_bytes}")
    return int(max_bytes)


def _too_large(path: Path, limit: int, from_env: bool, what: str) -> SceneFileError:
    if from_env:
        setting = f"set by {MAX_SCENE_BYTES_VAR} or by default; load_mesh's max_bytes overrides it"
    else:
        setting = "load_mesh's max_bytes argument"
    return SceneFileError(
        f"{path}: {what} more than {limit} bytes, the limit on scene files ({setting})"
    )


def _read_bytes(path: Path, compressed: bool, limit: int, from_env: bool = True) -> bytes:
    """Read a whole file, decompressing ``.gz`` in chunks, refusing more than ``limit`` bytes."""
    try:
        if compressed:
            buffer = io.BytesIO()
            with gzip.open(path, "rb") as handle:
                while True:
                    chunk = handle.read(min(_CHUNK, limit + 1 - buffer.tell()))
                    if not chunk:
                        break
                    buffer.write(chunk)
                    if buffer.tell() > limit:
                        raise _too_large(path, limit, from_env, "it decompresses to")
            data = buffer.getvalue()  # shares the buffer's bytes, no copy
        else:
            size = path.stat().st_size
            if size > limit:
                raise _too_large(path, limit, from_env, "it holds")
            with path.open("rb") as handle:
                # read(n) allocates n bytes up front: ask for what stat reported (+1 to
                # notice a file that grew), not for the limit.
                data = handle.read(size + 1)
            if len(data) > limit:
                raise _too_large(path, limit, from_env, "it holds")
    except (OSError, EOFError, zlib.error) as exc:
        kind = "gzip data" if compressed else "file"
        raise SceneFileError(f"{path}: cannot read {kind} ({exc})") from exc
    if not data:
        detail = "it decompresses to 0 bytes" if compressed else "0 bytes"
        raise SceneFileError(f"{path}: the file is empty ({detail})")
    return data


# --------------------------------------------------------------------------- glTF, GLB


def _load_gltf(data: bytes, path: Path, file_format: str, limit: int) -> tuple[F64Array, I64Array]:
    """Check the container and buffers, load with trimesh, and check what it returns."""
    document = _glb_document(data, path) if file_format == "glb" else _json_document(data, path)
    external = _check_buffers(document, path, limit)
    _check_accessors(document, path, len(data) + external)
    _check_nodes(document, path)
    try:
        import trimesh
        from trimesh.resolvers import FilePathResolver
    except ImportError as exc:  # pragma: no cover - trimesh is a core dependency
        raise BackendUnavailableError(
            f"{path}: reading {file_format.upper()} needs trimesh (pip install trimesh)"
        ) from exc
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(
                io.BytesIO(data),
                file_type=file_format,
                force="mesh",
                process=False,
                resolver=FilePathResolver(str(path.parent)),
                skip_materials=True,
            )
    except (Exception, RecursionError) as exc:  # trimesh raises many unrelated types
        raise SceneFileError(
            f"{path}: trimesh cannot read it as {file_format.upper()} ({type(exc).__name__}: "
            f"{str(exc)[:300]})"
        ) from exc
    return _trimesh_arrays(loaded, path)


def _trimesh_arrays(loaded: object, path: Path) -> tuple[F64Array, I64Array]:
    """Validate what trimesh returned: (V, 3) finite float32 vertices, (F, 3) faces in range."""
    faces = getattr(loaded, "faces", None)
    vertices = getattr(loaded, "vertices", None)
    if faces is None or vertices is None or len(faces) == 0:
        raise SceneFileError(f"{path}: the file holds no triangles (0 faces loaded)")
    face_array = np.asarray(faces)
    vertex_array = np.asarray(vertices)
    if face_array.ndim != 2 or face_array.shape[1] != 3 or face_array.dtype.kind not in "iu":
        raise SceneFileError(
            f"{path}: expected integer triangles, got faces of shape {face_array.shape} "
            f"and dtype {face_array.dtype}"
        )
    if vertex_array.ndim != 2 or vertex_array.shape[1] != 3 or vertex_array.dtype.kind not in "fiu":
        raise SceneFileError(
            f"{path}: expected (V, 3) vertex positions, got shape {vertex_array.shape} "
            f"and dtype {vertex_array.dtype}"
        )
    xyz = check_vertices(vertex_array.astype(np.float64), str(path))
    index = face_array.astype(np.int64).reshape(-1)
    check_polygons(np.full(face_array.shape[0], 3, dtype=np.int64), index, xyz.shape[0], str(path))
    return xyz, index.reshape(-1, 3)


def _glb_document(data: bytes, path: Path) -> dict[str, Any]:
    """Check a GLB container (header, chunk lengths) and return its JSON chunk."""
    if len(data) < 20 or data[:4] != b"glTF":
        raise SceneFileError(
            f"{path}: not a GLB file (it does not start with the magic 'glTF' and a 12-byte "
            f"header; {len(data)} bytes)"
        )
    version = int.from_bytes(data[4:8], "little")
    length = int.from_bytes(data[8:12], "little")
    if version != 2:
        raise SceneFileError(f"{path}: GLB version {version} is not supported (only 2)")
    if length != len(data):
        raise SceneFileError(
            f"{path}: the GLB header declares {length} bytes but the file has {len(data)}"
        )
    offset = 12
    document: dict[str, Any] | None = None
    while offset < len(data):
        if offset + 8 > len(data):
            raise SceneFileError(f"{path}: byte {offset}: GLB chunk header cut short")
        size = int.from_bytes(data[offset : offset + 4], "little")
        kind = data[offset + 4 : offset + 8]
        if offset + 8 + size > len(data):
            raise SceneFileError(
                f"{path}: byte {offset}: GLB chunk declares {size} bytes but only "
                f"{len(data) - offset - 8} remain"
            )
        if document is None:
            if kind != b"JSON":
                raise SceneFileError(f"{path}: byte {offset}: the first GLB chunk is not JSON")
            document = _json_document(data[offset + 8 : offset + 8 + size], path)
        offset += 8 + size
    if document is None:
        raise SceneFileError(f"{path}: the GLB file has no JSON chunk")
    return document


def _json_document(data: bytes, path: Path) -> dict[str, Any]:
    """Parse glTF JSON, which must be an object."""
    try:
        document = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise SceneFileError(f"{path}: glTF JSON is not UTF-8 (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise SceneFileError(
            f"{path}: invalid JSON at line {exc.lineno} column {exc.colno} ({exc.msg})"
        ) from None
    except (ValueError, RecursionError) as exc:
        raise SceneFileError(f"{path}: invalid JSON ({type(exc).__name__}: {exc})") from None
    if not isinstance(document, dict):
        raise SceneFileError(
            f"{path}: expected a JSON object at the top level, got {type(document).__name__}"
        )
    return document


def _check_buffers(document: dict[str, Any], path: Path, limit: int) -> int:
    """Refuse external buffers that are missing, outside the file's folder or too large.

    Returns the bytes the external buffer files hold together.
    """
    buffers = document.get("buffers", [])
    if not isinstance(buffers, list):
        raise SceneFileError(f"{path}: 'buffers' must be a JSON list")
    folder = path.parent.resolve()
    total = 0
    for number, buffer in enumerate(buffers):
        if not isinstance(buffer, dict):
            raise SceneFileError(f"{path}: buffer {number} is not a JSON object")
        uri = buffer.get("uri")
        if uri is None or (isinstance(uri, str) and uri.startswith("data:")):
            continue
        if not isinstance(uri, str):
            raise SceneFileError(f"{path}: buffer {number}'s uri is not a string")
        shown = repr(uri[:200])
        try:
            target = (folder / urllib.parse.unquote(uri)).resolve()
            if not target.is_relative_to(folder):
                raise SceneFileError(
                    f"{path}: buffer {number} refers to {shown}, outside the file's folder"
                )
            if not target.is_file():
                raise SceneFileError(f"{path}: buffer {number} refers to {shown}, not a file")
            total += target.stat().st_size
        except (OSError, ValueError) as exc:  # a NUL byte, a name too long, ...
            if isinstance(exc, SceneFileError):
                raise
            raise SceneFileError(
                f"{path}: buffer {number} refers to {shown}, which cannot be read ({exc})"
            ) from exc
        if total > limit:
            raise SceneFileError(
                f"{path}: its buffers hold more than {limit} bytes, the limit on scene files "
                f"(max_bytes, {MAX_SCENE_BYTES_VAR})"
            )
    return total


#: Deepest glTF node hierarchy accepted: trimesh's scene graph takes time cubic in
#: the depth (a chain of 300 nodes takes 0.7 s, of 1000 nodes 12 s).
MAX_GLTF_DEPTH = 256


def _check_nodes(document: dict[str, Any], path: Path) -> None:
    """Refuse node hierarchies that are not disjoint trees or deeper than MAX_GLTF_DEPTH.

    The glTF 2.0 specification requires disjoint strict trees (a node has at most one
    parent); cycles or shared children would multiply instances, and depth costs
    trimesh cubic time.
    """
    nodes = document.get("nodes", [])
    if not isinstance(nodes, list) or not all(isinstance(n, dict) for n in nodes):
        raise SceneFileError(f"{path}: 'nodes' must be a JSON list of objects")
    parent = [-1] * len(nodes)
    for i, node in enumerate(nodes):
        children = node.get("children", [])
        if not isinstance(children, list):
            raise SceneFileError(f"{path}: node {i}: 'children' must be a JSON list")
        for child in children:
            if isinstance(child, bool) or not isinstance(child, int):
                raise SceneFileError(f"{path}: node {i}: child {child!r} is not a node index")
            if not 0 <= child < len(nodes):
                raise SceneFileError(f"{path}: node {i}: child {child} of {len(nodes)} nodes")
            if parent[child] != -1 or child == i:
                raise SceneFileError(
                    f"{path}: node {child} has more than one parent (or is its own child); "
                    "glTF node hierarchies must be disjoint trees"
                )
            parent[child] = i
    depth = [0] * len(nodes)
    stack = [i for i in range(len(nodes)) if parent[i] == -1]
    reached = 0
    while stack:
        i = stack.pop()
        reached += 1
        if depth[i] > MAX_GLTF_DEPTH:
            raise SceneFileError(
                f"{path}: node {i} lies {depth[i]} levels deep; at most {MAX_GLTF_DEPTH} are read"
            )
        for child in nodes[i].get("children", []):
            depth[child] = depth[i] + 1
            stack.append(child)
    if reached != len(nodes):
        raise SceneFileError(f"{path}: the node hierarchy has a cycle")


_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_TYPE_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def _check_accessors(document: dict[str, Any], path: Path, available: int) -> None:
    """Refuse accessors that reach past their buffer view, and views past their buffer.

    An accessor without a buffer view stands for zeros; it may not declare more bytes
    than the file and its buffers hold (``available``), so it cannot make the reader
    allocate beyond what the data could describe.
    """

    def items(key: str) -> list[Any]:
        value = document.get(key, [])
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise SceneFileError(f"{path}: {key!r} must be a JSON list of objects")
        return value

    def number(owner: str, entry: dict[str, Any], key: str, default: int | None = None) -> int:
        value = entry.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise SceneFileError(f"{path}: {owner}: {key!r} must be a non-negative integer")
        return value

    buffers, views = items("buffers"), items("bufferViews")
    for i, view in enumerate(views):
        owner = f"bufferView {i}"
        j = number(owner, view, "buffer")
        end = number(owner, view, "byteOffset", 0) + number(owner, view, "byteLength")
        if j >= len(buffers):
            raise SceneFileError(f"{path}: {owner} refers to buffer {j} of {len(buffers)}")
        if end > number(f"buffer {j}", buffers[j], "byteLength"):
            raise SceneFileError(
                f"{path}: {owner} ends at byte {end}, past the end of buffer {j} "
                f"({buffers[j]['byteLength']} bytes)"
            )
    for i, accessor in enumerate(items("accessors")):
        owner = f"accessor {i}"
        count = number(owner, accessor, "count")
        kind, shape = accessor.get("componentType"), accessor.get("type")
        component = _COMPONENT_BYTES.get(kind) if isinstance(kind, int) else None
        width = _TYPE_COMPONENTS.get(shape) if isinstance(shape, str) else None
        if component is None or width is None:
            raise SceneFileError(f"{path}: {owner} has an unknown componentType or type")
        size = component * width
        if "bufferView" not in accessor:
            if count * size > available:
                raise SceneFileError(
                    f"{path}: {owner} has no bufferView and declares {count} elements "
                    f"({count * size} bytes), more than the file and its buffers hold "
                    f"({available} bytes)"
                )
            continue
        if count == 0:
            continue
        j = number(owner, accessor, "bufferView")
        if j >= len(views):
            raise SceneFileError(f"{path}: {owner} refers to bufferView {j} of {len(views)}")
        stride = number(f"bufferView {j}", views[j], "byteStride", 0) or size
        need = number(owner, accessor, "byteOffset", 0) + stride * (count - 1) + size
        if need > views[j]["byteLength"]:
            raise SceneFileError(
                f"{path}: {owner} declares {count} elements ({need} bytes) but its bufferView "
                f"{j} holds {views[j]['byteLength']} bytes"
            )


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


__all__ = [
    "DEFAULT_MAX_SCENE_BYTES",
    "MAX_SCENE_BYTES_VAR",
    "MESH_SUFFIXES",
    "SUPPORTED_SUFFIXES",
    "load_mesh",
    "parse_obj",
    "scene_stem",
]
