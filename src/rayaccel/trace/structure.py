"""The structure protocol: what every family's canonical structure offers the layers above.

pbrt keeps one aggregate interface over every accelerator; ours is this protocol, so
:mod:`rayaccel.api`, :mod:`rayaccel.bench`, :mod:`rayaccel.render` and the CLI handle a
BVH, a kd-tree or a grid without naming one. A builder returns a structure; the
registered traversals of the same structure key trace it.

Quality metrics beyond ``info()`` are optional (:class:`QualityMetrics`): the end-point
overlap and leaf count variability of Aila, Karras & Laine 2013 are defined for
hierarchies of boxes, not for grids.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Structure(Protocol):
    """A canonical acceleration structure built over a mesh's triangles."""

    def validate(self, triangles: np.ndarray | None = None) -> None:
        """Check every documented invariant; raise ``StructureInvariantError`` if one breaks.

        ``triangles`` (``(n, 3, 3)`` float32) enables the checks that need geometry
        (every primitive inside the bounds that list it).
        """

    def nbytes(self) -> int:
        """Return the size in bytes of the canonical arrays."""

    def info(self, inner_cost: float = 1.2, prim_cost: float = 1.0) -> dict[str, Any]:
        """Return counts and static quality figures (e.g. ``n_nodes``, ``depth``, ``sah``).

        ``inner_cost`` and ``prim_cost`` are the SAH constants of a traversal step and a
        primitive test (Aila et al. 2013: 1.2 and 1), for structures whose cost model
        uses them.
        """


@runtime_checkable
class QualityMetrics(Protocol):
    """Optional ray-independent and ray-dependent quality metrics of a structure."""

    def quality(
        self,
        triangles: np.ndarray,
        *,
        epo: bool = False,
        segments: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
        inner_cost: float = 1.2,
        prim_cost: float = 1.0,
    ) -> dict[str, Any]:
        """Return the requested metrics.

        Parameters
        ----------
        triangles : (n, 3, 3) float32 ndarray
            Corners of the mesh's triangles (``TriangleMesh.triangles()``).
        epo : bool
            Include ``"epo"``, the end-point overlap.
        segments : (origin, direction, tmin, t_hit), optional
            Ray segments (each ray up to its closest hit); include ``"lcv"`` (leaf count
            variability) and ``"mean_leaves_per_ray"`` over them.
        inner_cost, prim_cost : float
            The SAH constants.
        """
