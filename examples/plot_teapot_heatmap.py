"""
Build, intersect and see the cost
=================================

Build a BVH over the Utah teapot, cast one primary ray per pixel, cast shadow rays
from the hit points to a light, and draw how many BVH nodes each primary ray
visited: the per-ray counters every traversal can return (``stats=True``).
"""

# %%
# Build
# -----
# ``ra.build`` takes a mesh and a registry key (``rayaccel list`` shows them all).
# The teapot is procedural (Newell's 32 Bézier patches, 4,096 triangles), so no
# file is needed. The first call compiles numba kernels; later runs load them
# from the cache.
import matplotlib.pyplot as plt

import rayaccel as ra
from rayaccel.rays import from_preset
from rayaccel.render import (
    HeatScale,
    counter_image,
    heatmap_image,
    legend_image,
)

mesh = ra.scenes.get("teapot")
accel = ra.build(mesh, "bvh2.binned_sah", max_leaf_size=8)
info = accel.info()
print(
    f"{mesh.n_triangles} triangles -> {info['n_nodes']} nodes, "
    f"depth {info['depth']}, SAH cost {info['sah']:.1f}, "
    f"{info['bytes'] / 1024:.0f} KiB"
)

# %%
# Closest hits, with counters
# ---------------------------
# The scene's stored pinhole camera emits one ray per pixel, row by row from the
# top left. ``stats=True`` adds per-ray counters by name.
preset = ra.scenes.camera_preset("teapot")
camera = from_preset(preset, width=320, height=240)
rays = camera.rays()
hits = accel.intersect(rays.origin, rays.direction, stats=True)
hit = hits.prim >= 0
print(f"{hit.mean():.0%} of the pixels see the teapot")
print(
    f"per ray: {hits.stats['nodes'].mean():.1f} nodes, "
    f"{hits.stats['prim_tests'].mean():.1f} triangle tests"
)

# %%
# Any hit: shadow rays
# --------------------
# ``occluded`` answers "is anything in ``[tmin, tmax]``?" and stops at the first
# hit it finds. Directions need not be normalised: with ``tmax=1`` the segment
# ends exactly at the light.
points = rays.origin[hit] + hits.t[hit, None] * rays.direction[hit]
lo, hi = mesh.bounds()
light = hi + (hi - lo)  # a point light above and to the side
to_light = light - points
in_shadow = accel.occluded(points, to_light, tmin=1e-3, tmax=1.0)
print(f"{in_shadow.mean():.0%} of the visible points are in shadow")

# %%
# Heatmap of nodes visited
# ------------------------
# Traversal cost spans orders of magnitude, so the colour scale is logarithmic:
# black is no work, white the most. Rays grazing the silhouette and the handle
# pay the most; rays that miss the root box visit nothing.
nodes = counter_image(hits.stats, "nodes", camera.shape)
scale = HeatScale.fit([nodes], "nodes")
fig, (top, bottom) = plt.subplots(
    2, 1, figsize=(6.4, 6.2), height_ratios=(5, 1)
)
top.imshow(heatmap_image(nodes, scale))
top.set_title("nodes visited per pixel (bvh2.stack)")
bottom.imshow(legend_image(scale))
for axis in (top, bottom):
    axis.set_axis_off()
fig.tight_layout()
plt.show()

# %%
# The same image from the command line::
#
#     rayaccel render teapot --accel bvh2.binned_sah --view heatmap --metric nodes \
#         -o nodes.png --legend legend.png
