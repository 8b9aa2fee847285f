"""Saving a built structure to a file and loading it back, never trusting the file.

A saved accel is one ``.npz`` archive (numpy's zip of ``.npy`` arrays), written
atomically (:mod:`rayaccel._atomic`) and read with ``allow_pickle=False``, so loading
never runs code from the file. It holds:

- ``header``: UTF-8 JSON (stored as a uint8 array) with the format name and
  :data:`FORMAT_VERSION`, the rayaccel version that wrote it, the builder key and
  its options (and each build step's), the build and step times, the SAH cost at
  build time, the mesh's name, size and precision, the structure's class with every field
  (arrays by name, dtype and shape; scalars and small dicts by value; nested
  structures recursively), and a SHA-256 content hash;
- ``mesh.vertices`` (float64 for a float64 mesh), ``mesh.faces`` and one array per
  array field of the structure
  (``structure.node_lo``, ``structure.top.cell_start`` …).

The structure is taken apart by dataclass introspection, so every structure class of
every family is saved by the same code, but only the classes in
:data:`STRUCTURE_CLASSES` are ever instantiated on load. Loading checks, in order:
the file exists and is an npz archive with a header; the format name and version;
the class is allowed and its fields are exactly the ones this rayaccel defines (a
layout change between versions is refused rather than misread); every array is
present with the dtype and shape the header gives; the hash over the header and every
array (so an edited header, a flipped byte or a swapped array is refused); and
finally the mesh's own validation and the structure's ``validate()`` against the
mesh's triangles. Any failure raises :class:`rayaccel.errors.AccelFileError` naming
the file and what is wrong.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rayaccel._atomic import write_bytes_atomic
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.errors import AccelFileError, RayAccelError, StructureInvariantError
from rayaccel.grid.layouts.irregular import IrregularGrid
from rayaccel.grid.layouts.two_level import TwoLevelGrid
from rayaccel.grid.layouts.uniform import UniformGrid
from rayaccel.kdtree.layouts.kdtree import KdTree
from rayaccel.rays.io import json_default
from rayaccel.scene.mesh import TriangleMesh

#: The ``format`` field of every header.
FORMAT = "rayaccel.accel"
#: Bumped whenever the file layout changes; files of another version are refused.
FORMAT_VERSION = 1
#: The header's entry in the archive.
HEADER = "header"

#: The only classes a file may name, with the structure name their builders register.
STRUCTURE_CLASSES: dict[str, tuple[type, str]] = {
    "Bvh2": (Bvh2, "bvh2"),
    "KdTree": (KdTree, "kdtree"),
    "UniformGrid": (UniformGrid, "grid"),
    "TwoLevelGrid": (TwoLevelGrid, "grid"),
    "IrregularGrid": (IrregularGrid, "grid"),
}

#: Array dtypes a file may hold (no objects, no records).
_DTYPES = frozenset(
    np.dtype(t).str for t in (np.float32, np.float64, np.int16, np.int32, np.int64, np.uint8)
)


@dataclass(frozen=True, slots=True)
class SavedAccel:
    """The parts of an accel read back from a file (:func:`load`).

    Attributes
    ----------
    key : str
        Builder key, with its steps.
    structure_name : str
        The structure name its builder registers (``"bvh2"``, ``"kdtree"``, ``"grid"``).
    mesh : TriangleMesh
    structure : object
        The canonical structure, validated against ``mesh``.
    options : dict
        The builder's options by name.
    step_options : dict of str to dict
        Each build step's options, by step name.
    build_ms : float
    step_ms : dict of str to float
    build_sah : float or None
        SAH cost at build time (None for structures without one).
    header : dict
        The whole header.
    """

    key: str
    structure_name: str
    mesh: TriangleMesh
    structure: Any
    options: dict[str, Any]
    step_options: dict[str, dict[str, Any]]
    build_ms: float
    step_ms: dict[str, float]
    build_sah: float | None
    header: dict[str, Any]


def rayaccel_version() -> str:
    """Return the installed rayaccel version (``"unknown"`` outside an installed package)."""
    try:
        return importlib.metadata.version("rayaccel")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def options_dict(options: Any) -> dict[str, Any]:
    """Return an options dataclass as ``{field: value}`` (the values are JSON scalars)."""
    if options is None:
        return {}
    return {f.name: getattr(options, f.name) for f in dataclasses.fields(options)}


def _flatten(structure: Any, prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """Take ``structure`` apart: add its arrays to ``arrays`` and return its layout entry."""
    name = type(structure).__name__
    known = STRUCTURE_CLASSES.get(name)
    if known is None or known[0] is not type(structure):
        raise AccelFileError(f"cannot save a {name}: not a known structure class")
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(known[0]):
        value = getattr(structure, f.name)
        where = f"{prefix}.{f.name}"
        if isinstance(value, np.ndarray):
            array = np.ascontiguousarray(value)
            if array.dtype.str not in _DTYPES:
                raise AccelFileError(f"cannot save {where}: dtype {array.dtype} is not allowed")
            arrays[where] = array
            fields[f.name] = {"array": where}
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            fields[f.name] = {"structure": _flatten(value, where, arrays)}
        else:
            # Scalars and small dicts (build phases, counts) go in the header by value.
            fields[f.name] = {"value": json.loads(json.dumps(value, default=json_default))}
    return {"class": name, "fields": fields}


def content_digest(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over the header (without its hash) and every array's name, dtype, shape, bytes."""
    h = hashlib.sha256()
    body = {k: v for k, v in header.items() if k != "sha256"}
    h.update(json.dumps(body, sort_keys=True, default=json_default).encode())
    for name in sorted(arrays):
        array = arrays[name]
        h.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
        h.update(np.ascontiguousarray(array).data)
    return h.hexdigest()


def save(
    path: str | os.PathLike[str],
    *,
    key: str,
    structure_name: str,
    mesh: TriangleMesh,
    structure: Any,
    options: Any,
    step_options: dict[str, Any],
    build_ms: float,
    step_ms: dict[str, float],
    build_sah: float | None,
) -> Path:
    """Write an accel's parts to ``path`` (atomically); return the path.

    Parameters
    ----------
    path : str or path-like
        The destination, written as given (no suffix is added).
    key, structure_name, mesh, structure, build_ms, step_ms, build_sah
        The accel's parts (see :class:`SavedAccel`).
    options : dataclass
        The builder's options.
    step_options : dict of str to dataclass
        Each build step's options by step name.

    Raises
    ------
    AccelFileError
        The structure is not of a known class.
    OSError
        The file cannot be written (the destination is then unchanged).
    """
    # A float64 mesh is saved with its float64 vertices (its float32 ones are their rounding).
    vertices = mesh.vertices if mesh.vertices64 is None else mesh.vertices64
    arrays: dict[str, np.ndarray] = {"mesh.vertices": vertices, "mesh.faces": mesh.faces}
    layout = _flatten(structure, "structure", arrays)
    header: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "rayaccel_version": rayaccel_version(),
        "numpy_version": np.__version__,
        "builder": key,
        "structure": structure_name,
        "options": options_dict(options),
        "step_options": {name: options_dict(o) for name, o in step_options.items()},
        "build_ms": float(build_ms),
        "step_ms": {k: float(v) for k, v in step_ms.items()},
        "build_sah": build_sah,
        "mesh": {
            "name": mesh.name,
            "n_vertices": mesh.n_vertices,
            "n_triangles": mesh.n_triangles,
            "precision": mesh.precision,
            "digest": mesh.digest(),
        },
        "layout": layout,
        "arrays": {
            name: {"dtype": a.dtype.str, "shape": list(a.shape)} for name, a in arrays.items()
        },
    }
    header = json.loads(json.dumps(header, default=json_default))
    header["sha256"] = content_digest(header, arrays)
    text = json.dumps(header, sort_keys=True, default=json_default).encode()
    buffer = io.BytesIO()
    members = {HEADER: np.frombuffer(text, dtype=np.uint8), **arrays}
    np.savez(buffer, allow_pickle=False, **members)
    return write_bytes_atomic(path, buffer.getvalue())


def _fail(path: Path, message: str) -> AccelFileError:
    return AccelFileError(f"{path}: {message}")


def _read_header(path: Path, archive: Any) -> dict[str, Any]:
    if HEADER not in archive.files:
        raise _fail(path, "not a rayaccel accel file (an npz archive without a header)")
    try:
        raw = archive[HEADER]
        header = json.loads(raw.tobytes().decode("utf-8"))
    except (ValueError, UnicodeDecodeError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise _fail(path, f"unreadable header ({exc}); the file is truncated or corrupt") from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise _fail(path, "not a rayaccel accel file (its header names no rayaccel format)")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise _fail(
            path,
            f"written in accel file format {version!r} (by rayaccel "
            f"{header.get('rayaccel_version', 'unknown')}); this rayaccel "
            f"({rayaccel_version()}) reads format {FORMAT_VERSION} only: rebuild the "
            "structure and save it again",
        )
    return header


def _read_arrays(path: Path, archive: Any, header: dict[str, Any]) -> dict[str, np.ndarray]:
    listed = header.get("arrays")
    if not isinstance(listed, dict):
        raise _fail(path, "the header lists no arrays")
    arrays: dict[str, np.ndarray] = {}
    for name, spec in listed.items():
        if name not in archive.files:
            raise _fail(path, f"array {name!r} is missing (the file is truncated or altered)")
        try:
            array = archive[name]
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise _fail(
                path, f"array {name!r} is unreadable ({exc}): truncated or corrupt"
            ) from exc
        if (
            not isinstance(spec, dict)
            or array.dtype.str not in _DTYPES
            or array.dtype.str != spec.get("dtype")
            or list(array.shape) != spec.get("shape")
        ):
            raise _fail(
                path,
                f"array {name!r} is {array.dtype} {array.shape}, but the header says {spec!r}",
            )
        arrays[name] = array
    extra = set(archive.files) - set(listed) - {HEADER}
    if extra:
        raise _fail(path, f"arrays not listed in the header: {sorted(extra)}")
    return arrays


def _rebuild(path: Path, entry: Any, arrays: dict[str, np.ndarray], where: str) -> Any:
    """Instantiate the structure ``entry`` describes (allowed classes only)."""
    if not isinstance(entry, dict):
        raise _fail(path, f"{where}: malformed layout entry")
    name = entry.get("class")
    if name not in STRUCTURE_CLASSES:
        raise _fail(
            path, f"{where}: unknown structure class {name!r} (known: {sorted(STRUCTURE_CLASSES)})"
        )
    cls = STRUCTURE_CLASSES[name][0]
    stored = entry.get("fields")
    expected = [f.name for f in dataclasses.fields(cls)]
    if not isinstance(stored, dict) or sorted(stored) != sorted(expected):
        have = sorted(stored) if isinstance(stored, dict) else stored
        raise _fail(
            path,
            f"{where}: the file's {name} has fields {have}, this rayaccel's has "
            f"{sorted(expected)} (written by another version)",
        )
    values: dict[str, Any] = {}
    for field_name in expected:
        spec = stored[field_name]
        if isinstance(spec, dict) and set(spec) == {"array"} and spec["array"] in arrays:
            values[field_name] = arrays[spec["array"]]
        elif isinstance(spec, dict) and set(spec) == {"structure"}:
            values[field_name] = _rebuild(path, spec["structure"], arrays, f"{where}.{field_name}")
        elif isinstance(spec, dict) and set(spec) == {"value"}:
            values[field_name] = spec["value"]
        else:
            raise _fail(path, f"{where}.{field_name}: malformed field entry {spec!r}")
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise _fail(path, f"{where}: cannot make a {name} ({exc})") from exc


def load(path: str | os.PathLike[str]) -> SavedAccel:
    """Read, check and validate an accel file written by :func:`save`.

    Raises
    ------
    AccelFileError
        Missing file, not an npz archive, no rayaccel header, another format version,
        unknown structure class or fields, missing, mistyped or tampered arrays (hash
        mismatch), a truncated file, or a structure that fails validation.
    """
    file = Path(path)
    if not file.is_file():
        raise _fail(file, "no such accel file")
    try:
        archive = np.load(file, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise _fail(file, f"not a rayaccel accel file ({exc})") from exc
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise _fail(file, "not a rayaccel accel file (a single .npy array, not an npz archive)")
    with archive:
        header = _read_header(file, archive)
        arrays = _read_arrays(file, archive, header)
    if header.get("sha256") != content_digest(header, arrays):
        raise _fail(file, "content hash mismatch: the file was altered or corrupted; refusing it")
    try:
        mesh_info = header["mesh"]
        mesh = TriangleMesh(
            arrays["mesh.vertices"],
            arrays["mesh.faces"],
            str(mesh_info["name"]),
            precision=str(mesh_info.get("precision", "float32")),
        )
        structure = _rebuild(file, header["layout"], arrays, "structure")
        class_name = header["layout"]["class"]
        structure_name = str(header["structure"])
        if STRUCTURE_CLASSES[class_name][1] != structure_name:
            raise _fail(file, f"a {class_name} is not a {structure_name!r} structure")
        structure.validate(mesh.triangles())
        build_sah = header.get("build_sah")
        saved = SavedAccel(
            key=str(header["builder"]),
            structure_name=structure_name,
            mesh=mesh,
            structure=structure,
            options=dict(header["options"]),
            step_options={str(k): dict(v) for k, v in header["step_options"].items()},
            build_ms=float(header["build_ms"]),
            step_ms={str(k): float(v) for k, v in header["step_ms"].items()},
            build_sah=None if build_sah is None else float(build_sah),
            header=header,
        )
    except AccelFileError:
        raise
    except StructureInvariantError as exc:
        raise _fail(file, f"the saved structure is invalid: {exc}") from exc
    except (RayAccelError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise _fail(file, f"malformed accel file ({type(exc).__name__}: {exc})") from exc
    return saved
