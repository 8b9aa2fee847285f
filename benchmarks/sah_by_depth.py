"""Where a tree's SAH cost sits: inner and leaf cost per band of node depth.

Each node contributes ``C_inner·A(n)/A(root)`` (inner) or ``C_prim·N(n)·A(n)/A(root)``
(leaf), the terms of the SAH cost (C_inner 1.2, C_prim 1); the sums per depth band
show at which levels two builders differ (``docs/performance.md``, "Why PLOC beats
top-down SAH here").

    RAYACCEL_SCENE_PATH=../shared/scenes python benchmarks/sah_by_depth.py kitchen \\
        bvh2.binned_sah bvh2.ploc bvh2.binned_sah+reinsert
"""

from __future__ import annotations

import argparse

import numpy as np

import rayaccel

BANDS = ((0, 4), (4, 8), (8, 12), (12, 16), (16, 20), (20, 10**6))


def cost_by_depth(bvh, inner_cost: float = 1.2, prim_cost: float = 1.0) -> list[tuple]:
    """Return ``[(inner, leaf), ...]`` per band of :data:`BANDS`, then the total."""
    extent = bvh.node_hi.astype(np.float64) - bvh.node_lo
    area = extent[:, 0] * extent[:, 1] + extent[:, 1] * extent[:, 2] + extent[:, 2] * extent[:, 0]
    area = area / area[0]
    inner = bvh.node_count == 0
    cost = np.where(inner, inner_cost * area, prim_cost * area * bvh.node_count)
    depth = bvh.depths()
    rows = []
    for low, high in BANDS:
        band = (depth >= low) & (depth < high)
        rows.append((float(cost[band & inner].sum()), float(cost[band & ~inner].sum())))
    return [*rows, (float(cost.sum()),)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("keys", nargs="+")
    args = parser.parse_args()
    mesh = rayaccel.scenes.get(args.scene)
    head = [f"{low}–{high - 1}" if high < 10**6 else f"≥ {low}" for low, high in BANDS]
    print("| key | " + " | ".join(head) + " | total |")
    print("|---" * (len(head) + 2) + "|")
    for key in args.keys:
        rows = cost_by_depth(rayaccel.build(mesh, key).structure)
        cells = [f"{a:.2f} / {b:.2f}" for a, b in rows[:-1]]
        print(f"| {key} | " + " | ".join(cells) + f" | {rows[-1][0]:.2f} |")


if __name__ == "__main__":
    main()
