"""Recording ray sets: the batches a renderer traces, written as ``.npz`` chunks with a manifest.

A :class:`RayRecorder` collects batches by set name (``primary``, ``bounce1``,
``shadow0``...). When a set has buffered ``chunk_rays`` rays, they are written as
one ray-set file (:func:`rayaccel.rays.io.save_rays`, atomic), so a set larger
than memory is recorded in pieces. Every file carries the recording's metadata:
the scene's name and identity (:meth:`rayaccel.scene.mesh.TriangleMesh.digest`),
the set, the chunk's index, and what the caller adds (camera, seed, samples).
:meth:`RayRecorder.close` writes ``rays.json``, the manifest listing each set's
files and ray count.

Each chunk loads with :func:`rayaccel.rays.io.load_rays`; :func:`load_ray_set`
concatenates a set's chunks, refusing them when they belong to another scene.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from rayaccel._atomic import write_bytes_atomic
from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.rays.batch import RayBatch
from rayaccel.rays.io import json_default, load_ray_metadata, load_rays, save_rays

#: File name of a recording's manifest, and its format tag.
MANIFEST = "rays.json"
MANIFEST_FORMAT = "rayaccel-rays/1"
#: Rays per chunk file by default (4 Mi rays, 128 MiB).
CHUNK_RAYS = 1 << 22


class RayRecorder:
    """Write named ray sets of one scene into a folder, in chunks.

    Parameters
    ----------
    folder : path-like
        Created if missing. Files ``<set>-<chunk>.npz`` and ``rays.json`` go there.
    scene : str
        The scene's name.
    scene_digest : str
        The scene's identity (:meth:`rayaccel.scene.mesh.TriangleMesh.digest`).
    chunk_rays : int
        Rays per file (>= 1).
    **metadata
        JSON-serialisable values stored in every file and in the manifest.

    Use as a context manager (the manifest is written only when the block ends
    without an exception), or call :meth:`close` to write what is buffered and the
    manifest.
    """

    def __init__(
        self,
        folder: str | os.PathLike[str],
        *,
        scene: str,
        scene_digest: str,
        chunk_rays: int = CHUNK_RAYS,
        **metadata: Any,
    ) -> None:
        if chunk_rays < 1:
            raise InvalidInputError(f"chunk_rays must be >= 1, got {chunk_rays}")
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.chunk_rays = int(chunk_rays)
        self.metadata = {"scene": scene, "scene_digest": scene_digest, **metadata}
        self._buffers: dict[str, list[RayBatch]] = {}
        self._buffered: dict[str, int] = {}
        self._files: dict[str, list[str]] = {}
        self._counts: dict[str, int] = {}

    def add(self, name: str, rays: RayBatch) -> None:
        """Buffer ``rays`` under set ``name``; write full chunks."""
        if not name or not all(c.isalnum() or c in "_-" for c in name):
            raise InvalidInputError(f"ray set name must be letters, digits, _ or -: {name!r}")
        self._buffers.setdefault(name, []).append(rays)
        self._buffered[name] = self._buffered.get(name, 0) + rays.n_rays
        self._counts[name] = self._counts.get(name, 0) + rays.n_rays
        while self._buffered[name] >= self.chunk_rays:
            self._write(name, self.chunk_rays)

    def _write(self, name: str, n: int) -> None:
        batches = self._buffers[name]
        joined = RayBatch.concatenate(batches)
        head, rest = joined.subset(slice(0, n)), joined.subset(slice(n, None))
        index = len(self._files.setdefault(name, []))
        path = self.folder / f"{name}-{index:04d}.npz"
        save_rays(path, head, **self.metadata, set=name, chunk=index)
        self._files[name].append(path.name)
        self._buffers[name] = [rest] if rest.n_rays else []
        self._buffered[name] = rest.n_rays

    def close(self) -> dict[str, Any]:
        """Write the buffered rays and the manifest; return the manifest."""
        for name in list(self._buffers):
            if self._buffered[name]:
                self._write(name, self._buffered[name])
        manifest = {
            "format": MANIFEST_FORMAT,
            **self.metadata,
            "sets": {
                name: {"n_rays": self._counts[name], "files": self._files.get(name, [])}
                for name in self._counts
            },
        }
        text = json.dumps(manifest, indent=1, sort_keys=True, default=json_default)
        write_bytes_atomic(self.folder / MANIFEST, text.encode())
        return manifest

    def __enter__(self) -> RayRecorder:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        # An interrupted recording keeps its written chunks but gets no manifest, so
        # it is never taken for a complete one.
        if exc_type is None:
            self.close()


def read_manifest(folder: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a recording's ``rays.json``.

    Raises
    ------
    SceneFileError
        When it is missing, not JSON, or of another format.
    """
    path = Path(folder) / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SceneFileError(f"{path}: cannot read the ray recording's manifest ({exc})") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise SceneFileError(f"{path}: not a {MANIFEST_FORMAT} manifest")
    return manifest


def load_ray_set(
    folder: str | os.PathLike[str], name: str, scene_digest: str | None = None
) -> RayBatch:
    """Load set ``name`` of a recording (all its chunks, in order).

    Parameters
    ----------
    folder : path-like
        The recording's folder.
    name : str
        The set.
    scene_digest : str, optional
        When given, every chunk must have been recorded on the scene of this digest
        (:meth:`rayaccel.scene.mesh.TriangleMesh.digest`).

    Raises
    ------
    SceneFileError
        Unknown set, unreadable chunk, or rays of another scene.
    """
    manifest = read_manifest(folder)
    sets = manifest.get("sets", {})
    if name not in sets:
        raise SceneFileError(f"{folder}: no ray set {name!r} (sets: {', '.join(sorted(sets))})")
    batches = []
    for file in sets[name]["files"]:
        path = Path(folder) / file
        if scene_digest is not None:
            recorded = load_ray_metadata(path).get("scene_digest")
            if recorded != scene_digest:
                raise SceneFileError(
                    f"{path}: recorded on another scene (digest {str(recorded)[:12]}..., "
                    f"expected {scene_digest[:12]}...)"
                )
        batches.append(load_rays(path))
    if not batches:
        raise SceneFileError(f"{folder}: ray set {name!r} has no files")
    rays = RayBatch.concatenate(batches)
    if rays.n_rays != sets[name]["n_rays"]:
        raise SceneFileError(
            f"{folder}: ray set {name!r} has {rays.n_rays} rays, the manifest says "
            f"{sets[name]['n_rays']}"
        )
    return rays
