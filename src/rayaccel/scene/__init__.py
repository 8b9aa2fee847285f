"""Scenes: the triangle mesh type, file loading, procedural scenes and the catalog.

``TriangleMesh`` (:mod:`~rayaccel.scene.mesh`) is what every structure is built
over; :func:`load_mesh` (:mod:`~rayaccel.scene.io`) reads OBJ, PLY, STL and glTF
files; :mod:`~rayaccel.scene.procedural` builds the Cornell box, triangle soups,
Haines' sphereflake and Newell's teapot; :mod:`~rayaccel.scene.catalog` names
them all (``get("teapot")``, ``get("kitchen")``) and stores camera presets.
"""

from __future__ import annotations

from rayaccel.scene.catalog import (
    ALIASES,
    DEFAULT_SCENE,
    SceneInfo,
    camera_preset,
    clear_cache,
    describe,
    file_scenes,
    get,
    load_cached,
    names,
    resolve,
    search_folders,
)
from rayaccel.scene.io import SUPPORTED_SUFFIXES, load_mesh, parse_obj
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.scene.procedural import (
    cornell_box,
    sphereflake,
    teapot,
    teapot_in_stadium,
    triangle_soup,
)

__all__ = [
    "ALIASES",
    "DEFAULT_SCENE",
    "SUPPORTED_SUFFIXES",
    "SceneInfo",
    "TriangleMesh",
    "camera_preset",
    "clear_cache",
    "cornell_box",
    "describe",
    "file_scenes",
    "get",
    "load_cached",
    "load_mesh",
    "names",
    "parse_obj",
    "resolve",
    "search_folders",
    "sphereflake",
    "teapot",
    "teapot_in_stadium",
    "triangle_soup",
]
