"""Area lights of the path tracer: emitting triangles, sampled by power for next-event estimation.

Next-event estimation (Pharr, Jakob & Humphreys, *PBR* 4th ed. §13.4) picks one
light triangle per shading point with probability proportional to its power
(luminance of its radiance × area) and a point uniformly on it (Turk 1990,
``(1 − √u₁, √u₁·(1 − u₂), √u₁·u₂)`` barycentrics), so the pdf per unit area is
``p_tri / area``. Lights emit from both sides.

The emitters are the scene's emissive triangles (:class:`~rayaccel.render.materials.Materials`)
or, for a scene without any, one square *virtual* light facing down a given axis at
a given point: it lights the scene but is not geometry, so camera and bounce rays
never see it and shadow rays are not stopped by it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from rayaccel.errors import InvalidInputError
from rayaccel.render.materials import Materials
from rayaccel.scene.mesh import TriangleMesh

F64Array = npt.NDArray[np.float64]

#: Rec. 709 luminance weights, for choosing lights by power.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True, slots=True, eq=False)
class AreaLights:
    """Emitting triangles with their sampling table.

    Attributes
    ----------
    triangles : (L, 3, 3) float64
        Corner positions.
    emission : (L, 3) float64
        Emitted radiance per triangle.
    cdf : (L,) float64
        Cumulative probability of choosing each triangle (the last is 1).
    area : (L,) float64
        Areas.
    virtual : bool
        True when the lights are not part of the scene's geometry.
    """

    triangles: F64Array
    emission: F64Array
    cdf: F64Array
    area: F64Array
    virtual: bool = False

    @classmethod
    def from_triangles(
        cls, triangles: npt.ArrayLike, emission: npt.ArrayLike, *, virtual: bool = False
    ) -> AreaLights:
        """Build the sampling table over ``triangles`` emitting ``emission``.

        Raises
        ------
        InvalidInputError
            On bad shapes, non-finite values, or lights of zero total power.
        """
        tri = np.ascontiguousarray(triangles, dtype=np.float64)
        radiance = np.ascontiguousarray(emission, dtype=np.float64)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3) or radiance.shape != (tri.shape[0], 3):
            raise InvalidInputError(
                f"lights: expected (L, 3, 3) triangles and (L, 3) emission, got {tri.shape} "
                f"and {radiance.shape}"
            )
        if not (np.isfinite(tri).all() and np.isfinite(radiance).all()) or (radiance < 0).any():
            raise InvalidInputError("lights: triangles and emission must be finite, emission >= 0")
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        power = area * (radiance @ LUMINANCE)
        if tri.shape[0] == 0 or not power.sum() > 0:
            raise InvalidInputError("lights: no light with positive area and emission")
        cdf = np.cumsum(power) / power.sum()
        cdf[-1] = 1.0
        return cls(tri, radiance, cdf, area, virtual)

    @classmethod
    def from_materials(cls, mesh: TriangleMesh, materials: Materials) -> AreaLights | None:
        """Return the scene's emissive triangles as lights, or None when nothing emits."""
        if materials.n_triangles != mesh.n_triangles:
            raise InvalidInputError(
                f"materials describe {materials.n_triangles} triangles, the mesh has "
                f"{mesh.n_triangles}"
            )
        rows = materials.emissive()
        if rows.size == 0:
            return None
        tri = mesh.triangles()[rows]
        radiance = materials.emission[rows]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        if not (area > 0).any():
            return None
        keep = area > 0
        return cls.from_triangles(tri[keep], radiance[keep])

    @classmethod
    def virtual_square(
        cls, center: npt.ArrayLike, facing: npt.ArrayLike, size: float, radiance: float
    ) -> AreaLights:
        """Return a square light of side ``size`` at ``center`` whose normal is ``facing``.

        Two triangles emitting a white ``radiance``; not part of any mesh.
        """
        c = np.asarray(center, dtype=np.float64)
        n = np.asarray(facing, dtype=np.float64)
        if c.shape != (3,) or n.shape != (3,) or not np.linalg.norm(n) > 0:
            raise InvalidInputError("virtual light: center and facing must be (3,), facing != 0")
        if not (np.isfinite(size) and size > 0 and np.isfinite(radiance) and radiance > 0):
            raise InvalidInputError("virtual light: size and radiance must be finite and > 0")
        n = n / np.linalg.norm(n)
        helper = np.eye(3)[int(np.argmin(np.abs(n)))]
        a = np.cross(n, helper)
        a *= 0.5 * size / np.linalg.norm(a)
        b = np.cross(n, a)
        corners = [c - a - b, c + a - b, c + a + b, c - a + b]
        tri = np.array([[corners[0], corners[1], corners[2]], [corners[0], corners[2], corners[3]]])
        return cls.from_triangles(tri, np.full((2, 3), float(radiance)), virtual=True)

    @property
    def n_lights(self) -> int:
        """Number of light triangles."""
        return int(self.triangles.shape[0])


def default_virtual_light(
    mesh: TriangleMesh, point: npt.ArrayLike, up: npt.ArrayLike
) -> AreaLights:
    """Return a virtual square light at ``point`` facing ``-up``, sized to the scene.

    The side is 5% of the scene's diagonal ``D``. The radiance makes the irradiance
    of a surface facing the light at the distance ``d`` from the light to the scene's
    centre (at least ``D/4``) about π, so a white diffuse surface there reflects a
    radiance of about 1 before tone mapping (``E ≈ L·A/d²`` for a small light).
    """
    lo, hi = (np.asarray(b, dtype=np.float64) for b in mesh.bounds())
    diagonal = float(np.linalg.norm(hi - lo)) or 1.0
    size = 0.05 * diagonal
    distance = max(float(np.linalg.norm(np.asarray(point) - 0.5 * (lo + hi))), 0.25 * diagonal)
    radiance = np.pi * distance**2 / size**2
    return AreaLights.virtual_square(point, -np.asarray(up, dtype=np.float64), size, radiance)
