"""A wavefront path tracer over any structure and traversal, which records every ray it traces.

The thesis measured its structures on the rays of a path tracer: primary rays,
bounce rays per depth and shadow rays (Chapter 5). This module renders the same
kind of image and hands each batch of rays to a recorder
(:class:`rayaccel.rays.record.RayRecorder`) before tracing it, so a study can replay
exactly those rays through every structure.

Light transport (Pharr, Jakob & Humphreys, *PBR* 4th ed., Ch. 13): Lambertian
surfaces (:mod:`rayaccel.render.materials`), emitters seen directly by the camera,
and next-event estimation to the area lights (:mod:`rayaccel.render.lights`) at
every hit: one light point per hit, with a shadow ray (an any-hit query) that ends
just before the light. Bounces sample the cosine-weighted hemisphere, so the
throughput is multiplied by the albedo alone. Emission reached by a bounce ray is
not added, since next-event estimation already counts that light (no multiple
importance sampling: the estimator stays unbiased for diffuse surfaces). Russian
roulette (Arvo & Kirk 1990) ends a path after ``rr_depth`` bounces with
probability ``1 − min(1, max(throughput))``. Surfaces are two-sided.

Wavefront (Laine, Karras & Aila 2013, "Megakernels Considered Harmful"): each
depth is one closest-hit trace of all live paths, one shading kernel, one any-hit
trace of their shadow rays, then the live paths are compacted. The traces go
through :meth:`rayaccel.api.Accel.trace`, so every registered structure and
traversal renders, and the rays recorded are the rays traced.

Random numbers are a hash of ``(seed, sample, depth, pixel, dimension)``
(:mod:`rayaccel.render.path_kernels`), so an image does not depend on the thread
count or on the traversal.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rayaccel._atomic import write_bytes_atomic
from rayaccel.api import Accel
from rayaccel.dtypes import REAL
from rayaccel.errors import InvalidInputError
from rayaccel.rays.batch import RayBatch
from rayaccel.rays.camera import PinholeCamera
from rayaccel.render.lights import AreaLights
from rayaccel.render.materials import Materials
from rayaccel.render.path_kernels import camera_directions, pass_key, shade_hits
from rayaccel.render.shading import srgb_encode

FloatArray = npt.NDArray[np.float32]
U8Array = npt.NDArray[np.uint8]

#: A shadow ray ends this fraction of its length before the light point.
SHADOW_END = 1e-3


@dataclass(frozen=True, slots=True)
class PathOptions:
    """Options of :func:`path_trace`.

    Attributes
    ----------
    spp : int
        Samples (paths) per pixel, >= 1. The thesis rendered 64 at 1080×720; the
        default is small so a study runs in minutes.
    max_depth : int
        Bounces after the camera ray, >= 0 (0: direct light only).
    rr_depth : int
        Russian roulette starts after this many bounces, >= 1.
    seed : int
        Seed of every random decision.
    epsilon : float
        Offset of new ray origins from the surface, relative to ``max(1, |p|∞)``.
    """

    spp: int = 4
    max_depth: int = 3
    rr_depth: int = 2
    seed: int = 0
    epsilon: float = 1e-4

    def __post_init__(self) -> None:
        if self.spp < 1 or self.spp > 1 << 20:
            raise InvalidInputError(f"spp must be in 1..2^20, got {self.spp}")
        if not 0 <= self.max_depth <= 64:
            raise InvalidInputError(f"max_depth must be in 0..64, got {self.max_depth}")
        if self.rr_depth < 1:
            raise InvalidInputError(f"rr_depth must be >= 1, got {self.rr_depth}")
        if not (np.isfinite(self.epsilon) and 0 <= self.epsilon < 0.1):
            raise InvalidInputError(f"epsilon must be in [0, 0.1), got {self.epsilon}")


@dataclass(slots=True, eq=False)
class PathImage:
    """A rendered image and the rays it took.

    Attributes
    ----------
    radiance : (H, W, 3) float32
        Linear radiance per pixel (mean over the samples).
    counts : dict of str to int
        Rays traced per ray set (``primary``, ``bounce1``..., ``shadow0``...).
    """

    radiance: FloatArray
    counts: dict[str, int] = field(default_factory=dict)

    def tonemapped(self, exposure: float = 1.0) -> U8Array:
        """8-bit sRGB of ``exposure · radiance`` clamped to ``[0, 1]``."""
        return srgb_encode(self.radiance.astype(np.float64) * exposure)

    def write_exr(self, path: str | os.PathLike[str]) -> Path:
        """Write the linear radiance as a float32 OpenEXR file (ZIP), atomically.

        Needs the ``openexr`` package (the ``study`` extra).
        """
        try:
            import OpenEXR
        except ImportError as exc:
            raise InvalidInputError(
                "EXR output needs the openexr package: pip install 'rayaccel[study]'"
            ) from exc
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        pixels = np.ascontiguousarray(self.radiance, dtype=np.float32)
        with tempfile.TemporaryDirectory() as folder:
            scratch = Path(folder) / "image.exr"
            with OpenEXR.File(header, {"RGB": pixels}) as image:
                image.write(str(scratch))
            data = scratch.read_bytes()
        return write_bytes_atomic(path, data)


Recorder = Callable[[str, RayBatch], Any]


def path_trace(
    accel: Accel,
    camera: PinholeCamera,
    *,
    materials: Materials,
    lights: AreaLights,
    options: PathOptions | None = None,
    traversal: str | None = None,
    record: Recorder | None = None,
    progress: Callable[[int, int], Any] | None = None,
) -> PathImage:
    """Render ``camera``'s view of ``accel``'s mesh by path tracing.

    Parameters
    ----------
    accel : Accel
        The structure (any registered builder); its mesh is the scene.
    camera : PinholeCamera
        The view and resolution.
    materials : Materials
        One per triangle of the mesh.
    lights : AreaLights
        The lights sampled by next-event estimation.
    options : PathOptions, optional
    traversal : str, optional
        Traversal key; default the structure's default traversal.
    record : callable, optional
        Called as ``record(name, rays)`` with every batch before it is traced (a
        :class:`rayaccel.rays.record.RayRecorder`'s ``add``).
    progress : callable, optional
        Called as ``progress(done, total)`` after every sample pass.

    Returns
    -------
    PathImage
    """
    opt = options or PathOptions()
    mesh = accel.mesh
    if materials.n_triangles != mesh.n_triangles:
        raise InvalidInputError(
            f"materials describe {materials.n_triangles} triangles, the mesh has "
            f"{mesh.n_triangles}"
        )
    tri = mesh.triangles()
    width, height = camera.width, camera.height
    n_pixels = width * height
    forward, right, up = camera.frame()
    frame = np.ascontiguousarray([forward, right, up], dtype=np.float64)
    half_w, half_h = camera.half_extent()
    eye = np.asarray(camera.eye, dtype=REAL)
    radiance = np.zeros((n_pixels, 3), dtype=np.float64)
    counts: dict[str, int] = {}

    def traced(name: str, rays: RayBatch, query: str) -> Any:
        if record is not None:
            record(name, rays)
        counts[name] = counts.get(name, 0) + rays.n_rays
        return accel.trace(rays, query=query, traversal=traversal)

    for sample in range(opt.spp):
        directions = np.empty((n_pixels, 3), dtype=np.float64)
        camera_directions(frame, half_w, half_h, width, height,
                           pass_key(opt.seed, sample, 0), directions)  # fmt: skip
        rays = RayBatch(np.broadcast_to(eye, (n_pixels, 3)), directions.astype(REAL))
        pixel = np.arange(n_pixels, dtype=np.int64)
        throughput = np.ones((n_pixels, 3), dtype=np.float64)
        for depth in range(opt.max_depth + 1):
            name = "primary" if depth == 0 else f"bounce{depth}"
            hits = traced(name, rays, "closest")
            n = rays.n_rays
            s_origin = np.empty((n, 3), dtype=np.float64)
            s_dir = np.empty((n, 3), dtype=np.float64)
            s_contrib = np.empty((n, 3), dtype=np.float64)
            s_ok = np.empty(n, dtype=np.bool_)
            n_origin = np.empty((n, 3), dtype=np.float64)
            n_dir = np.empty((n, 3), dtype=np.float64)
            n_thr = np.empty((n, 3), dtype=np.float64)
            n_ok = np.empty(n, dtype=np.bool_)
            shade_hits(
                tri, materials.albedo, materials.emission, lights.triangles, lights.emission,
                lights.cdf, lights.area, rays.origin, rays.direction, hits.t, hits.prim, hits.u,
                hits.v, pixel, throughput, pass_key(opt.seed, sample, depth + 1), depth == 0,
                depth >= opt.rr_depth, float(opt.epsilon), radiance, s_origin, s_dir,
                s_contrib, s_ok, n_origin, n_dir, n_thr, n_ok,
            )  # fmt: skip
            if s_ok.any():
                shadow = RayBatch(s_origin[s_ok].astype(REAL), s_dir[s_ok].astype(REAL), 0.0,
                                  1.0 - SHADOW_END)  # fmt: skip
                blocked = traced(f"shadow{depth}", shadow, "any").hit
                lit = ~blocked
                radiance[pixel[s_ok][lit]] += s_contrib[s_ok][lit]
            if depth == opt.max_depth or not n_ok.any():
                break
            rays = RayBatch(n_origin[n_ok].astype(REAL), n_dir[n_ok].astype(REAL))
            pixel = pixel[n_ok]
            throughput = n_thr[n_ok]
        if progress is not None:
            progress(sample + 1, opt.spp)
    image = (radiance / opt.spp).reshape(height, width, 3).astype(np.float32)
    return PathImage(image, counts)
