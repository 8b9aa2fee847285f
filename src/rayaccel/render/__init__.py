"""Pictures of scenes and of traversal cost (layer 7).

* :mod:`rayaccel.render.heatmap`: per-ray counter heatmaps on one shared
  logarithmic colour scale, a separate legend image, atomic PNG writing.
* :mod:`rayaccel.render.shading`: a shaded preview (normal-tinted headlight
  shading with optional ambient occlusion).
"""

from __future__ import annotations

from rayaccel.render.heatmap import (
    GRADIENT,
    HeatScale,
    colorize,
    counter_image,
    heatmap_image,
    legend_image,
    trace_counters,
    write_png,
)
from rayaccel.render.shading import shade

__all__ = [
    "GRADIENT",
    "HeatScale",
    "colorize",
    "counter_image",
    "heatmap_image",
    "legend_image",
    "shade",
    "trace_counters",
    "write_png",
]
