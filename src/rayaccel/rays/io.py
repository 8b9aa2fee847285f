"""Ray-set files: a :class:`~rayaccel.rays.batch.RayBatch` saved as an ``.npz`` archive.

Recorded ray sets (primary, diffuse, shadow rays of a render) let benchmarks replay
exactly the same queries across structures, runs and machines. The format is a
plain, uncompressed numpy ``.npz`` archive with five members:

========== ============ ===========================================
member     dtype        shape / content
========== ============ ===========================================
origin     float32      ``(n, 3)``
direction  float32      ``(n, 3)``
tmin       float32      ``(n,)``
tmax       float32      ``(n,)``
metadata   unicode      ``()``: a JSON object (scene, camera, seed...)
========== ============ ===========================================

Arrays are stored bit for bit, so a round trip reproduces the batch exactly.
Files load with ``allow_pickle=False``. Saving is atomic: the archive is written
to a temporary file in the destination directory, flushed and ``fsync``-ed, then
moved over the destination with :func:`os.replace`; a crash or an error mid-write
leaves any previous file untouched and no temporary file behind.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from rayaccel._atomic import write_bytes_atomic
from rayaccel._docstrings import with_sections
from rayaccel.dtypes import REAL
from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.rays.batch import RayBatch

#: Members of a ray-set archive.
RAY_FILE_KEYS = ("origin", "direction", "tmin", "tmax", "metadata")

_SHAPES = {"origin": 2, "direction": 2, "tmin": 1, "tmax": 1}


def json_default(value: object) -> Any:
    """Convert numpy scalars and arrays, paths, tuples and sets for ``json.dumps``."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (Path, os.PathLike)):
        return os.fspath(value)
    if isinstance(value, (tuple, set, frozenset)):
        return list(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _encode_metadata(metadata: dict[str, object]) -> str:
    try:
        return json.dumps(metadata, default=json_default, sort_keys=True, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"metadata: expected JSON-serialisable values ({exc})") from exc


def save_rays(path: str | os.PathLike[str], rays: RayBatch, **metadata: object) -> Path:
    """Write a ray batch and its metadata to an ``.npz`` file atomically.

    Parameters
    ----------
    path : str or path-like
        Destination, used as given (no suffix is appended; ``.npz`` is
        conventional). Its directory must exist. An existing file is replaced.
    rays : RayBatch
        The rays to store (float32 arrays, saved bit for bit).
    **metadata
        JSON-serialisable values describing the set (numpy scalars and arrays
        are converted to Python numbers and lists).

    Returns
    -------
    pathlib.Path
        The written path.

    Raises
    ------
    InvalidInputError
        If ``rays`` is not a :class:`RayBatch` or ``metadata`` is not
        JSON-serialisable.
    OSError
        If the file cannot be written; the destination is then unchanged.
    """
    if not isinstance(rays, RayBatch):
        raise InvalidInputError(f"rays: expected a RayBatch, got {type(rays).__name__}")
    text = _encode_metadata(metadata)
    buffer = io.BytesIO()
    np.savez(
        buffer,
        origin=rays.origin,
        direction=rays.direction,
        tmin=rays.tmin,
        tmax=rays.tmax,
        metadata=np.array(text),
    )
    return write_bytes_atomic(path, buffer.getvalue())


def _read_members(path: Path) -> dict[str, np.ndarray]:
    try:
        loaded = np.load(path, allow_pickle=False)
    except FileNotFoundError as exc:
        raise SceneFileError(f"{path}: no such ray-set file") from exc
    except IsADirectoryError as exc:
        raise SceneFileError(f"{path}: is a directory, expected a ray-set file") from exc
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise SceneFileError(f"{path}: cannot read ray-set archive ({exc})") from exc
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise SceneFileError(f"{path}: expected an .npz ray-set archive, got a single array")
    with loaded as archive:
        keys = set(archive.files)
        missing = sorted(set(RAY_FILE_KEYS) - keys)
        unknown = sorted(keys - set(RAY_FILE_KEYS))
        if missing or unknown:
            raise SceneFileError(
                f"{path}: not a ray-set archive; missing members {missing}, "
                f"unexpected members {unknown}, expected {list(RAY_FILE_KEYS)}"
            )
        try:
            return {key: archive[key] for key in RAY_FILE_KEYS}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise SceneFileError(f"{path}: cannot read ray-set archive ({exc})") from exc


def _parse_metadata(path: Path, member: np.ndarray) -> dict[str, Any]:
    if member.shape != () or member.dtype.kind != "U":
        raise SceneFileError(
            f"{path}: metadata must be a unicode scalar, got {member.dtype} {member.shape}"
        )
    try:
        value = json.loads(str(member))
    except json.JSONDecodeError as exc:
        raise SceneFileError(f"{path}: metadata is not valid JSON ({exc})") from exc
    if not isinstance(value, dict):
        raise SceneFileError(f"{path}: metadata must be a JSON object, got {type(value).__name__}")
    return value


#: The parameter of the ray-set readers.
_PATH_PARAMETER = """\
Parameters
----------
path : str or path-like
    The ``.npz`` ray-set file.
"""


@with_sections(_PATH_PARAMETER)
def load_rays(path: str | os.PathLike[str]) -> RayBatch:
    """Read a ray batch written by :func:`save_rays`.

    Returns
    -------
    RayBatch
        Bit-identical to the saved batch.

    Raises
    ------
    SceneFileError
        Naming ``path``, if the file is missing or unreadable, lacks a member or
        has extra ones, or a member has the wrong dtype (float32 required) or
        shape, row counts disagree, or ``tmin`` contains NaN.
    """
    source = Path(path)
    members = _read_members(source)
    _parse_metadata(source, members["metadata"])
    n_rays = None
    for key, ndim in _SHAPES.items():
        array = members[key]
        if array.dtype != REAL:
            raise SceneFileError(f"{source}: member {key!r} must be float32, got {array.dtype}")
        expected = "(n, 3)" if ndim == 2 else "(n,)"
        if array.ndim != ndim or (ndim == 2 and array.shape[1] != 3):
            raise SceneFileError(
                f"{source}: member {key!r} must have shape {expected}, got {array.shape}"
            )
        if n_rays is None:
            n_rays = array.shape[0]
        elif array.shape[0] != n_rays:
            raise SceneFileError(
                f"{source}: member {key!r} has {array.shape[0]} rows, origin has {n_rays}"
            )
    try:
        return RayBatch(members["origin"], members["direction"], members["tmin"], members["tmax"])
    except InvalidInputError as exc:
        raise SceneFileError(f"{source}: invalid ray set ({exc})") from exc


@with_sections(_PATH_PARAMETER)
def load_ray_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read the metadata stored by :func:`save_rays`.

    Returns
    -------
    dict
        The keyword arguments given to :func:`save_rays`, as decoded JSON
        (tuples come back as lists).

    Raises
    ------
    SceneFileError
        Naming ``path``, if the file is missing, unreadable, not a ray-set
        archive, or its metadata is not a JSON object.
    """
    source = Path(path)
    return _parse_metadata(source, _read_members(source)["metadata"])
