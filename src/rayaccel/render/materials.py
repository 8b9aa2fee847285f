"""Surface materials of the path tracer: a diffuse albedo and an emitted radiance per triangle.

The path tracer (:mod:`rayaccel.render.path`) shades every surface as Lambertian
(reflectance ``albedo / π``) and treats triangles with a non-zero ``emission`` as
area lights. Materials come from, in this order:

- the built-in Cornell box (``cornell-box``): the classic red, green and white
  walls and the ceiling light, with the reflectances and the light's radiance of
  Morgan McGuire's ``CornellBox-Original.mtl`` (McGuire 2017, Computer Graphics
  Archive), part by part (:data:`rayaccel.scene.procedural.CORNELL_BOX_PARTS`);
- an OBJ file's material library: ``usemtl`` assigns each face's triangles the
  named material, whose ``Kd`` is the albedo and ``Ke`` the emission (Wavefront MTL);
- otherwise every triangle gets :data:`DEFAULT_ALBEDO` and emits nothing (PLY files
  carry geometry only); the scene is then lit by a light the caller places
  (:mod:`rayaccel.render.lights`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from rayaccel.dtypes import REAL
from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.scene.procedural import CORNELL_BOX_PARTS

FloatArray = npt.NDArray[np.float32]

#: Albedo of every triangle of a scene file without materials (a light grey).
DEFAULT_ALBEDO = 0.7

#: The Cornell box's materials (``CornellBox-Original.mtl``): albedo, emission.
_WHITE = (0.725, 0.71, 0.68)
_CORNELL: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "floor": (_WHITE, (0.0, 0.0, 0.0)),
    "light": ((0.78, 0.78, 0.78), (17.0, 12.0, 4.0)),
    "ceiling": (_WHITE, (0.0, 0.0, 0.0)),
    "back_wall": (_WHITE, (0.0, 0.0, 0.0)),
    "right_wall": ((0.14, 0.45, 0.091), (0.0, 0.0, 0.0)),
    "left_wall": ((0.63, 0.065, 0.05), (0.0, 0.0, 0.0)),
    "short_block": (_WHITE, (0.0, 0.0, 0.0)),
    "tall_block": (_WHITE, (0.0, 0.0, 0.0)),
}


@dataclass(frozen=True, slots=True, eq=False)
class Materials:
    """Per-triangle diffuse albedo and emitted radiance.

    Attributes
    ----------
    albedo : (F, 3) float32
        Diffuse reflectance per triangle and RGB channel, in ``[0, 1]``.
    emission : (F, 3) float32
        Emitted radiance per triangle (both sides), ``>= 0``.
    source : str
        Where they came from (``"cornell-box"``, the MTL file's name, ``"default"``).
    """

    albedo: FloatArray
    emission: FloatArray
    source: str = "default"

    def __post_init__(self) -> None:
        for name in ("albedo", "emission"):
            value = np.ascontiguousarray(getattr(self, name), dtype=REAL)
            if value.ndim != 2 or value.shape[1] != 3:
                raise InvalidInputError(f"materials: {name} must be (F, 3), got {value.shape}")
            if not np.isfinite(value).all() or (value < 0).any():
                raise InvalidInputError(f"materials: {name} must be finite and >= 0")
            object.__setattr__(self, name, value)
        if self.albedo.shape != self.emission.shape:
            raise InvalidInputError("materials: albedo and emission differ in length")
        if (self.albedo > 1).any():
            raise InvalidInputError("materials: albedo must be <= 1 (energy conservation)")

    @classmethod
    def uniform(cls, n_triangles: int, albedo: float = DEFAULT_ALBEDO) -> Materials:
        """Every triangle grey with ``albedo``, none emitting."""
        grey = np.full((n_triangles, 3), albedo, dtype=REAL)
        return cls(grey, np.zeros_like(grey), "default")

    @property
    def n_triangles(self) -> int:
        """Number of triangles described."""
        return int(self.albedo.shape[0])

    def emissive(self) -> npt.NDArray[np.int64]:
        """Return the indices of the triangles that emit light."""
        return np.flatnonzero(self.emission.max(axis=1) > 0)


def cornell_box_materials(mesh: TriangleMesh) -> Materials:
    """Return the built-in Cornell box's materials, part by part."""
    albedo = np.empty((mesh.n_triangles, 3), dtype=REAL)
    emission = np.zeros((mesh.n_triangles, 3), dtype=REAL)
    for part, rows in CORNELL_BOX_PARTS.items():
        albedo[rows], emission[rows] = _CORNELL[part]
    return Materials(albedo, emission, "cornell-box")


def read_mtl(path: str | os.PathLike[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read a Wavefront material library: ``{name: (Kd, Ke)}`` (missing entries are 0).

    Raises
    ------
    SceneFileError
        When the file cannot be read or a ``Kd``/``Ke`` line is not three numbers.
    """
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise SceneFileError(f"{path}: cannot read the material library ({exc})") from exc
    found: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    current: str | None = None
    for number, raw in enumerate(text.splitlines(), start=1):
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        if words[0] == "newmtl" and len(words) >= 2:
            current = " ".join(words[1:])
            found[current] = (np.zeros(3), np.zeros(3))
        elif words[0] in ("Kd", "Ke") and current is not None:
            try:
                value = np.array([float(w) for w in words[1:4]])
            except ValueError:
                value = np.empty(0)
            if value.shape != (3,) or not np.isfinite(value).all():
                raise SceneFileError(f"{path}:{number}: {words[0]} needs three finite numbers")
            found[current][0 if words[0] == "Kd" else 1][:] = value
    return found


def obj_triangle_materials(path: str | os.PathLike[str]) -> tuple[list[str | None], Path | None]:
    """Return the material name of each triangle of an OBJ file, and its ``mtllib`` path.

    Triangles follow the order of the ``f`` lines, a face of ``k`` corners giving
    ``k − 2`` triangles (fan triangulation, as :func:`rayaccel.scene.io.parse_obj`).
    """
    path = Path(path)
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise SceneFileError(f"{path}: cannot read ({exc})") from exc
    names: list[str | None] = []
    current: str | None = None
    library: Path | None = None
    for raw in lines:
        words = raw.split("#", 1)[0].split()
        if not words:
            continue
        if words[0] == "usemtl":
            current = " ".join(words[1:]) or None
        elif words[0] == "mtllib" and len(words) >= 2 and library is None:
            library = path.parent / " ".join(words[1:])
        elif words[0] == "f" and len(words) >= 4:
            names += [current] * (len(words) - 3)
    return names, library


def obj_materials(path: str | os.PathLike[str], mesh: TriangleMesh) -> Materials | None:
    """Materials of an OBJ file with a material library, or None when it has none.

    Triangles without ``usemtl``, or naming a material the library lacks, get
    :data:`DEFAULT_ALBEDO`.

    Raises
    ------
    SceneFileError
        When the file's triangle count differs from ``mesh``'s (not the mesh loaded
        from this file), or the library cannot be read.
    """
    names, library = obj_triangle_materials(path)
    if library is None or not any(names):
        return None
    if len(names) != mesh.n_triangles:
        raise SceneFileError(
            f"{path}: {len(names)} triangles in the file, {mesh.n_triangles} in the mesh"
        )
    table = read_mtl(library)
    albedo = np.full((len(names), 3), DEFAULT_ALBEDO, dtype=REAL)
    emission = np.zeros((len(names), 3), dtype=REAL)
    for name, (kd, ke) in table.items():
        rows = np.array([n == name for n in names])
        albedo[rows] = np.clip(kd, 0.0, 1.0)
        emission[rows] = ke
    return Materials(albedo, emission, library.name)


def scene_materials(mesh: TriangleMesh, path: str | os.PathLike[str] | None = None) -> Materials:
    """Return a scene's materials: the Cornell box's, an OBJ file's, or uniform grey.

    Parameters
    ----------
    mesh : TriangleMesh
        The scene.
    path : path-like, optional
        The file ``mesh`` was loaded from, if any.
    """
    if mesh.name == "cornell-box" and mesh.n_triangles == CORNELL_BOX_PARTS["tall_block"].stop:
        return cornell_box_materials(mesh)
    if path is not None and Path(path).suffix.lower() == ".obj":
        found = obj_materials(path, mesh)
        if found is not None:
            return found
    return Materials.uniform(mesh.n_triangles)
