"""The standard ray sets of a scene: primary, diffuse and shadow rays (tinybvh's speed test).

Every system of a benchmark traces the **same** :class:`~rayaccel.rays.batch.RayBatch`
objects, generated once per scene:

``primary``  (closest hit) one ray per pixel of a pinhole camera, row-major from
             the top-left: coherent. The camera is the scene's catalog preset
             (:func:`rayaccel.scene.catalog.camera_preset`; interior scenes are
             seen from inside) or else :func:`rayaccel.rays.camera.frame_bounds`
             around the bounding box, with +Y up.
``diffuse``  (closest hit) one cosine-weighted bounce from every primary hit:
             incoherent (:func:`rayaccel.rays.bounce.diffuse_rays`).
``shadow``   (any hit) from every primary hit towards one point light, with
             ``tmax = 1 - 1e-4`` on unnormalised directions
             (:func:`rayaccel.rays.bounce.shadow_rays`).

The point light is the preset's ``light`` entry when it has one. Otherwise it is
placed by a probe ray: from the preset's eye (or the bounding-box centre) straight
up, at 80% of the distance to the first surface hit (a ceiling), or, if nothing is
hit, 40% of the box's height above the start. Primary hits come from a
``bvh2.binned_sah`` trace (the default builder), which every correct structure
reproduces; all randomness comes from ``seed``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rayaccel import api, registry
from rayaccel.errors import InvalidInputError
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.rays.bounce import diffuse_rays, shadow_rays
from rayaccel.rays.camera import PinholeCamera, frame_bounds, from_preset
from rayaccel.rays.views import turned
from rayaccel.scene import catalog
from rayaccel.scene.mesh import TriangleMesh

#: Every standard ray set and the query it is traced with.
RAY_KINDS: dict[str, str] = {"primary": "closest", "diffuse": "closest", "shadow": "any"}
#: Keys of a camera preset that :func:`rayaccel.rays.camera.from_preset` takes.
_CAMERA_KEYS = ("eye", "target", "up", "fov_deg")


@dataclass(frozen=True, slots=True, eq=False)
class RaySet:
    """One named ray set of a scene.

    Attributes
    ----------
    kind : str
        ``"primary"``, ``"diffuse"`` or ``"shadow"``.
    query : {"closest", "any"}
        The query the set is traced with.
    rays : RayBatch
    """

    kind: str
    query: str
    rays: RayBatch

    @property
    def n_rays(self) -> int:
        """Number of rays."""
        return self.rays.n_rays


def parse_kinds(spec: str | Sequence[str] | None) -> list[str]:
    """Parse ``--rays``: ``"primary,diffuse,shadow"``, ``"all"`` or a list.

    Raises
    ------
    InvalidInputError
        An unknown ray set name.
    """
    if spec is None:
        return list(RAY_KINDS)
    items = spec.split(",") if isinstance(spec, str) else [s for p in spec for s in p.split(",")]
    kinds = [item.strip() for item in items if item.strip()]
    if kinds == ["all"]:
        return list(RAY_KINDS)
    for kind in kinds:
        if kind not in RAY_KINDS:
            raise InvalidInputError(
                f"rays: unknown ray set {kind!r}; expected some of {', '.join(RAY_KINDS)}"
            )
    if not kinds:
        raise InvalidInputError("rays: expected at least one ray set")
    return [kind for kind in RAY_KINDS if kind in kinds]


def scene_camera(
    mesh: TriangleMesh, name: str | None, *, width: int, height: int, view: str | None = None
) -> tuple[PinholeCamera, Mapping[str, Any] | None]:
    """Return the benchmark camera of a scene and its catalog preset (None if framed).

    Parameters
    ----------
    mesh : TriangleMesh
        The scene; its bounding box is framed when it has no preset.
    name : str, optional
        Catalog name (or path) used to look up a preset.
    width, height : int
        Resolution.
    view : str, optional
        A named view of that camera (:mod:`rayaccel.rays.views`: ``yaw120``,
        ``orbit90``); default the camera itself.
    """
    preset = catalog.camera_preset(name) if name else None
    if preset is not None:
        camera = from_preset({k: preset[k] for k in _CAMERA_KEYS if k in preset}, width, height)
    else:
        lo, hi = mesh.bounds()
        camera = frame_bounds(lo, hi, width=width, height=height)
    return (camera if view is None else turned(camera, view)), preset


def scene_light(
    accel: api.Accel, camera: PinholeCamera, preset: Mapping[str, Any] | None
) -> np.ndarray:
    """Return the ``(3,)`` float64 point light of the shadow rays (module docstring)."""
    if preset is not None and "light" in preset:
        light = np.asarray(preset["light"], dtype=np.float64)
        if light.shape != (3,):
            raise InvalidInputError(f"preset light: expected a (3,) point, got {light.shape}")
        return light
    lo, hi = (np.asarray(b, dtype=np.float64) for b in accel.mesh.bounds())
    up = np.asarray(camera.up, dtype=np.float64)
    up /= np.linalg.norm(up)
    start = np.asarray(camera.eye, dtype=np.float64) if preset is not None else 0.5 * (lo + hi)
    height = float(np.abs(up) @ (hi - lo)) or 1.0
    probe = accel.intersect(start[None, :], up[None, :], traversal=_reference(accel))
    distance = 0.8 * float(probe.t[0]) if probe.hit[0] else 0.4 * height
    return start + distance * up


def _reference(accel: api.Accel) -> str:
    """Return the structure's reference traversal, which the bench compiles before any scene."""
    return registry.default_traversal(accel.structure_name)


def standard_raysets(
    mesh: TriangleMesh,
    name: str | None = None,
    *,
    kinds: Sequence[str] = tuple(RAY_KINDS),
    width: int = 512,
    height: int = 512,
    seed: int = 0,
    accel: api.Accel | None = None,
    view: str | None = None,
) -> dict[str, RaySet]:
    """Generate the standard ray sets of a scene.

    Parameters
    ----------
    mesh : TriangleMesh
        The scene the rays are generated for.
    name : str, optional
        Catalog name of the scene, for its camera preset.
    kinds : sequence of str
        Which of :data:`RAY_KINDS` to return.
    width, height : int
        Primary-ray resolution (``width · height`` primary rays).
    seed : int
        Seed of the diffuse sampler.
    accel : Accel, optional
        Structure used to find the primary hits; default a fresh
        ``bvh2.binned_sah`` build.
    view : str, optional
        Another view of the scene's camera (:mod:`rayaccel.rays.views`); the point
        light stays where the scene's camera puts it.

    Returns
    -------
    dict of str to RaySet
        In :data:`RAY_KINDS` order, only the requested kinds.
    """
    kinds = parse_kinds(list(kinds))
    camera, preset = scene_camera(mesh, name, width=width, height=height)
    viewed = camera if view is None else turned(camera, view)
    primary = viewed.rays()
    sets: dict[str, RaySet] = {}
    if "primary" in kinds:
        sets["primary"] = RaySet("primary", RAY_KINDS["primary"], primary)
    if kinds == ["primary"]:
        return sets
    accel = accel or api.build(mesh)
    hits: HitBatch = accel.trace(primary, traversal=_reference(accel))
    normals = mesh.normals()
    if "diffuse" in kinds:
        rays, _ = diffuse_rays(primary, hits, normals, seed=seed)
        sets["diffuse"] = RaySet("diffuse", RAY_KINDS["diffuse"], rays)
    if "shadow" in kinds:
        light = scene_light(accel, camera, preset)
        rays, _ = shadow_rays(primary, hits, normals, light, seed=seed)
        sets["shadow"] = RaySet("shadow", RAY_KINDS["shadow"], rays)
    return sets
