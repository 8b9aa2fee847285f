"""Render a scene with the path tracer and record its ray sets: the study's first step.

The thesis (§5.1) rendered each scene with a path tracer and replayed the primary,
bounce and shadow rays it traced. :func:`render_scene` does that for a catalog
scene or a scene file: the scene's camera preset (or a framing of its box), its
materials (:func:`rayaccel.render.materials.scene_materials`), its emissive
triangles as lights or, when nothing emits, a virtual light where the benchmark's
point light is (:func:`rayaccel.bench.raysets.scene_light`), and optionally a
:class:`~rayaccel.rays.record.RayRecorder` writing every ray set with the scene's
identity, the camera, the seed and the sample counts.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rayaccel import api
from rayaccel.bench.raysets import scene_camera, scene_light
from rayaccel.rays.camera import PinholeCamera
from rayaccel.rays.record import CHUNK_RAYS, RayRecorder
from rayaccel.render.lights import AreaLights, default_virtual_light
from rayaccel.render.materials import Materials, scene_materials
from rayaccel.render.path import PathImage, PathOptions, path_trace
from rayaccel.scene import catalog
from rayaccel.scene.mesh import TriangleMesh


def scene_lights(
    accel: api.Accel,
    materials: Materials,
    camera: PinholeCamera,
    preset: Any,
) -> AreaLights:
    """Return the scene's emissive triangles, or a virtual light at the bench's light point."""
    lights = AreaLights.from_materials(accel.mesh, materials)
    if lights is not None:
        return lights
    point = scene_light(accel, camera, preset)
    return default_virtual_light(accel.mesh, point, camera.up)


def render_scene(
    mesh: TriangleMesh,
    name: str | None = None,
    *,
    accel: api.Accel | None = None,
    traversal: str | None = None,
    width: int = 256,
    height: int = 192,
    options: PathOptions | None = None,
    record_to: str | os.PathLike[str] | None = None,
    chunk_rays: int = CHUNK_RAYS,
    progress: Callable[[int, int], Any] | None = None,
) -> PathImage:
    """Path trace ``mesh`` from its camera; record the rays into ``record_to`` if given.

    Parameters
    ----------
    mesh : TriangleMesh
        The scene.
    name : str, optional
        Its catalog name or file path: selects the camera preset and materials.
    accel : Accel, optional
        The structure to trace with; default ``api.build(mesh)``.
    traversal : str, optional
        Traversal key; default the structure's.
    width, height : int
        Image size. The default (256×192, 4 samples) is far smaller than the
        thesis's 1080×720 at 64 samples, so a study runs in minutes.
    options : PathOptions, optional
        Samples, depth, roulette, seed.
    record_to : path-like, optional
        Folder for the recorded ray sets (:mod:`rayaccel.rays.record`).
    chunk_rays : int
        Rays per recorded file.
    progress : callable, optional
        ``progress(done, total)`` after every sample pass.
    """
    opt = options or PathOptions()
    accel = accel or api.build(mesh)
    camera, preset = scene_camera(mesh, name, width=width, height=height)
    source = catalog.resolve(name) if name is not None else None
    materials = scene_materials(mesh, source if isinstance(source, Path) else None)
    lights = scene_lights(accel, materials, camera, preset)
    if record_to is None:
        return path_trace(accel, camera, materials=materials, lights=lights, options=opt,
                          traversal=traversal, progress=progress)  # fmt: skip
    camera_record = {"eye": camera.eye, "target": camera.target, "up": camera.up,
                     "fov_deg": camera.fov_deg, "width": width, "height": height}  # fmt: skip
    with RayRecorder(
        record_to, scene=mesh.name, scene_digest=mesh.digest(), chunk_rays=chunk_rays,
        camera=camera_record, seed=opt.seed, spp=opt.spp, max_depth=opt.max_depth,
        rr_depth=opt.rr_depth, materials=materials.source, lights=lights.n_lights,
        virtual_light=lights.virtual,
    ) as recorder:  # fmt: skip
        return path_trace(accel, camera, materials=materials, lights=lights, options=opt,
                          traversal=traversal, record=recorder.add,
                          progress=progress)  # fmt: skip
