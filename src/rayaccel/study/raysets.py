"""The ray sets of one scene in a sweep: generated ones, and the path tracer's recorded ones.

Generated sets (``primary``, ``diffuse``, ``shadow``) come from
:func:`rayaccel.bench.raysets.standard_raysets`. The ``path`` kind renders the scene
once with the path tracer (:func:`rayaccel.study.recording.render_scene`) and
records its rays under ``<rays folder>/<scene>``; a later run (a resumed sweep)
reuses the recording when its manifest has the same scene digest and parameters,
and records again otherwise. The recorded sets are merged into three:
``path-primary``, ``path-bounce`` (all depths) and ``path-shadow`` (all depths),
as the thesis grouped them.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from rayaccel.bench.raysets import RaySet, standard_raysets
from rayaccel.errors import SceneFileError
from rayaccel.rays.batch import RayBatch
from rayaccel.rays.record import load_ray_set, read_manifest
from rayaccel.render.path import PathOptions
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.study.config import GENERATED_KINDS, PATH_SETS, RayConfig
from rayaccel.study.recording import render_scene


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


def _recording_matches(folder: Path, mesh: TriangleMesh, rays: RayConfig) -> bool:
    try:
        manifest = read_manifest(folder)
    except SceneFileError:
        return False
    camera = manifest.get("camera", {})
    return bool(
        manifest.get("scene_digest") == mesh.digest()
        and camera.get("width") == rays.width
        and camera.get("height") == rays.height
        and manifest.get("seed") == rays.seed
        and manifest.get("spp") == rays.spp
        and manifest.get("max_depth") == rays.max_depth
        and manifest.get("rr_depth") == rays.rr_depth
    )


def path_raysets(
    mesh: TriangleMesh, name: str, rays: RayConfig, folder: str | os.PathLike[str]
) -> dict[str, RaySet]:
    """Record (or reuse) the path tracer's rays of a scene; return the three merged sets."""
    where = Path(folder) / _safe(name)
    if not _recording_matches(where, mesh, rays):
        options = PathOptions(spp=rays.spp, max_depth=rays.max_depth, rr_depth=rays.rr_depth,
                              seed=rays.seed)  # fmt: skip
        render_scene(mesh, name, width=rays.width, height=rays.height, options=options,
                     record_to=where)  # fmt: skip
    sets = read_manifest(where)["sets"]
    digest = mesh.digest()

    def merged(prefix: str) -> RayBatch:
        names = sorted((s for s in sets if re.fullmatch(rf"{prefix}\d*", s)),
                       key=lambda s: int(s[len(prefix):] or 0))  # fmt: skip
        if not names:
            return RayBatch(np.zeros((0, 3)), np.ones((0, 3)))
        return RayBatch.concatenate([load_ray_set(where, s, digest) for s in names])

    out = {
        "path-primary": merged("primary"),
        "path-bounce": merged("bounce"),
        "path-shadow": merged("shadow"),
    }
    return {key: RaySet(key, PATH_SETS[key], batch) for key, batch in out.items()}


def scene_raysets(
    mesh: TriangleMesh, name: str, rays: RayConfig, folder: str | os.PathLike[str]
) -> dict[str, RaySet]:
    """Return every ray set ``rays`` asks for, by set name (see the module docstring)."""
    sets: dict[str, RaySet] = {}
    generated = [k for k in rays.kinds if k in GENERATED_KINDS]
    if generated:
        sets.update(standard_raysets(mesh, name, kinds=generated, width=rays.width,
                                     height=rays.height, seed=rays.seed))  # fmt: skip
    if "path" in rays.kinds:
        sets.update(path_raysets(mesh, name, rays, folder))
    return {key: sets[key] for key in rays.set_names()}
