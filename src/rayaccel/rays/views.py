"""Named views: other cameras of a scene, derived from its benchmark camera.

Speed measured from one camera can mislead: a view into a corner and a view out of a
window stress a structure differently. A view turns or moves the scene's camera (its
catalog preset, or the framing of its bounding box); steps join with ``+`` and apply
in order:

``preset``      the camera as it is.
``yaw<deg>``    the camera turned ``deg`` degrees in place, about its up axis through
                its eye: an interior camera looks at another wall, a doorway or a window.
``orbit<deg>``  the eye carried ``deg`` degrees around the target, about the up axis,
                looking at it: an exterior camera sees another side of the scene.
``walk<frac>``  eye and target moved ``frac`` of the way from the eye to the target:
                ``walk0.5+yaw180`` stands halfway to the target and looks back.

Positive angles turn counter-clockwise seen from above (right-handed about ``up``).
``rayaccel bench`` takes a view after a scene name: ``living_room@walk0.5+yaw180``.
"""

from __future__ import annotations

import math
import re

import numpy as np

from rayaccel.errors import InvalidInputError
from rayaccel.rays.camera import PinholeCamera

#: One step of a view: ``yaw<deg>``, ``orbit<deg>`` or ``walk<frac>``, the number an
#: optional sign and decimal digits.
_STEP = re.compile(r"(yaw|orbit|walk)([+-]?\d+(?:\.\d+)?)")
#: The separator between the steps of a view.
STEP_SEPARATOR = "+"
#: The separator between a scene and a view in a scene spec (``living_room@yaw120``).
VIEW_SEPARATOR = "@"


def parse_view(view: str) -> list[tuple[str, float]]:
    """Return the ``(kind, amount)`` steps of a view name; ``[]`` for ``"preset"``.

    Raises
    ------
    InvalidInputError
        A name that is not ``preset`` or steps ``yaw<deg>``, ``orbit<deg>``,
        ``walk<frac>`` joined by ``+``.
    """
    if view == "preset":
        return []
    steps = []
    for text in view.split(STEP_SEPARATOR) if isinstance(view, str) else [None]:
        match = _STEP.fullmatch(text) if text is not None else None
        if match is None:
            raise InvalidInputError(
                "view: expected 'preset' or steps yaw<degrees>, orbit<degrees>, walk<fraction> "
                f"joined by '+' (e.g. yaw120, walk0.5+yaw180), got {view!r}"
            )
        amount = float(match.group(2))
        if not math.isfinite(amount):
            raise InvalidInputError(f"view: {text!r} is not a finite number")
        steps.append((match.group(1), amount))
    return steps


def split_view(spec: str) -> tuple[str, str | None]:
    """Split ``"scene@view"`` into the scene and the view (None without one).

    Only a suffix that names a view is split off, so a file path holding ``@``
    elsewhere stays whole.
    """
    scene, separator, view = spec.rpartition(VIEW_SEPARATOR)
    if separator and scene:
        try:
            parse_view(view)
        except InvalidInputError:
            return spec, None
        return scene, view
    return spec, None


def turned(camera: PinholeCamera, view: str) -> PinholeCamera:
    """Return ``camera`` seen from the named ``view`` (module docstring).

    Rotations are about the camera's ``up`` axis, through its eye (``yaw``) or its
    target (``orbit``); ``up``, the field of view and the resolution are kept.
    """
    steps = parse_view(view)
    if not steps:
        return camera
    axis = np.asarray(camera.up, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    eye = np.asarray(camera.eye, dtype=np.float64)
    target = np.asarray(camera.target, dtype=np.float64)
    for kind, amount in steps:
        if kind == "walk":
            shift = amount * (target - eye)
            eye, target = eye + shift, target + shift
            continue
        centre = eye if kind == "yaw" else target
        rotation = _rotation(axis, math.radians(amount))
        eye, target = centre + rotation @ (eye - centre), centre + rotation @ (target - centre)
    return PinholeCamera(
        tuple(eye.tolist()), tuple(target.tolist()), camera.up, camera.fov_deg,
        camera.width, camera.height,
    )  # fmt: skip


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Return the 3×3 matrix rotating by ``angle`` radians about the unit ``axis``.

    Rodrigues' formula: ``I + sin(a) K + (1 - cos(a)) K²`` with ``K`` the cross-product
    matrix of ``axis``.
    """
    x, y, z = axis
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    rotation: np.ndarray = np.eye(3) + math.sin(angle) * cross
    rotation += (1.0 - math.cos(angle)) * (cross @ cross)
    return rotation
