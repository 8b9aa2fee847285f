"""Heatmaps of per-ray traversal counters, on one shared logarithmic colour scale.

An instrumented trace (``stats=True``) returns one counter value per ray; primary
rays are emitted row-major from the top-left pixel, so ``hits.stats[metric]
.reshape(height, width)`` is the picture (STYLE §4.4). Traversal cost spans
orders of magnitude (a ray through empty space visits one node, a grazing ray
near a dense object thousands), so values are mapped on a **logarithmic** scale::

    s = (log v - log vmin) / (log vmax - log vmin),  clipped to [0, 1]

Values at or below ``vmin`` (zero included: rays that did no work) get the first
colour, values at or above ``vmax`` the last. The colour of ``s`` is a
piecewise-linear interpolation, in sRGB byte space, of the seven stops of
:data:`GRADIENT`: black → blue → cyan → green → yellow → red → white at equal
spacing. Brightness grows monotonically except around blue, so black reads as
"no work" and white as "the most work", and the hue changes between stops make
factors of two easy to tell apart (the thermal scale of Wald et al.'s and
Aila & Laine's cost pictures).

To compare several structures, fit **one** :class:`HeatScale` over all their
images (:meth:`HeatScale.fit`), colour each with it and write a single separate
legend (:func:`legend_image`: the gradient bar with tick labels in counter units,
titled with the metric). PNG files are written atomically (:func:`write_png`).
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rayaccel import registry
from rayaccel._atomic import write_bytes_atomic
from rayaccel.api import Accel
from rayaccel.counters import COUNTER_NAMES
from rayaccel.errors import InvalidInputError
from rayaccel.rays.camera import PinholeCamera

U8Array = npt.NDArray[np.uint8]
F64Array = npt.NDArray[np.float64]

#: Colour stops ``(position, (r, g, b))`` of the heatmap gradient, position in [0, 1].
GRADIENT: tuple[tuple[float, tuple[int, int, int]], ...] = (
    (0.0 / 6.0, (0, 0, 0)),  # black: no work
    (1.0 / 6.0, (0, 0, 255)),  # blue
    (2.0 / 6.0, (0, 255, 255)),  # cyan
    (3.0 / 6.0, (0, 255, 0)),  # green
    (4.0 / 6.0, (255, 255, 0)),  # yellow
    (5.0 / 6.0, (255, 0, 0)),  # red
    (6.0 / 6.0, (255, 255, 255)),  # white: the most work
)

#: What one unit of each counter is, for legend titles and tick labels.
COUNTER_UNITS: dict[str, str] = {
    "steps": "traversal steps",
    "nodes": "nodes visited",
    "box_tests": "box tests",
    "prim_tests": "triangle tests",
    "stack_peak": "stack entries",
    "bytes": "bytes fetched",
}


def counter_unit(metric: str) -> str:
    """Return the unit label of a counter (its name with spaces for unknown counters)."""
    return COUNTER_UNITS.get(metric, metric.replace("_", " "))


def check_metric(metric: str) -> str:
    """Return ``metric`` if it is a counter name, else raise ``InvalidInputError``."""
    if metric not in COUNTER_NAMES:
        raise InvalidInputError(
            f"metric: expected one of {', '.join(COUNTER_NAMES)}, got {metric!r}"
        )
    return metric


@dataclass(frozen=True, slots=True)
class HeatScale:
    """A colour scale shared by every image of one comparison.

    Parameters
    ----------
    metric : str
        Counter name, used in the legend title.
    vmin, vmax : float
        Values mapped to the first and the last colour; ``vmax > vmin``, and
        ``vmin > 0`` on a log scale.
    log : bool
        Logarithmic (default) or linear mapping.

    Raises
    ------
    InvalidInputError
        On non-finite bounds, ``vmax <= vmin`` or ``vmin <= 0`` with ``log``.
    """

    metric: str
    vmin: float
    vmax: float
    log: bool = True

    def __post_init__(self) -> None:
        vmin, vmax = float(self.vmin), float(self.vmax)
        if not (math.isfinite(vmin) and math.isfinite(vmax)):
            raise InvalidInputError(f"scale: expected finite bounds, got [{vmin}, {vmax}]")
        if not vmax > vmin:
            raise InvalidInputError(f"scale: expected vmax > vmin, got [{vmin}, {vmax}]")
        if self.log and not vmin > 0.0:
            raise InvalidInputError(f"scale: a log scale needs vmin > 0, got {vmin}")
        object.__setattr__(self, "vmin", vmin)
        object.__setattr__(self, "vmax", vmax)

    @classmethod
    def fit(
        cls,
        images: Iterable[npt.ArrayLike],
        metric: str,
        *,
        vmin: float | None = None,
        vmax: float | None = None,
        log: bool = True,
    ) -> HeatScale:
        """Return the scale spanning every value of every image.

        Parameters
        ----------
        images : iterable of array_like
            Counter images (any shape) that will share the scale.
        metric : str
            Counter name.
        vmin, vmax : float, optional
            Fixed bounds (e.g. ``--scale-max``), overriding the fitted ones.
            Fitted defaults: ``vmin`` is the smallest positive value (log) or 0
            (linear), ``vmax`` the largest value; a degenerate range is widened
            to ``[vmin, 2·vmin]`` (``[0, 1]`` if everything is 0).
        log : bool
            Logarithmic (default) or linear mapping.

        Returns
        -------
        HeatScale
        """
        arrays = [np.asarray(image, dtype=np.float64).ravel() for image in images]
        values = np.concatenate(arrays) if arrays else np.zeros(0)
        values = values[np.isfinite(values)]
        positive = values[values > 0]
        if vmin is None:
            if log:
                vmin = float(positive.min()) if positive.size else 1.0
            else:
                vmin = float(min(values.min(), 0.0)) if values.size else 0.0
        if vmax is None:
            vmax = float(values.max()) if values.size else 0.0
            if not vmax > vmin:
                vmax = 2.0 * vmin if vmin > 0 else vmin + 1.0
        return cls(metric, float(vmin), float(vmax), log)

    def normalize(self, values: npt.ArrayLike) -> F64Array:
        """Map values to ``[0, 1]`` (log or linear, clipped; NaN maps to 0).

        Parameters
        ----------
        values : array_like of float
            Counter values, any shape.

        Returns
        -------
        ndarray of float64, same shape
        """
        v = np.asarray(values, dtype=np.float64)
        if self.log:
            lo, hi = math.log(self.vmin), math.log(self.vmax)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (np.log(np.maximum(v, self.vmin)) - lo) / (hi - lo)
        else:
            s = (v - self.vmin) / (self.vmax - self.vmin)
        return np.clip(np.nan_to_num(s, nan=0.0), 0.0, 1.0)

    def ticks(self, max_ticks: int = 9) -> list[float]:
        """Return tick values inside ``[vmin, vmax]``, both ends included.

        On a log scale: the 1-2-5 sequence per decade, thinned to powers of ten
        when that gives more than ``max_ticks``. On a linear scale: about
        ``max_ticks`` round values. Inner ticks closer than 7% of the bar to an
        end are dropped so labels do not overlap.
        """
        if self.log:
            lo = math.floor(math.log10(self.vmin))
            hi = math.ceil(math.log10(self.vmax))
            for mantissas in ((1.0, 2.0, 5.0), (1.0,)):
                inner = [
                    m * 10.0**e
                    for e in range(lo, hi + 1)
                    for m in mantissas
                    if self.vmin * 1.05 < m * 10.0**e < self.vmax / 1.05
                ]
                if len(inner) + 2 <= max_ticks:
                    break
            if len(inner) + 2 > max_ticks:  # many decades: every k-th power of ten
                stride = math.ceil(len(inner) / max(max_ticks - 2, 1))
                inner = inner[::stride]
        else:
            span = self.vmax - self.vmin
            raw = span / max(max_ticks - 1, 1)
            magnitude = 10.0 ** math.floor(math.log10(raw))
            step = next(m * magnitude for m in (1.0, 2.0, 5.0, 10.0) if m * magnitude >= raw)
            first = math.ceil(self.vmin / step) * step
            inner = [
                first + k * step
                for k in range(int(span / step) + 2)
                if self.vmin + 0.05 * step < first + k * step < self.vmax - 0.05 * step
            ]
        # Keep labels of inner ticks from running into the end labels
        position = self.normalize(inner) if inner else np.zeros(0)
        inner = [t for t, p in zip(inner, position, strict=True) if 0.07 < p < 0.93]
        return [self.vmin, *inner, self.vmax]

    @property
    def title(self) -> str:
        """Legend title: the metric, its unit per ray and the scale kind."""
        kind = "log scale" if self.log else "linear scale"
        return f"{self.metric}: {counter_unit(self.metric)} per ray ({kind})"


def format_value(value: float) -> str:
    """Format a counter value compactly: ``3``, ``2.5``, ``12k``, ``1.5M``."""
    magnitude = abs(value)
    for limit, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if magnitude >= limit:
            return f"{value / limit:.3g}{suffix}"
    return f"{value:.3g}"


def colorize(values: npt.ArrayLike, scale: HeatScale) -> U8Array:
    """Colour values with the :data:`GRADIENT` on ``scale``.

    Parameters
    ----------
    values : array_like of float, shape ``S``
        Counter values.
    scale : HeatScale
        The scale that maps them to ``[0, 1]`` along the gradient.

    Returns
    -------
    ndarray of uint8, shape ``S + (3,)``
        sRGB colours.
    """
    s = scale.normalize(values)
    positions = np.array([stop[0] for stop in GRADIENT])
    colours = np.array([stop[1] for stop in GRADIENT], dtype=np.float64)
    channels = [np.interp(s, positions, colours[:, c]) for c in range(3)]
    return np.rint(np.stack(channels, axis=-1)).astype(np.uint8)


def counter_image(hits_stats: dict[str, Any] | None, metric: str, shape: Sequence[int]) -> F64Array:
    """Return a counter of row-major primary rays as an image.

    Parameters
    ----------
    hits_stats : dict of str to (n,) int32 ndarray
        ``hits.stats`` of an instrumented trace.
    metric : str
        Counter name (``rayaccel.COUNTER_NAMES``).
    shape : (height, width)
        Image shape; ``height · width`` must equal ``n``.

    Returns
    -------
    (height, width) float64 ndarray

    Raises
    ------
    InvalidInputError
        Unknown metric, no statistics, or a size mismatch.
    """
    check_metric(metric)
    if hits_stats is None:
        raise InvalidInputError("hits: no statistics; trace with stats=True")
    values = np.asarray(hits_stats[metric], dtype=np.float64)
    height, width = (int(x) for x in shape)
    if values.size != height * width:
        raise InvalidInputError(
            f"shape: {height}x{width} image needs {height * width} rays, got {values.size}"
        )
    return values.reshape(height, width)


def trace_counters(
    accel: Accel,
    camera: PinholeCamera,
    metric: str,
    *,
    traversal: str | None = None,
    query: str = "closest",
) -> F64Array:
    """Trace the camera's primary rays with statistics and return one counter as an image.

    Parameters
    ----------
    accel : Accel
        The structure to trace.
    camera : PinholeCamera
        Its rays are traced in row-major pixel order.
    metric : str
        Counter name (``rayaccel.COUNTER_NAMES``).
    traversal : str, optional
        Traversal registry key; default: the structure's default (reference) traversal,
        e.g. ``bvh2.stack``, whose counters the study reports (not the fastest one that
        queries naming no traversal use).
    query : {"closest", "any"}
        Closest-hit or any-hit rays.

    Returns
    -------
    (camera.height, camera.width) float64 ndarray
    """
    check_metric(metric)
    key = traversal or registry.default_traversal(accel.structure_name)
    hits = accel.trace(camera.rays(), query=query, traversal=key, stats=True)
    return counter_image(hits.stats, metric, camera.shape)


def heatmap_image(values: npt.ArrayLike, scale: HeatScale) -> U8Array:
    """Return the ``(h, w, 3)`` uint8 heatmap of a ``(h, w)`` counter image."""
    array = np.asarray(values)
    if array.ndim != 2:
        raise InvalidInputError(f"values: expected a (height, width) image, got {array.shape}")
    return colorize(array, scale)


def legend_image(scale: HeatScale, *, width: int = 640, height: int = 140) -> U8Array:
    """Draw the legend of ``scale``: gradient bar, ticks in counter units, metric as title.

    Parameters
    ----------
    scale : HeatScale
        The scale of the images the legend goes with.
    width, height : int
        Size of the image in pixels.

    Returns
    -------
    (height, width, 3) uint8 ndarray

    Notes
    -----
    The bar is coloured by :func:`colorize` itself (not by a matplotlib colormap),
    so the legend matches the images pixel for pixel; matplotlib (Agg, no pyplot
    state) only lays out the ticks and the title.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if width < 64 or height < 48:
        raise InvalidInputError(f"legend size: expected at least 64x48, got {width}x{height}")
    dpi = 100.0
    figure = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(figure)
    axes = figure.add_axes((0.04, 0.38, 0.92, 0.28))
    # Sample the bar uniformly in normalised position, then map back to values
    s = np.linspace(0.0, 1.0, 512)
    if scale.log:
        lo, hi = math.log(scale.vmin), math.log(scale.vmax)
        bar_values = np.exp(lo + s * (hi - lo))
    else:
        bar_values = scale.vmin + s * (scale.vmax - scale.vmin)
    bar = colorize(bar_values, scale)[None, :, :]
    axes.imshow(bar, aspect="auto", extent=(0.0, 1.0, 0.0, 1.0), interpolation="nearest")
    ticks = scale.ticks()
    axes.set_xticks([float(x) for x in scale.normalize(ticks)])
    axes.set_xticklabels([format_value(t) for t in ticks], fontsize=9)
    axes.set_yticks([])
    axes.set_xlim(0.0, 1.0)
    axes.set_title(scale.title, fontsize=10)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[:height, :width, :3])


def write_png(path: str | os.PathLike[str], image: npt.ArrayLike) -> Path:
    """Write an ``(h, w, 3)`` or ``(h, w)`` uint8 image as PNG, atomically.

    The image is encoded into a temporary file in the destination's folder,
    flushed and ``fsync``-ed, then moved over the destination with
    :func:`os.replace`, so readers never see a half-written file.

    Parameters
    ----------
    path : str or path-like
        Destination; its folder must exist.
    image : array_like of uint8
        ``(h, w, 3)`` RGB or ``(h, w)`` grey pixels.

    Returns
    -------
    pathlib.Path
        The written path.
    """
    from PIL import Image

    array = np.asarray(image)
    if (
        array.dtype != np.uint8
        or array.ndim not in (2, 3)
        or (array.ndim == 3 and array.shape[2] not in (3, 4))
    ):
        raise InvalidInputError(
            f"image: expected (h, w), (h, w, 3) or (h, w, 4) uint8, got {array.dtype} {array.shape}"
        )
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(array)).save(buffer, format="PNG")
    return write_bytes_atomic(path, buffer.getvalue())
