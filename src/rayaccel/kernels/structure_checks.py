"""Checks shared by the ``validate`` methods of every family's canonical structure.

Plain numpy, no kernels: a structure's ``validate`` checks its own layout, then hands
the references it lists to these helpers, so the families raise the same errors
(prefixed with the family's name) for the same breakage.
"""

from __future__ import annotations

import numpy as np

from rayaccel.errors import StructureInvariantError


def check_prims_listed(prim_index: np.ndarray, n_prims: int, family: str) -> None:
    """Raise :class:`StructureInvariantError` unless ``prim_index`` lists each primitive.

    Every entry must lie in ``[0, n_prims)`` and every primitive must be listed at
    least once (by some leaf). ``family`` prefixes the message (``"bvh2"``, ``"kdtree"``).
    """
    if prim_index.size and (prim_index.min() < 0 or prim_index.max() >= n_prims):
        raise StructureInvariantError(f"{family}: prim_index entry out of range [0, n_prims)")
    referenced = np.zeros(n_prims, dtype=bool)
    referenced[prim_index] = True
    if not referenced.all():
        raise StructureInvariantError(
            f"{family}: primitive {int(np.argmin(referenced))} is in no leaf"
        )
