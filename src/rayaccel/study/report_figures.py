"""The pictures of a study report: bar charts of throughput and memory traffic, heatmaps.

The charts follow the MSc thesis's Figures 5.1–5.6: for one family of structures
and one ray set, grouped bars of Mrays/s per scene with one bar per system (a
builder with one of its traversals), the peers' bars hatched so that they read
as references rather than contenders; and one chart of the memory traffic per ray
(the ``bytes`` counter) of every system. They are drawn with matplotlib's
object-oriented API (:class:`~matplotlib.figure.Figure` on a
:class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`), so the report never
touches pyplot's global state or the process's backend, as
:mod:`rayaccel.render.heatmap` does.

The heatmap gallery traces each scene's primary rays through each (builder,
traversal) of the results with statistics on and colours one counter per pixel
(``nodes``; ``cells`` for grids, which visit no nodes). Every image of a scene and
counter shares one :class:`~rayaccel.render.heatmap.HeatScale`, so its colours
compare across structures, and gets one legend.

Every PNG is encoded in memory and written atomically
(:func:`rayaccel._atomic.write_bytes_atomic`).
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rayaccel._atomic import write_bytes_atomic
from rayaccel.errors import RayAccelError

#: Resolution of the charts (dots per inch of the figure size).
DPI = 100

#: Face colours of the peers' (hatched) bars: grey, so they read as references.
PEER_GREYS = ("0.85", "0.6", "0.4", "0.95")


@dataclass(frozen=True, slots=True)
class Picture:
    """One image of the report.

    Attributes
    ----------
    src : str
        File name, relative to the report's folder.
    alt : str
        Text alternative for the ``<img>``.
    width, height : int
        Size in pixels, for the ``<img>`` attributes.
    caption : str
        Figure caption (may be empty for gallery tiles).
    """

    src: str
    alt: str
    width: int
    height: int
    caption: str = ""


@dataclass(frozen=True, slots=True)
class Series:
    """One bar per group: a system's (or a peer's) values, ``None`` where missing."""

    label: str
    values: tuple[float | None, ...]
    hatched: bool = False


@dataclass(frozen=True, slots=True)
class HeatmapGroup:
    """The heatmaps of one scene and counter, on one shared scale, and their legend."""

    metric: str
    legend: Picture
    images: list[Picture]


@dataclass(frozen=True, slots=True)
class HeatmapScene:
    """The gallery of one scene: a group per counter, and what could not be drawn."""

    scene: str
    groups: list[HeatmapGroup] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def safe_name(*parts: str) -> str:
    """Return a file-name stem made of ``parts``: letters, digits, ``.``, ``_`` and ``-`` only."""
    text = "-".join(parts)
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._-") or "figure"


def bar_chart(
    path: Path, title: str, groups: Sequence[str], series: Sequence[Series], ylabel: str
) -> tuple[int, int]:
    """Draw grouped bars, one group per label of ``groups`` and one bar per series.

    Parameters
    ----------
    path : pathlib.Path
        PNG destination, written atomically.
    title : str
        Chart title.
    groups : sequence of str
        Labels along the x axis.
    series : sequence of Series
        Bars: ``series[i].values[j]`` is the bar of series ``i`` in group ``j``;
        missing values leave a gap. Hatched series are the peers.
    ylabel : str
        Label of the value axis.

    Returns
    -------
    (width, height) : tuple of int
        Size of the written image in pixels.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n_bars = max(len(series), 1)
    inches = min(max(6.5, 2.5 + 0.28 * n_bars * len(groups)), 14.0)
    figure = Figure(figsize=(inches, 3.8), dpi=DPI, layout="constrained")
    canvas = FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    x = np.arange(len(groups), dtype=np.float64)
    width = 0.8 / n_bars
    systems = peers = 0
    for i, item in enumerate(series):
        heights = [math.nan if v is None else float(v) for v in item.values]
        # Systems take the colour cycle, peers grey tones with hatching, in both cases by order
        if item.hatched:
            colour, peers = PEER_GREYS[peers % len(PEER_GREYS)], peers + 1
        else:
            colour, systems = f"C{systems % 10}", systems + 1
        axes.bar(x + (i - (n_bars - 1) / 2) * width, heights, width, label=item.label,
                 color=colour, edgecolor="black", linewidth=0.5,
                 hatch="//" if item.hatched else None)  # fmt: skip
    long_labels = len(groups) > 4 or max((len(g) for g in groups), default=0) > 14
    axes.set_xticks(x, list(groups), rotation=25 if long_labels else 0,
                    ha="right" if long_labels else "center", fontsize=9)  # fmt: skip
    axes.set_ylabel(ylabel)
    axes.set_title(title, fontsize=10)
    axes.grid(axis="y", linewidth=0.4, alpha=0.5)
    axes.set_axisbelow(True)
    if series:
        axes.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    write_bytes_atomic(path, buffer.getvalue())
    size = canvas.get_width_height()
    return int(size[0]), int(size[1])


def heatmap_gallery(
    pairs: dict[str, list[tuple[str, str]]],
    out_dir: Path,
    *,
    width: int = 160,
    height: int = 120,
) -> list[HeatmapScene]:
    """Trace and write the heatmaps of every scene and (builder, traversal) pair.

    Parameters
    ----------
    pairs : dict of str to list of (str, str)
        For each scene, the (builder, traversal) pairs to draw, in report order.
    out_dir : pathlib.Path
        Folder of the PNG files (``heat-*.png``).
    width, height : int
        Resolution of each heatmap (the benchmark camera of the scene).

    Returns
    -------
    list of HeatmapScene
        One per scene, with a note for every scene or pair that could not be drawn
        (a scene file that is absent here, a builder that fails).

    Notes
    -----
    This builds every structure again and compiles the instrumented kernels of
    any traversal not yet compiled; its cost is that of ``rayaccel render --view
    heatmap`` per pair.
    """
    from rayaccel import api
    from rayaccel.bench.raysets import scene_camera
    from rayaccel.render.heatmap import (
        HeatScale,
        heatmap_image,
        legend_image,
        trace_counters,
        write_png,
    )
    from rayaccel.scene import catalog

    gallery: list[HeatmapScene] = []
    for number, (scene, scene_pairs) in enumerate(pairs.items()):
        entry = HeatmapScene(scene)
        gallery.append(entry)
        try:
            mesh = catalog.get(scene)
            camera, _ = scene_camera(mesh, scene, width=width, height=height)
        except RayAccelError as exc:
            entry.notes.append(f"{scene}: not drawn ({exc})")
            continue
        accels: dict[str, api.Accel] = {}
        traced: dict[str, list[tuple[str, str, np.ndarray]]] = {}
        for builder, traversal in scene_pairs:
            try:
                if builder not in accels:
                    accels[builder] = api.build(mesh, builder)
                accel = accels[builder]
                metric = "cells" if accel.structure_name == "grid" else "nodes"
                values = trace_counters(accel, camera, metric, traversal=traversal)
            except RayAccelError as exc:
                entry.notes.append(f"{builder} + {traversal}: not drawn ({exc})")
                continue
            traced.setdefault(metric, []).append((builder, traversal, values))
        for metric, items in traced.items():
            # One scale per scene and counter, so the scene's images compare
            scale = HeatScale.fit([values for _, _, values in items], metric)
            stem = safe_name("heat", str(number), scene, metric)
            legend_name = f"{stem}-legend.png"
            write_png(out_dir / legend_name, legend_image(scale, width=480, height=110))
            legend = Picture(legend_name, f"legend: {scale.title}", 480, 110)
            images = []
            for k, (builder, traversal, values) in enumerate(items):
                name = f"{stem}-{k}.png"
                write_png(out_dir / name, heatmap_image(values, scale))
                label = f"{builder} + {traversal}"
                images.append(Picture(name, f"{metric} per primary ray, {scene}, {label}",
                                      width, height, label))  # fmt: skip
            entry.groups.append(HeatmapGroup(metric, legend, images))
    return gallery
