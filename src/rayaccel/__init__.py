"""rayaccel: build, traverse, measure and compare ray tracing acceleration structures.

Quick start::

    import numpy as np, rayaccel as ra
    mesh = ra.scenes.get("cornell-box")            # or ra.load_mesh("scene.obj")
    accel = ra.build(mesh, "bvh2.binned_sah")
    hits = accel.intersect(origins, directions)     # hits.t, hits.prim, hits.u, hits.v
    blocked = accel.occluded(origins, directions, 1e-4, 1.0)
"""

from __future__ import annotations

from rayaccel import config as config
from rayaccel import registry as registry
from rayaccel.api import Accel, build, load_accel
from rayaccel.counters import COUNTER_NAMES, Counter
from rayaccel.errors import (
    AccelFileError,
    BackendUnavailableError,
    InvalidInputError,
    RayAccelError,
    SceneFileError,
    StructureInvariantError,
    TraversalOverflowError,
    UnknownVariantError,
)
from rayaccel.rays.batch import HitBatch, RayBatch
from rayaccel.scene import catalog as scenes
from rayaccel.scene.io import load_mesh
from rayaccel.scene.mesh import TriangleMesh

__version__ = "0.1.0"

__all__ = [
    "COUNTER_NAMES",
    "Accel",
    "AccelFileError",
    "BackendUnavailableError",
    "Counter",
    "HitBatch",
    "InvalidInputError",
    "RayAccelError",
    "RayBatch",
    "SceneFileError",
    "StructureInvariantError",
    "TraversalOverflowError",
    "TriangleMesh",
    "UnknownVariantError",
    "build",
    "load_accel",
    "load_mesh",
    "scenes",
]
