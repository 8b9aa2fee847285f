"""Refitting an acceleration structure to moved vertices, for every family.

:meth:`rayaccel.Accel.refit` calls :func:`refit_structure`: the mesh keeps its faces,
only the vertices move (an animation frame, a simulation step). What a refit can do
depends on the family:

- **BVH** (``bvh2``): the topology is kept and every box is recomputed bottom-up in
  parallel (:func:`rayaccel.bvh.builders.refit_vertices.refit_bvh2`; Wald, Boulos & Shirley
  2007). Leaves over split references (SBVH, ``+presplit``) get their triangles'
  whole boxes: conservative, still correct, a little looser than the build's clips.
  The SAH cost of the refitted tree is compared with the cost at build time; the
  ratio measures how far the topology has drifted from the geometry (Wald et al. 2007
  §4.2 rebuild when it grows), and ``rebuild_if_worse=r`` rebuilds from scratch,
  with the same builder, steps and options, once the refitted cost exceeds ``r``
  times the build-time cost.
- **kd-trees and grids**: split planes and cells are positions in space, chosen for
  the old geometry; moving a triangle changes which cells it overlaps, so there is
  nothing to refit. ``refit`` rebuilds them with the same builder and options and says
  so in its report (``"method": "rebuild"``).

Derived traversal layouts (packed rows, wide nodes, links, ropes, cell ranges) copy
boxes and triangle corners out of the canonical structure; the ``Accel`` drops them all
on a refit, and each is derived again from the refitted structure on its next use.
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rayaccel.bvh.builders.refit_vertices import (
    RefitTopology,
    refit_bvh2,
    refit_topology,
    sah_of,
)
from rayaccel.bvh.layouts.bvh2 import Bvh2
from rayaccel.bvh.precision import conservative_bvh2
from rayaccel.errors import InvalidInputError
from rayaccel.scene.mesh import TriangleMesh

#: What a rebuild returns: the new structure, its build milliseconds and per-step times.
Rebuild = Callable[[TriangleMesh], tuple[Any, float, dict[str, float]]]


@dataclass(frozen=True, slots=True)
class RefitOutcome:
    """What :func:`refit_structure` made.

    Attributes
    ----------
    mesh : TriangleMesh
        The mesh with the new vertices (same faces and name).
    structure : object
        The refitted or rebuilt structure.
    build_sah : float or None
        SAH cost at build time of the topology now held (the rebuilt tree's own cost
        after a rebuild); None for structures without a SAH cost (grids).
    rebuilt : tuple of (build_ms, step_ms), or None
        Set when the structure was rebuilt.
    report : dict
        See :meth:`rayaccel.Accel.refit`.
    """

    mesh: TriangleMesh
    structure: Any
    build_sah: float | None
    rebuilt: tuple[float, dict[str, float]] | None
    report: dict[str, Any]


def sah_cost(structure: Any) -> float | None:
    """Return the SAH cost of ``structure`` (None for structures without one, e.g. grids)."""
    if isinstance(structure, Bvh2):
        return sah_of(structure)
    method = getattr(structure, "sah_cost", None)
    return float(method()) if callable(method) else None


def can_refit(structure: Any) -> bool:
    """Whether ``structure``'s boxes can be refitted in place of a rebuild (BVHs)."""
    return isinstance(structure, Bvh2)


def check_ratio(rebuild_if_worse: object) -> float | None:
    """Validate ``rebuild_if_worse``: None, or a positive number (``inf``: never rebuild)."""
    if rebuild_if_worse is None:
        return None
    if isinstance(rebuild_if_worse, bool) or not isinstance(rebuild_if_worse, numbers.Real):
        raise InvalidInputError(
            f"rebuild_if_worse: expected None or a positive number, got {rebuild_if_worse!r}"
        )
    ratio = float(rebuild_if_worse)
    if math.isnan(ratio) or ratio <= 0.0:
        raise InvalidInputError(f"rebuild_if_worse: expected a positive ratio, got {ratio!r}")
    return ratio


def refitted_mesh(mesh: TriangleMesh, new_vertices: object) -> TriangleMesh:
    """Return ``mesh`` with ``new_vertices`` (same faces, name and precision), validated.

    Raises
    ------
    InvalidInputError
        ``new_vertices`` is not a finite ``(V, 3)`` array with the mesh's vertex count.
    """
    try:
        array = np.asarray(new_vertices)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"new_vertices: expected a (V, 3) float array, got {exc}") from exc
    expected = (mesh.n_vertices, 3)
    if array.shape != expected:
        raise InvalidInputError(
            f"new_vertices: a refit keeps the topology, so expected shape {expected} "
            f"(the mesh's vertex count), got {array.shape}"
        )
    try:
        return mesh.with_vertices(array)
    except InvalidInputError as exc:
        message = str(exc)
        if message.startswith("vertices:"):
            message = "new_" + message
        raise InvalidInputError(message) from exc


def _topology(memo: dict[str, Any] | None, bvh: Bvh2, mesh: TriangleMesh) -> RefitTopology:
    """Return ``bvh``'s refit topology from ``memo``, finding and keeping it on first use."""
    if memo is None:
        return refit_topology(bvh, mesh.faces)
    topology = memo.get("refit_topology")
    if topology is None:
        topology = memo["refit_topology"] = refit_topology(bvh, mesh.faces)
    return topology


def refit_structure(
    structure: Any,
    mesh: TriangleMesh,
    new_vertices: object,
    *,
    build_sah: float | None,
    rebuild_if_worse: object,
    rebuild: Rebuild,
    structure_name: str,
    sah_now: float | None = None,
    memo: dict[str, Any] | None = None,
) -> RefitOutcome:
    """Refit ``structure`` to ``new_vertices``, or rebuild it (see the module docstring).

    Parameters
    ----------
    structure : object
        The canonical structure built over ``mesh``.
    mesh : TriangleMesh
        The mesh it was built (or last refitted) over.
    new_vertices : (V, 3) array_like of float
        The new positions, one per vertex of ``mesh``.
    build_sah : float or None
        SAH cost of the topology at build time; None to take ``structure``'s current
        cost (it has not been refitted since it was built).
    rebuild_if_worse : float or None
        Rebuild when the refitted SAH cost exceeds this many times ``build_sah``.
    rebuild : callable
        ``rebuild(new_mesh) -> (structure, build_ms, step_ms)`` with the same builder,
        steps and options.
    structure_name : str
        The structure's registry name, for the report.
    sah_now : float, optional
        SAH cost of ``structure`` as it is, when known (the last refit's
        ``sah_after``); otherwise computed (one pass over the nodes).
    memo : dict, optional
        Kept by the caller from one refit of this topology to the next: it holds the
        :class:`~rayaccel.bvh.builders.refit_vertices.RefitTopology`, found on the first
        refit. The caller starts a new one when the structure is rebuilt.

    Returns
    -------
    RefitOutcome

    Raises
    ------
    InvalidInputError
        Bad ``new_vertices`` (shape, vertex count, NaN or inf) or ``rebuild_if_worse``.
    """
    limit = check_ratio(rebuild_if_worse)
    new_mesh = refitted_mesh(mesh, new_vertices)
    start = time.perf_counter()
    sah_before = sah_now if sah_now is not None else sah_cost(structure)
    if build_sah is None:
        build_sah = sah_before
    report: dict[str, Any] = {
        "structure": structure_name,
        "method": "refit",
        "reason": "",
        "sah_build": build_sah,
        "sah_before": sah_before,
        "sah_refit": None,
        "ratio": None,
        "rebuild_if_worse": limit,
        "refit_ms": None,
        "rebuild_ms": None,
    }
    refitted = None
    if can_refit(structure):
        refit_start = time.perf_counter()
        topology = _topology(memo, structure, new_mesh)
        if new_mesh.precision == "float64":
            # Refitted and widened to contain the float64 triangles (bvh/precision.py).
            refitted = conservative_bvh2(structure, new_mesh, topology)
        else:
            refitted = refit_bvh2(structure, new_mesh.vertices, new_mesh.faces, topology)
        report["refit_ms"] = (time.perf_counter() - refit_start) * 1e3
        sah_refit = sah_of(refitted)
        report["sah_refit"] = sah_refit
        if build_sah is not None and build_sah > 0.0:
            report["ratio"] = sah_refit / build_sah
        if limit is not None and report["ratio"] is not None and report["ratio"] > limit:
            report["method"] = "rebuild"
            report["reason"] = (
                f"refitted SAH {sah_refit:.4g} exceeds rebuild_if_worse={limit:g} x the "
                f"build-time SAH {build_sah:.4g}"
            )
    else:
        report["method"] = "rebuild"
        report["reason"] = (
            f"a {structure_name!r} cannot be refitted (its split planes or cells are "
            "positions in space), so it is rebuilt with the same builder and options"
        )
    rebuilt = None
    if report["method"] == "rebuild":
        fresh, build_ms, step_ms = rebuild(new_mesh)
        report["rebuild_ms"] = build_ms
        rebuilt = (build_ms, step_ms)
        structure_now = fresh
        build_sah = sah_cost(fresh)
    else:
        structure_now = refitted
    report["sah_after"] = build_sah if rebuilt else report["sah_refit"]
    report["ms"] = (time.perf_counter() - start) * 1e3
    return RefitOutcome(new_mesh, structure_now, build_sah, rebuilt, report)
