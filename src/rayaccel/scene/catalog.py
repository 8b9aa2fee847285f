"""Named scenes: procedural ones built in, file scenes found on a search path.

``get("teapot")`` builds a procedural scene (parameters pass through:
``get("sphereflake", level=3)``); ``get("kitchen")`` loads the first file whose
name without suffix matches, from the folders listed in ``RAYACCEL_SCENE_PATH``
(``os.pathsep``-separated) followed by any ``search_path`` argument. Matching is
exact first, then ignoring case and treating ``-`` and ``_`` alike
(``living-room`` finds ``living_room.ply``); a few aliases name the shared
benchmark scenes (``bunny``, ``sponza``, ``bathroom``). A name that is the path of
an existing file loads that file. Scenes downloaded by :func:`fetch` (``rayaccel
scenes fetch NAME``) are found by their catalog name after the search path. Unknown
names raise :class:`~rayaccel.errors.UnknownVariantError` with close matches.

Loaded meshes are cached per process (LRU, keyed by resolved path, size and
modification time) because the large scenes take seconds to parse; meshes are
immutable, so sharing them is safe. :func:`camera_preset` holds hand-placed
pinhole cameras for the interior scenes, each inside the room and looking at
furniture, so that nearly every primary ray and diffuse bounce hits something.
"""

from __future__ import annotations

import difflib
import functools
import inspect
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from rayaccel.config import SCENE_PATH_VAR
from rayaccel.errors import InvalidInputError, SceneFileError, UnknownVariantError
from rayaccel.scene import procedural
from rayaccel.scene.fetch import fetch, fetched_scenes, remote_status
from rayaccel.scene.io import SUPPORTED_SUFFIXES, load_mesh, scene_stem
from rayaccel.scene.mesh import TriangleMesh

PathList = Sequence[str | os.PathLike[str]] | str | os.PathLike[str] | None

#: The scene used when none is named: procedural, so it needs no files (4,096 triangles).
DEFAULT_SCENE = "teapot"

_PROCEDURAL: dict[str, Callable[..., TriangleMesh]] = {
    "cornell-box": procedural.cornell_box,
    "soup": procedural.triangle_soup,
    "sphereflake": procedural.sphereflake,
    "teapot": procedural.teapot,
    "teapot-in-stadium": procedural.teapot_in_stadium,
}

#: Friendly names of the shared benchmark scenes -> file stem.
ALIASES: dict[str, str] = {
    "bunny": "stanford-bunny",
    "sponza": "sponza_dabrovic",
    "living-room": "living_room",
    "salle-de-bain": "salle_de_bain",
    "bathroom": "salle_de_bain",
    "cornell-box-original": "CornellBox-Original",
}

# Up axis of every known scene, for describe() and camera code.
_UP_AXIS: dict[str, str] = {
    "cornell-box": "+y",
    "soup": "none",
    "sphereflake": "+z",
    "teapot": "+z",
    "teapot-in-stadium": "+z",
    "CornellBox-Original": "+y",
    "stanford-bunny": "+y",
    "staircase": "+y",
    "living_room": "+y",
    "kitchen": "+y",
    "salle_de_bain": "+y",
    "sponza_dabrovic": "+z",
}

# Pinhole cameras (vertical field of view) placed by inspecting each scene. Interior
# presets keep the eye inside the room; tests/scene/test_catalog.py checks that at
# least 95% of a 64x64 grid of primary rays hits geometry.
_CAMERA_PRESETS: dict[str, dict[str, Any]] = {
    "cornell-box": {
        "eye": (278.0, 273.0, 20.0),
        "target": (278.0, 273.0, 559.2),
        "up": (0.0, 1.0, 0.0),
        "fov_deg": 55.0,
    },
    "CornellBox-Original": {
        "eye": (0.0, 1.0, 0.95),
        "target": (0.0, 1.0, -1.0),
        "up": (0.0, 1.0, 0.0),
        "fov_deg": 55.0,
    },
    "staircase": {  # Bitterli's view through the arch: stairs, chair and lamp
        "eye": (0.03, 1.53, 4.88),
        "target": (-0.01, 1.75, -0.12),
        "up": (0.0, 1.0, 0.0),
        "fov_deg": 50.0,
    },
    "living_room": {  # sofa, side table and bottles, windows out of view
        "eye": (3.6, 1.3, -0.6),
        "target": (2.1, 0.7, -3.0),
        "up": (0.0, 1.0, 0.0),
        "fov_deg": 55.0,
    },
    "kitchen": {  # Bitterli's view: island, cooker, hood and dining table
        "eye": (1.21, 1.8, 3.85),
        "target": (-0.98, 1.6, -0.64),
        "up": (0.0, 1.0, 0.0),
        "fov_deg": 45.0,
    },
    "salle_de_bain": {  # the Mitsuba scene's view: bathtub, basin and mirror
        "eye": (-11.91, 4.43, 9.44),
        "target": (-3.52, 3.82, 4.04),
        "up": (0.0, 1.0, 0.0),
        "fov_deg": 55.0,
    },
    "sponza_dabrovic": {  # down the atrium's long axis at head height (Z up)
        "eye": (-12.0, 0.0, 2.0),
        "target": (0.0, 0.0, 2.0),
        "up": (0.0, 0.0, 1.0),
        "fov_deg": 55.0,
    },
    "sphereflake": {
        "eye": (2.1, 1.3, 1.7),
        "target": (0.0, 0.0, 0.0),
        "up": (0.0, 0.0, 1.0),
        "fov_deg": 45.0,
    },
    "teapot": {
        "eye": (7.0, -8.5, 5.5),
        "target": (0.2, 0.0, 1.4),
        "up": (0.0, 0.0, 1.0),
        "fov_deg": 35.0,
    },
    "teapot-in-stadium": {
        "eye": (7.0, -8.5, 5.5),
        "target": (0.2, 0.0, 1.4),
        "up": (0.0, 0.0, 1.0),
        "fov_deg": 50.0,
    },
}


@dataclass(frozen=True, slots=True)
class SceneInfo:
    """One entry of :func:`describe`.

    Attributes
    ----------
    name : str
        The name :func:`get` accepts.
    kind : {"procedural", "file"}
        Built in code, or found on the search path.
    summary : str
        First line of the builder's docstring, or the file name.
    up : str
        World up axis (``"+y"``, ``"+z"``, ``"none"`` or ``"?"`` if unknown).
    path : pathlib.Path or None
        The file of a file scene.
    """

    name: str
    kind: Literal["procedural", "file"]
    summary: str
    up: str
    path: Path | None = None


def _normalise(name: str) -> str:
    return name.strip().lower().replace("_", "-")


def search_folders(extra: PathList = None) -> list[Path]:
    """Return the folders searched for file scenes, in order.

    Parameters
    ----------
    extra : path-like, str or sequence of them, optional
        Folders searched after ``RAYACCEL_SCENE_PATH``. A single string may hold
        several folders separated by ``os.pathsep``.

    Returns
    -------
    list of pathlib.Path
        Existing folders only, duplicates removed, environment first.
    """
    entries: list[str] = os.environ.get(SCENE_PATH_VAR, "").split(os.pathsep)
    if isinstance(extra, (str, os.PathLike)):
        entries.extend(os.fspath(extra).split(os.pathsep))
    elif extra is not None:
        entries.extend(os.fspath(entry) for entry in extra)
    folders: list[Path] = []
    for entry in entries:
        if not entry:
            continue
        folder = Path(entry).expanduser()
        if folder.is_dir() and folder.resolve() not in {f.resolve() for f in folders}:
            folders.append(folder)
    return folders


def _scene_files(folder: Path) -> Iterable[Path]:
    try:
        children = sorted(folder.iterdir())
    except OSError:
        return []
    return [
        child
        for child in children
        if child.name.lower().endswith(SUPPORTED_SUFFIXES) and child.is_file()
    ]


def file_scenes(search_path: PathList = None) -> dict[str, Path]:
    """Return the file scenes found on the search path, ``name -> path``.

    Parameters
    ----------
    search_path : path-like or sequence, optional
        Extra folders after ``RAYACCEL_SCENE_PATH`` (see :func:`search_folders`).

    Returns
    -------
    dict of str to pathlib.Path
        Names are file names without suffix; the first folder on the path wins,
        and within a folder the first suffix in
        :data:`~rayaccel.scene.io.SUPPORTED_SUFFIXES` order.
    """
    found: dict[str, Path] = {}
    rank = {suffix: i for i, suffix in enumerate(SUPPORTED_SUFFIXES)}
    for folder in search_folders(search_path):
        candidates: dict[str, tuple[int, Path]] = {}
        for path in _scene_files(folder):
            stem = scene_stem(path)
            suffix = path.name[len(stem) :].lower()
            order = rank.get(suffix, len(rank))
            if stem not in candidates or order < candidates[stem][0]:
                candidates[stem] = (order, path)
        for stem, (_, path) in sorted(candidates.items()):
            found.setdefault(stem, path)
    return found


def names(search_path: PathList = None) -> list[str]:
    """Return every scene name :func:`get` accepts, procedural ones first.

    Parameters
    ----------
    search_path : path-like or sequence, optional
        Extra folders after ``RAYACCEL_SCENE_PATH``.

    Returns
    -------
    list of str
        The procedural names, then the file scenes found, then the fetched scenes
        that no file on the search path shadows (aliases not listed).
    """
    files = [name for name in file_scenes(search_path) if name not in _PROCEDURAL]
    fetched = [name for name in _fetched(files) if name not in _PROCEDURAL]
    return [*_PROCEDURAL, *files, *fetched]


def _fetched(files: Iterable[str]) -> dict[str, Path]:
    """Return the fetched scenes whose names no file scene in ``files`` takes."""
    taken = {_normalise(ALIASES.get(_normalise(name), name)) for name in files}
    return {
        name: path
        for name, path in fetched_scenes().items()
        if _normalise(ALIASES.get(_normalise(name), name)) not in taken
    }


def describe(search_path: PathList = None) -> list[SceneInfo]:
    """Return one :class:`SceneInfo` per available scene, in :func:`names` order.

    Parameters
    ----------
    search_path : path-like or sequence, optional
        Extra folders after ``RAYACCEL_SCENE_PATH``.

    Returns
    -------
    list of SceneInfo
    """
    infos = []
    for name, builder in _PROCEDURAL.items():
        summary = (inspect.getdoc(builder) or "").splitlines()[0]
        infos.append(SceneInfo(name, "procedural", summary, _UP_AXIS.get(name, "?")))
    files = file_scenes(search_path)
    for name, path in files.items():
        if name not in _PROCEDURAL:
            infos.append(SceneInfo(name, "file", path.name, _UP_AXIS.get(name, "?"), path))
    remote = {status.scene.name: status.scene for status in remote_status()}
    for name, path in _fetched(files).items():
        if name not in _PROCEDURAL:
            scene = remote[name]
            summary = f"{scene.title} (fetched: {path.name})"
            infos.append(SceneInfo(name, "file", summary, scene.up, path))
    return infos


def resolve(name: str, search_path: PathList = None) -> str | Path:
    """Return the procedural name or the file a scene name refers to.

    Parameters
    ----------
    name : str
        A procedural name, a file scene name or alias, or a path to a file.
    search_path : path-like or sequence, optional
        Extra folders after ``RAYACCEL_SCENE_PATH``.

    Returns
    -------
    str or pathlib.Path
        The canonical procedural name, or the path of the scene file.

    Raises
    ------
    UnknownVariantError
        No scene has that name; the message lists close matches and the search path.
    SceneFileError
        ``name`` looks like a path (it has a folder part) but no file is there.
    """
    if not isinstance(name, str):
        raise InvalidInputError(f"name: expected a scene name (str), got {name!r}")
    key = _normalise(name)
    for procedural_name in _PROCEDURAL:
        if key == procedural_name:
            return procedural_name
    candidate = Path(name).expanduser()
    if candidate.is_file():
        return candidate
    files = file_scenes(search_path)
    wanted = ALIASES.get(key, name)
    if wanted in files:
        return files[wanted]
    by_key = {_normalise(stem): path for stem, path in reversed(list(files.items()))}
    for probe in (_normalise(wanted), _normalise(scene_stem(name))):
        if probe in by_key:
            return by_key[probe]
    if os.sep in name or (os.altsep and os.altsep in name):
        raise SceneFileError(f"{name}: no such file")
    remote = {_normalise(status.scene.name): status for status in remote_status()}
    for probe in (key, _normalise(wanted)):
        if probe in remote:
            status = remote[probe]
            if status.path is not None:
                return status.path
            raise UnknownVariantError(
                f"scene {name!r} is downloadable but not fetched yet; run 'rayaccel scenes "
                f"fetch {status.scene.name}' or rayaccel.scenes.fetch({status.scene.name!r})"
            )
    choices = [*_PROCEDURAL, *files, *ALIASES, *(s.scene.name for s in remote.values())]
    close = difflib.get_close_matches(name, choices, n=3, cutoff=0.5)
    close += [c for c in difflib.get_close_matches(key, choices, n=3, cutoff=0.5) if c not in close]
    hint = f"did you mean {', '.join(map(repr, close))}? " if close else ""
    folders = search_folders(search_path)
    where = os.pathsep.join(map(str, folders)) if folders else "nothing"
    raise UnknownVariantError(
        f"unknown scene {name!r}; {hint}procedural scenes: {', '.join(_PROCEDURAL)}; "
        f"file scenes are looked up in {SCENE_PATH_VAR} (searched: {where}); "
        "'rayaccel scenes list --remote' shows the scenes that can be downloaded"
    )


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, size: int, mtime_ns: int) -> TriangleMesh:
    del size, mtime_ns  # part of the cache key only
    return load_mesh(path)


def load_cached(path: str | os.PathLike[str]) -> TriangleMesh:
    """Load a scene file through the per-process LRU cache (8 entries).

    Parameters
    ----------
    path : str or path-like
        The scene file.

    Returns
    -------
    TriangleMesh
        The cached mesh while the file's resolved path, size and modification
        time are unchanged; otherwise a fresh load.

    Raises
    ------
    SceneFileError
        As :func:`~rayaccel.scene.io.load_mesh`.
    """
    resolved = Path(path).expanduser().resolve()
    try:
        stat = resolved.stat()
    except OSError as exc:
        raise SceneFileError(f"{path}: no such file ({exc.strerror})") from exc
    return _load_cached(str(resolved), stat.st_size, stat.st_mtime_ns)


def clear_cache() -> None:
    """Forget every cached file and procedural mesh."""
    _load_cached.cache_clear()
    _build_cached.cache_clear()


@functools.lru_cache(maxsize=16)
def _build_cached(name: str, params: tuple[tuple[str, Any], ...]) -> TriangleMesh:
    return _PROCEDURAL[name](**dict(params))


def _check_params(name: str, params: dict[str, Any]) -> None:
    signature = inspect.signature(_PROCEDURAL[name])
    allowed = list(signature.parameters)
    for key in params:
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=2)
            hint = f"; did you mean {', '.join(map(repr, close))}?" if close else ""
            raise UnknownVariantError(
                f"scene {name!r} has no parameter {key!r} (parameters: {', '.join(allowed)}){hint}"
            )


def get(name: str = DEFAULT_SCENE, *, search_path: PathList = None, **params: Any) -> TriangleMesh:
    """Return the scene called ``name``.

    Parameters
    ----------
    name : str
        A procedural scene (``"cornell-box"``, ``"soup"``, ``"sphereflake"``,
        ``"teapot"``, ``"teapot-in-stadium"``), a file scene found on the search
        path (``"kitchen"`` -> ``kitchen.ply.gz``) or one of :data:`ALIASES`, or
        a path to a scene file. Default :data:`DEFAULT_SCENE`.
    search_path : path-like or sequence, optional
        Folders searched after ``RAYACCEL_SCENE_PATH``.
    **params
        Passed to a procedural builder, e.g. ``level=3`` for ``"sphereflake"``.

    Returns
    -------
    TriangleMesh
        Shared, immutable, possibly cached.

    Raises
    ------
    UnknownVariantError
        Unknown scene name, or a parameter the builder does not take.
    InvalidInputError
        Parameters given for a file scene, or invalid parameter values.
    SceneFileError
        A scene file is missing or malformed.
    """
    target = resolve(name, search_path)
    if isinstance(target, Path):
        if params:
            raise InvalidInputError(
                f"scene {name!r} is a file ({target.name}); it takes no parameters, "
                f"got {sorted(params)}"
            )
        return load_cached(target)
    _check_params(target, params)
    try:
        return _build_cached(target, tuple(sorted(params.items())))
    except TypeError:  # an unhashable parameter value: build without the cache
        return _PROCEDURAL[target](**params)


def camera_preset(name: str) -> dict[str, Any] | None:
    """Return the stored pinhole camera of a scene, or ``None`` if it has none.

    Parameters
    ----------
    name : str
        A scene name or alias, as for :func:`get` (no file lookup is made).

    Returns
    -------
    dict or None
        A fresh dict ``{"eye": (x, y, z), "target": (x, y, z), "up": (x, y, z),
        "fov_deg": float}``; ``fov_deg`` is the vertical field of view. For
        the interior scenes (``staircase``, ``living_room``, ``kitchen``,
        ``salle_de_bain``, ``sponza_dabrovic``, ``cornell-box``,
        ``CornellBox-Original``) the eye is inside the room, so at least 95% of
        primary rays hit.
    """
    key = _normalise(name)
    stem = scene_stem(name)
    wanted = ALIASES.get(key, stem)
    for preset_name, preset in _CAMERA_PRESETS.items():
        if _normalise(preset_name) in (key, _normalise(wanted)):
            return dict(preset)
    return None


__all__ = [
    "ALIASES",
    "DEFAULT_SCENE",
    "SceneInfo",
    "camera_preset",
    "clear_cache",
    "describe",
    "fetch",
    "file_scenes",
    "get",
    "load_cached",
    "names",
    "remote_status",
    "resolve",
    "search_folders",
]
