"""A quick shaded picture of a scene: normal-tinted headlight shading and ambient occlusion.

This is a preview, not a renderer: it shows what the acceleration structure sees
(and that it sees it right). Every primary ray's closest hit is shaded with

* a **headlight** term ``|cos θ|`` between the ray and the triangle's geometric
  normal (two-sided, so back faces of open meshes are lit too);
* a pastel **tint** from the normal's direction, ``albedo = 0.55 + 0.45·|n|``
  per channel, so surfaces facing different axes are told apart;
* optionally **ambient occlusion**: ``k`` cosine-weighted rays of bounded length
  per hit (:func:`rayaccel.rays.bounce.ambient_occlusion_rays`), traced as
  any-hit queries (``accel.occluded``); the unoccluded fraction scales the
  colour (Zhukov, Iones & Kronin 1998; Pharr, Jakob & Humphreys, *PBR* 4th ed.
  §13.2 on cosine-weighted sampling).

Pixels whose ray misses get a constant background. The linear result is encoded
with the sRGB transfer curve (IEC 61966-2-1) into 8 bits.

Cost: one closest-hit trace of ``w·h`` rays plus, with AO, ``k·w·h`` any-hit rays.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from rayaccel.api import Accel
from rayaccel.errors import InvalidInputError
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.rays.bounce import ambient_occlusion_rays
from rayaccel.rays.camera import PinholeCamera

U8Array = npt.NDArray[np.uint8]
F64Array = npt.NDArray[np.float64]

#: Linear RGB of pixels whose primary ray misses the scene.
BACKGROUND: tuple[float, float, float] = (0.02, 0.02, 0.03)
#: Share of light that reaches a surface regardless of the headlight angle.
AMBIENT = 0.12


def srgb_encode(linear: npt.ArrayLike) -> U8Array:
    """Encode linear ``[0, 1]`` values with the sRGB transfer curve into uint8."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.rint(255.0 * encoded).astype(np.uint8)


def ambient_visibility(
    accel: Accel,
    rays: RayBatch,
    hits: HitBatch,
    normals: npt.ArrayLike,
    *,
    samples: int,
    radius: float | None = None,
    traversal: str | None = None,
    seed: int = 0,
) -> F64Array:
    """Return the unoccluded fraction of ``samples`` AO rays at every hit, per primary ray.

    Parameters
    ----------
    accel : Accel
        The structure the AO rays are traced against.
    rays : RayBatch
        The primary rays.
    hits : HitBatch
        Their closest hits.
    normals : (F, 3) array_like of float
        Triangle normals of ``accel.mesh``.
    samples : int
        AO rays per hit, ``>= 1``.
    radius : float, optional
        Occlusion distance; default a tenth of the hit points' bounding-box diagonal.
    traversal : str, optional
        Traversal key used for the any-hit queries.
    seed : int
        Seed of the sampler.

    Returns
    -------
    (n,) float64 ndarray
        1 where nothing occludes (and for rays that missed), down to 0.
    """
    ao_rays, source = ambient_occlusion_rays(
        rays,
        hits,
        normals,
        n_per_hit=samples,
        radius=radius,
        seed=seed,
    )
    n = len(hits)
    visibility = np.ones(n, dtype=np.float64)
    if ao_rays.n_rays == 0:
        return visibility
    blocked = accel.occluded(
        ao_rays.origin, ao_rays.direction, ao_rays.tmin, ao_rays.tmax, traversal=traversal
    )
    occluded = np.bincount(source, weights=blocked.astype(np.float64), minlength=n)
    counts = np.bincount(source, minlength=n)
    has = counts > 0
    visibility[has] = 1.0 - occluded[has] / counts[has]
    return visibility


def shade(
    accel: Accel,
    camera: PinholeCamera,
    *,
    traversal: str | None = None,
    ao_samples: int = 0,
    ao_radius: float | None = None,
    seed: int = 0,
) -> U8Array:
    """Render a shaded preview of ``accel``'s mesh through ``camera``.

    Parameters
    ----------
    accel : Accel
        The structure to trace; its mesh supplies the normals.
    camera : PinholeCamera
        One primary ray per pixel.
    traversal : str, optional
        Traversal registry key; default the structure's default traversal.
    ao_samples : int
        Ambient-occlusion rays per pixel; 0 (default) disables AO.
    ao_radius : float, optional
        Occlusion distance in world units (default: a tenth of the visible extent).
    seed : int
        Seed of the AO sampler.

    Returns
    -------
    (camera.height, camera.width, 3) uint8 ndarray
        sRGB image, row 0 at the top.

    Raises
    ------
    InvalidInputError
        Negative ``ao_samples``.
    """
    if isinstance(ao_samples, bool) or not isinstance(ao_samples, (int, np.integer)):
        raise InvalidInputError(f"ao_samples: expected an int >= 0, got {ao_samples!r}")
    if ao_samples < 0:
        raise InvalidInputError(f"ao_samples: expected an int >= 0, got {ao_samples}")
    rays = camera.rays()
    hits = accel.trace(rays, query="closest", traversal=traversal)
    normals = accel.mesh.normals().astype(np.float64)
    hit = hits.hit
    n = np.zeros((rays.n_rays, 3))
    n[hit] = normals[hits.prim[hit]]
    direction = rays.direction.astype(np.float64)
    length = np.linalg.norm(direction, axis=1)
    cosine = np.abs(np.einsum("ij,ij->i", n, direction)) / np.where(length > 0, length, 1.0)
    albedo = 0.55 + 0.45 * np.abs(n)
    light = AMBIENT + (1.0 - AMBIENT) * cosine
    if ao_samples > 0:
        light = light * ambient_visibility(
            accel,
            rays,
            hits,
            normals,
            samples=int(ao_samples),
            radius=ao_radius,
            traversal=traversal,
            seed=seed,
        )
    colour = albedo * light[:, None]
    colour[~hit] = BACKGROUND
    return srgb_encode(colour).reshape(camera.height, camera.width, 3)
