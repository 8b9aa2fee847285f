"""Download the standard benchmark scenes into a user cache, checked against known hashes.

:func:`fetch` downloads one entry of :data:`~rayaccel.scene.remote.REMOTE_SCENES` with
pooch, checks its SHA-256 before the file enters the cache (pooch writes to a temporary
file and moves it only when the hash matches, so a corrupted or substituted download
leaves nothing behind), unpacks archives with pooch's ``Unzip``/``Untar`` after checking
that no member would land outside the cache, and returns the scene file. A second call
finds the file in the cache and downloads nothing. Entries without a published hash
are refused unless the caller passes ``verify=False``: an unchecked download is never
trusted silently.

The cache is ``$RAYACCEL_CACHE_DIR`` when set, else pooch's ``os_cache("rayaccel")``
(``~/.cache/rayaccel`` on Linux). Downloads live in ``downloads/<key>/``, one folder per
URL, so entries that share an archive (San Miguel and its low-poly version) share one
download; scenes assembled from parts go to ``scenes/<name>.ply``.
:func:`fetched_scenes` lists what is cached, which is how ``rayaccel.scenes.get`` finds
fetched scenes by name.
"""

from __future__ import annotations

import difflib
import fnmatch
import hashlib
import os
import tarfile
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from rayaccel._atomic import write_bytes_atomic
from rayaccel.errors import InvalidInputError, SceneFileError, UnknownVariantError
from rayaccel.scene.io import SUPPORTED_SUFFIXES, load_mesh
from rayaccel.scene.remote import REMOTE_SCENES, RemoteScene

#: Environment variable naming the cache folder (default: pooch's ``os_cache("rayaccel")``).
CACHE_DIR_VAR = "RAYACCEL_CACHE_DIR"
#: Seconds pooch waits for the server to answer or send the next chunk.
TIMEOUT_S = 60.0
#: Folder, inside the folder of an archive, that its members are unpacked into.
UNPACKED = "unpacked"


@dataclass(frozen=True, slots=True)
class RemoteStatus:
    """One row of :func:`remote_status`: a downloadable scene and its cache state.

    Attributes
    ----------
    scene : RemoteScene
        The catalog entry.
    path : pathlib.Path or None
        The cached scene file, or ``None`` when it is not fetched.
    """

    scene: RemoteScene
    path: Path | None

    @property
    def cached(self) -> bool:
        """Whether the scene file is in the cache."""
        return self.path is not None

    @property
    def verified(self) -> bool:
        """Whether downloads of this entry are checked against a known SHA-256."""
        return self.scene.sha256 is not None


def cache_dir() -> Path:
    """Return the cache folder (it need not exist yet).

    Returns
    -------
    pathlib.Path
        ``$RAYACCEL_CACHE_DIR`` when set and not empty, else pooch's
        ``os_cache("rayaccel")``.
    """
    override = os.environ.get(CACHE_DIR_VAR, "").strip()
    if override:
        return Path(override).expanduser()
    import pooch

    return Path(pooch.os_cache("rayaccel"))


def lookup(name: str) -> RemoteScene:
    """Return the catalog entry called ``name`` (case, ``-`` and ``_`` ignored).

    Raises
    ------
    UnknownVariantError
        No downloadable scene has that name; the message suggests close ones.
    """
    if not isinstance(name, str):
        raise InvalidInputError(f"name: expected a scene name (str), got {name!r}")
    key = _normalise(name)
    for entry_name, entry in REMOTE_SCENES.items():
        if _normalise(entry_name) == key:
            return entry
    choices = list(REMOTE_SCENES)
    close = difflib.get_close_matches(key, choices, n=3, cutoff=0.5)
    hint = f"did you mean {', '.join(map(repr, close))}? " if close else ""
    raise UnknownVariantError(
        f"no downloadable scene {name!r}; {hint}downloadable scenes: {', '.join(choices)}"
    )


def _normalise(name: str) -> str:
    return name.strip().lower().replace("_", "-")


def _download_folder(scene: RemoteScene, root: Path) -> Path:
    """Return ``downloads/<key>``: one folder per URL, named by it, readable and stable."""
    digest = hashlib.sha256(scene.url.encode()).hexdigest()[:12]
    return root / "downloads" / f"{_basename(scene.url)}-{digest}"


def _basename(url: str) -> str:
    name = PurePosixPath(url.split("?", 1)[0].split("#", 1)[0]).name
    return name or "download"


def _is_glob(member: str) -> bool:
    return any(char in member for char in "*?[")


def _scene_file(scene: RemoteScene, root: Path) -> Path | None:
    """Return the cached scene file of ``scene``, or ``None`` when it is not there."""
    folder = _download_folder(scene, root)
    download = folder / _basename(scene.url)
    if scene.archive is None:
        return download if download.is_file() else None
    if scene.member is None:
        raise SceneFileError(f"scene {scene.name!r}: an archive entry needs a member")
    if _is_glob(scene.member):
        assembled = root / "scenes" / f"{scene.name}.ply"
        return assembled if assembled.is_file() else None
    unpacked = folder / UNPACKED
    exact = unpacked / scene.member
    if exact.is_file():
        return exact
    if not unpacked.is_dir():
        return None
    wanted = PurePosixPath(scene.member).name
    matches = sorted(path for path in unpacked.rglob(wanted) if path.is_file())
    return matches[0] if len(matches) == 1 else None


def cached_path(name: str) -> Path | None:
    """Return the cached scene file of a downloadable scene, or ``None`` if not fetched.

    Parameters
    ----------
    name : str
        A name of :data:`~rayaccel.scene.remote.REMOTE_SCENES`.

    Raises
    ------
    UnknownVariantError
        No downloadable scene has that name.
    """
    return _scene_file(lookup(name), cache_dir())


def download_sha256(name: str) -> str | None:
    """Return the SHA-256 of a scene's cached download, or ``None`` when there is none.

    For entries without a published hash this is the value to check against the
    source by other means (and to record in the catalog).

    Raises
    ------
    UnknownVariantError
        No downloadable scene has that name.
    """
    scene = lookup(name)
    return _sha256(_download_folder(scene, cache_dir()) / _basename(scene.url))


def fetched_scenes() -> dict[str, Path]:
    """Return every downloadable scene already in the cache, ``name -> scene file``."""
    root = cache_dir()
    found: dict[str, Path] = {}
    for name, scene in REMOTE_SCENES.items():
        path = _scene_file(scene, root)
        if path is not None:
            found[name] = path
    return found


def remote_status() -> list[RemoteStatus]:
    """Return one :class:`RemoteStatus` per downloadable scene, in catalog order."""
    root = cache_dir()
    return [RemoteStatus(scene, _scene_file(scene, root)) for scene in REMOTE_SCENES.values()]


def fetch(
    name: str | RemoteScene,
    *,
    verify: bool = True,
    force: bool = False,
    progress: bool = False,
) -> Path:
    """Download a benchmark scene into the cache (once) and return its scene file.

    Parameters
    ----------
    name : str or RemoteScene
        A name of :data:`~rayaccel.scene.remote.REMOTE_SCENES` (``rayaccel scenes list
        --remote`` shows them), or an entry.
    verify : bool, default True
        With ``False``, entries that have no published SHA-256 are downloaded without
        a check (their hash is then reported by the CLI, not trusted). Entries with a
        hash are always checked.
    force : bool, default False
        Download and unpack again even when the scene is cached.
    progress : bool, default False
        Show pooch's progress bar (needs ``tqdm``).

    Returns
    -------
    pathlib.Path
        The scene file, which :func:`rayaccel.scenes.get` also finds by ``name`` now.

    Raises
    ------
    UnknownVariantError
        Unknown name; the message suggests close ones.
    SceneFileError
        The entry has no published hash and ``verify`` is true; the download failed
        (HTTP error, refused connection, timeout); its SHA-256 differs from the known
        one (nothing is left in the cache); the archive is damaged, has members that
        would unpack outside the cache, or lacks the scene file.
    """
    scene = name if isinstance(name, RemoteScene) else lookup(name)
    if scene.sha256 is None and verify:
        raise SceneFileError(
            f"scene {scene.name!r} has no published SHA-256, so its download from "
            f"{scene.url} cannot be checked; to download it unchecked anyway, call "
            f"fetch({scene.name!r}, verify=False) or run 'rayaccel scenes fetch "
            f"{scene.name} --no-verify'"
        )
    root = cache_dir()
    folder = _download_folder(scene, root)
    download = folder / _basename(scene.url)
    if force:
        _remove(scene, root)
    elif (found := _scene_file(scene, root)) is not None and (
        scene.sha256 is None or _sha256(download) == scene.sha256
    ):
        return found
    downloaded = _retrieve(scene, folder, progress)
    action = "download" if downloaded else "fetch"
    if scene.archive is None:
        return download
    if scene.member is None:
        raise SceneFileError(f"scene {scene.name!r}: an archive entry needs a member")
    _unpack(scene, download, action)
    if _is_glob(scene.member):
        return _assemble(scene, folder / UNPACKED, root / "scenes" / f"{scene.name}.ply")
    path = _scene_file(scene, root)
    if path is None:
        raise SceneFileError(
            f"scene {scene.name!r}: {scene.member} is not in {download.name} "
            f"(unpacked into {folder / UNPACKED}); scene files there: "
            f"{_list_scene_files(folder / UNPACKED)}"
        )
    return path


def _retrieve(scene: RemoteScene, folder: Path, progress: bool) -> bool:
    """Download ``scene.url`` into ``folder`` unless a matching file is there.

    Returns whether a download took place.
    """
    import pooch
    import requests

    target = folder / _basename(scene.url)
    before = _stamp(target)
    known_hash = None if scene.sha256 is None else f"sha256:{scene.sha256}"
    downloader = pooch.HTTPDownloader(
        progressbar=progress,
        timeout=TIMEOUT_S,
        headers={"User-Agent": "rayaccel (pooch)"},
    )
    try:
        pooch.retrieve(
            scene.url,
            known_hash=known_hash,
            fname=target.name,
            path=folder,
            downloader=downloader,
            progressbar=progress,
        )
    except requests.HTTPError as exc:
        status = exc.response.status_code if exc.response is not None else "?"
        raise SceneFileError(
            f"scene {scene.name!r}: downloading {scene.url} failed with HTTP {status}; "
            "the source may have moved (check the catalog entry)"
        ) from exc
    except requests.RequestException as exc:
        raise SceneFileError(
            f"scene {scene.name!r}: could not download {scene.url} "
            f"({type(exc).__name__}: {_first_line(exc)})"
        ) from exc
    except ValueError as exc:  # pooch: the hash of the download differs
        raise SceneFileError(
            f"scene {scene.name!r}: the file downloaded from {scene.url} does not have "
            f"the known SHA-256 {scene.sha256}; it was discarded ({_first_line(exc)})"
        ) from exc
    return _stamp(target) != before


def _stamp(path: Path) -> tuple[int, int] | None:
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_mtime_ns, stat.st_size


def _first_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _sha256(path: Path) -> str | None:
    digest = hashlib.sha256()
    try:
        with path.open("rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


def _members(download: Path, archive: str) -> list[tuple[str, bool]]:
    """Return ``(name, is_link)`` for every member of an archive."""
    try:
        if archive == "zip":
            with zipfile.ZipFile(download) as bundle:
                return [(info.filename, False) for info in bundle.infolist()]
        with tarfile.open(download) as bundle:
            return [(info.name, info.issym() or info.islnk()) for info in bundle.getmembers()]
    except (zipfile.BadZipFile, tarfile.TarError, OSError, EOFError) as exc:
        raise SceneFileError(f"{download}: not a readable {archive} archive ({exc})") from exc


def _check_members(download: Path, archive: str) -> None:
    """Refuse archives whose members would unpack outside their folder, or links."""
    for member, is_link in _members(download, archive):
        parts = PurePosixPath(member.replace("\\", "/")).parts
        if member.startswith(("/", "\\")) or ".." in parts or (parts and ":" in parts[0]):
            raise SceneFileError(
                f"{download}: archive member {member!r} would unpack outside the cache"
            )
        if is_link:
            raise SceneFileError(f"{download}: archive member {member!r} is a link")


def _unpack(scene: RemoteScene, download: Path, action: str) -> None:
    """Unpack the archive with pooch's processors (again after a new download)."""
    import pooch

    assert scene.archive is not None  # checked by the caller
    _check_members(download, scene.archive)
    processor: Callable[[str, str, Any], Any]
    if scene.archive == "zip":
        processor = pooch.Unzip(extract_dir=UNPACKED)
    else:
        processor = pooch.Untar(extract_dir=UNPACKED)
    try:
        processor(str(download), action, None)
    except (zipfile.BadZipFile, tarfile.TarError, EOFError) as exc:
        raise SceneFileError(f"{download}: unpacking failed ({exc})") from exc


def _list_scene_files(folder: Path, limit: int = 5) -> str:
    if not folder.is_dir():
        return "none"
    files = sorted(
        path.relative_to(folder).as_posix()
        for path in folder.rglob("*")
        if path.is_file() and path.name.lower().endswith(SUPPORTED_SUFFIXES)
    )
    if not files:
        return "none"
    more = f" and {len(files) - limit} more" if len(files) > limit else ""
    return ", ".join(files[:limit]) + more


def _assemble(scene: RemoteScene, unpacked: Path, target: Path) -> Path:
    """Concatenate the parts matching ``scene.member`` into one binary PLY."""
    assert scene.member is not None
    parts = sorted(
        path
        for path in unpacked.rglob("*")
        if path.is_file()
        and fnmatch.fnmatchcase(path.relative_to(unpacked).as_posix(), scene.member)
    )
    if not parts:
        raise SceneFileError(
            f"scene {scene.name!r}: no file in {unpacked} matches {scene.member!r}; "
            f"scene files there: {_list_scene_files(unpacked)}"
        )
    meshes = [load_mesh(part) for part in parts]
    target.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(target, ply_bytes(meshes))
    return target


def ply_bytes(meshes: Iterable[Any]) -> bytes:
    """Return one binary little-endian PLY holding every mesh's triangles.

    Parameters
    ----------
    meshes : iterable of TriangleMesh
        Concatenated in order; each mesh's vertex indices are offset past the
        vertices of the meshes before it.

    Returns
    -------
    bytes
        float32 ``x y z`` vertices and ``uchar``-counted int32 triangle lists.
    """
    vertex_blocks: list[np.ndarray[Any, Any]] = []
    face_blocks: list[np.ndarray[Any, Any]] = []
    offset = 0
    for mesh in meshes:
        vertices = np.asarray(mesh.vertices, dtype="<f4")
        faces = np.asarray(mesh.faces, dtype=np.int64) + offset
        vertex_blocks.append(vertices)
        face_blocks.append(faces)
        offset += vertices.shape[0]
    vertices = np.concatenate(vertex_blocks) if vertex_blocks else np.zeros((0, 3), "<f4")
    faces = np.concatenate(face_blocks) if face_blocks else np.zeros((0, 3), np.int64)
    rows = np.empty(faces.shape[0], dtype=[("n", "u1"), ("v", "<i4", (3,))])
    rows["n"] = 3
    rows["v"] = faces
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment assembled by rayaccel scenes fetch\n"
        f"element vertex {vertices.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\n"
        f"element face {faces.shape[0]}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    return header.encode("ascii") + vertices.tobytes() + rows.tobytes()


def _remove(scene: RemoteScene, root: Path) -> None:
    """Delete a scene's download, its unpacked folder and its assembled file."""
    import shutil

    folder = _download_folder(scene, root)
    shutil.rmtree(folder, ignore_errors=True)
    if scene.member is not None and _is_glob(scene.member):
        (root / "scenes" / f"{scene.name}.ply").unlink(missing_ok=True)


__all__ = [
    "CACHE_DIR_VAR",
    "RemoteStatus",
    "cache_dir",
    "cached_path",
    "download_sha256",
    "fetch",
    "fetched_scenes",
    "lookup",
    "ply_bytes",
    "remote_status",
]
