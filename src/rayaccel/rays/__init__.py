"""Rays: batches, primary-ray cameras, secondary-ray generators and ray-set files.

Layer 2 (STYLE §2): depends only on the foundation modules and takes plain arrays
(bounds, per-triangle normals) rather than scene objects.
"""

from __future__ import annotations

from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.rays.bounce import (
    SHADOW_TMAX,
    ambient_occlusion_rays,
    cosine_hemisphere,
    diffuse_rays,
    offset_origin,
    shadow_rays,
)
from rayaccel.rays.camera import PinholeCamera, frame_bounds, from_preset
from rayaccel.rays.io import load_ray_metadata, load_rays, save_rays

__all__ = [
    "SHADOW_TMAX",
    "HitBatch",
    "PinholeCamera",
    "RayBatch",
    "ambient_occlusion_rays",
    "cosine_hemisphere",
    "diffuse_rays",
    "frame_bounds",
    "from_preset",
    "load_ray_metadata",
    "load_rays",
    "offset_origin",
    "save_rays",
    "shadow_rays",
]
