"""Check one peer against the oracle on every standard ray set; print OK (run as a script).

``tests/bench/test_harness.py`` runs it in a subprocess per peer: the peers hold native
objects (Embree scenes, Open3D tensors, Dr.Jit variables, Warp meshes) whose teardown in
the test process's garbage collector is not theirs to order, so they live and die here.
"""

from __future__ import annotations

import sys

import numpy as np

from rayaccel.bench import harness, peers
from rayaccel.bench.raysets import standard_raysets
from rayaccel.scene import catalog


def main(name: str) -> int:
    peer = peers.get_peer(name)
    if not peer.available():
        print(f"UNAVAILABLE {peer.unavailable_reason()}")
        return 0
    mesh = catalog.get("cornell-box")
    sets = standard_raysets(mesh, "cornell-box", width=8, height=8, seed=1)
    peer.build(mesh)
    for kind, rayset in sets.items():
        ref = harness.reference_hits(mesh, rayset, 64, 0)
        rays = peer.prepare(ref.rays)  # 64 rays: more than one trimesh chunk
        if rayset.query == "any":
            prim = np.where(peer.occluded(rays), 0, -1)
            bad = harness.count_mismatches(ref, "any", None, prim, harness.RTOL_PEER)
        else:
            t, prim = peer.intersect(rays)
            bad = harness.count_mismatches(ref, "closest", t, prim, harness.RTOL_PEER)
        print(f"{kind} mismatches {bad}")
        if bad:
            return 1
    print("OK")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
