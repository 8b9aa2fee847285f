"""Named views: other cameras of a scene, derived from its benchmark camera.

Speed measured from one camera can mislead: a view into a corner and a view out of a
window stress a structure differently. A view name turns the scene's camera (its
catalog preset, or the framing of its bounding box) about the camera's up axis:

``preset``     the camera as it is.
``yaw<deg>``   the camera turned ``deg`` degrees in place, about its eye: an interior
               camera looks at another wall, a doorway or a window.
``orbit<deg>`` the eye carried ``deg`` degrees around the target, looking at it: an
               exterior camera sees another side of the scene.

Positive angles turn counter-clockwise seen from above (right-handed about ``up``).
``rayaccel bench`` takes a view after a scene name: ``living_room@yaw120``.
"""

from __future__ import annotations

import math
import re

import numpy as np

from rayaccel.errors import InvalidInputError
from rayaccel.rays.camera import PinholeCamera

#: ``yaw<deg>`` or ``orbit<deg>``, the angle an optional sign and decimal digits.
_VIEW = re.compile(r"(yaw|orbit)([+-]?\d+(?:\.\d+)?)")
#: The separator between a scene and a view in a scene spec (``living_room@yaw120``).
VIEW_SEPARATOR = "@"


def parse_view(view: str) -> tuple[str, float]:
    """Return ``(pivot, degrees)`` of a view name; ``("eye", 0.0)`` for ``"preset"``.

    Raises
    ------
    InvalidInputError
        A name that is not ``preset``, ``yaw<deg>`` or ``orbit<deg>``.
    """
    if view == "preset":
        return "eye", 0.0
    match = _VIEW.fullmatch(view) if isinstance(view, str) else None
    if match is None:
        raise InvalidInputError(
            f"view: expected 'preset', 'yaw<degrees>' or 'orbit<degrees>' (e.g. yaw120), "
            f"got {view!r}"
        )
    degrees = float(match.group(2))
    if not math.isfinite(degrees):
        raise InvalidInputError(f"view: the angle must be finite, got {view!r}")
    return ("eye" if match.group(1) == "yaw" else "target"), degrees


def split_view(spec: str) -> tuple[str, str | None]:
    """Split ``"scene@view"`` into the scene and the view (None without one).

    Only a suffix that names a view is split off, so a file path holding ``@``
    elsewhere stays whole.
    """
    scene, separator, view = spec.rpartition(VIEW_SEPARATOR)
    if separator and scene and (view == "preset" or _VIEW.fullmatch(view)):
        return scene, view
    return spec, None


def turned(camera: PinholeCamera, view: str) -> PinholeCamera:
    """Return ``camera`` seen from the named ``view`` (module docstring).

    The rotation is about the camera's ``up`` axis through its eye (``yaw``) or its
    target (``orbit``); ``up``, the field of view and the resolution are kept.
    """
    pivot, degrees = parse_view(view)
    if degrees == 0.0:
        return camera
    axis = np.asarray(camera.up, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    eye = np.asarray(camera.eye, dtype=np.float64)
    target = np.asarray(camera.target, dtype=np.float64)
    centre = eye if pivot == "eye" else target
    rotation = _rotation(axis, math.radians(degrees))
    new_eye = centre + rotation @ (eye - centre)
    new_target = centre + rotation @ (target - centre)
    return PinholeCamera(
        tuple(new_eye.tolist()), tuple(new_target.tolist()), camera.up, camera.fov_deg,
        camera.width, camera.height,
    )  # fmt: skip


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Return the 3×3 matrix rotating by ``angle`` radians about the unit ``axis``.

    Rodrigues' formula: ``I + sin(a) K + (1 - cos(a)) K²`` with ``K`` the cross-product
    matrix of ``axis``.
    """
    x, y, z = axis
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * (cross @ cross)
