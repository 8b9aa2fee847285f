"""How coherent a ray batch is: the share of its packets whose rays travel together.

A packet traversal (``bvh2.packet``, Wald et al. 2001) pays off when the consecutive
rays it groups share their path through the tree: camera rays in image order, shadow
rays towards one light from neighbouring hits. It loses to a single-ray traversal on
incoherent batches such as diffuse bounces, whose neighbouring rays leave in unrelated
directions (docs/performance.md has both sides measured). :func:`packet_coherence`
looks at a fixed sample of packets of consecutive rays, spread over the batch, and
calls a packet coherent when its directions lie within a small cone and share their
signs (the packet traversal's octant) and its origins lie close together relative to
the scene. It reads a few hundred rays whatever the batch size.
"""

from __future__ import annotations

import numpy as np

from rayaccel.kernels.aabb_packet import PACKET
from rayaccel.rays.batch import RayBatch

#: Rays of a packet (``bvh2.packet``'s width).
PACKET_RAYS = PACKET
#: Packets sampled from a batch.
SAMPLED_PACKETS = 64
#: A coherent packet's directions lie within this angle of its first ray's.
MAX_ANGLE_DEGREES = 8.0
#: A coherent packet's origins lie within this fraction of the scene's diagonal of its
#: first ray's origin.
MAX_ORIGIN_SPREAD = 0.05


def packet_coherence(rays: RayBatch, scene_diagonal: float) -> float:
    """Return the share (0 to 1) of sampled packets of consecutive rays that are coherent.

    Parameters
    ----------
    rays : RayBatch
        The batch, in the order it will be traced.
    scene_diagonal : float
        Length of the scene box's diagonal, the scale of the origins' spread.

    Returns
    -------
    float
        0 for a batch smaller than one packet.
    """
    n_packets = rays.n_rays // PACKET_RAYS
    if n_packets == 0:
        return 0.0
    first = np.arange(0, n_packets, -(-n_packets // SAMPLED_PACKETS))
    rows = first[:, None] * PACKET_RAYS + np.arange(PACKET_RAYS)
    direction = rays.direction[rows]
    origin = rays.origin[rows]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        unit = direction / np.sqrt(np.einsum("pra,pra->pr", direction, direction))[..., None]
        cosine = np.min(np.einsum("pra,pa->pr", unit, unit[:, 0]), axis=1)
        offset = origin - origin[:, :1]
        spread = np.sqrt(np.max(np.einsum("pra,pra->pr", offset, offset), axis=1))
        same_signs = np.all(np.signbit(direction) == np.signbit(direction[:, :1]), axis=(1, 2))
        coherent = (
            same_signs
            & (cosine >= np.cos(np.radians(MAX_ANGLE_DEGREES)))
            & (spread <= MAX_ORIGIN_SPREAD * scene_diagonal)
        )
    return float(np.mean(coherent))
