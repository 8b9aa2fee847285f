import itertools

import numpy as np
import pytest
from PIL import Image

import rayaccel
from rayaccel.errors import InvalidInputError
from rayaccel.rays.camera import from_preset
from rayaccel.render.heatmap import (
    GRADIENT,
    HeatScale,
    check_metric,
    colorize,
    format_value,
    heatmap_image,
    legend_image,
    trace_counters,
    write_png,
)
from rayaccel.render.shading import shade


@pytest.fixture(scope="module")
def box():
    mesh = rayaccel.scenes.get("cornell-box")
    accel = rayaccel.build(mesh)
    camera = from_preset(rayaccel.scenes.camera_preset("cornell-box"), 24, 16)
    return accel, camera


def test_log_scale_maps_decades_evenly():
    scale = HeatScale("nodes", 1.0, 1000.0)
    s = scale.normalize([0.0, 0.5, 1.0, 10.0, 100.0, 1000.0, 5000.0])
    np.testing.assert_allclose(s, [0, 0, 0, 1 / 3, 2 / 3, 1, 1], atol=1e-12)


def test_linear_scale():
    scale = HeatScale("nodes", 0.0, 10.0, log=False)
    np.testing.assert_allclose(scale.normalize([-1, 0, 5, 10, 20]), [0, 0, 0.5, 1, 1])


def test_gradient_stops_are_hit_exactly():
    scale = HeatScale("nodes", 1.0, 10.0**6)
    # Stop k sits at 10**k on this six-decade scale
    colours = colorize([10.0**k for k in range(7)], scale)
    assert [tuple(c) for c in colours] == [stop[1] for stop in GRADIENT]
    assert tuple(colours[0]) == (0, 0, 0)
    assert tuple(colours[-1]) == (255, 255, 255)


def test_shared_scale_gives_equal_values_equal_colours():
    a = np.array([[1, 4], [16, 64]], dtype=float)
    b = np.array([[4, 16], [64, 256]], dtype=float)
    scale = HeatScale.fit([a, b], "nodes")
    assert (scale.vmin, scale.vmax) == (1.0, 256.0)
    ia, ib = heatmap_image(a, scale), heatmap_image(b, scale)
    # 4, 16 and 64 appear in both images: same colour on the shared scale
    assert (ia[0, 1] == ib[0, 0]).all()
    assert (ia[1, 0] == ib[0, 1]).all()
    assert (ia[1, 1] == ib[1, 0]).all()
    # Fitted alone, b's smallest value would be black; shared, it is not
    alone = heatmap_image(b, HeatScale.fit([b], "nodes"))
    assert tuple(alone[0, 0]) == (0, 0, 0)
    assert tuple(ib[0, 0]) != (0, 0, 0)


def test_fit_respects_fixed_bounds_and_degenerate_ranges():
    scale = HeatScale.fit([np.array([3.0, 7.0, 900.0])], "bytes", vmax=100.0)
    assert scale.vmax == 100.0
    assert scale.vmin == 3.0
    assert tuple(colorize([900.0], scale)[0]) == (255, 255, 255)
    flat = HeatScale.fit([np.full(4, 5.0)], "nodes")
    assert flat.vmax > flat.vmin == 5.0
    empty = HeatScale.fit([np.zeros(3)], "nodes")
    assert empty.vmin > 0
    with pytest.raises(InvalidInputError):
        HeatScale("nodes", 0.0, 10.0)
    with pytest.raises(InvalidInputError):
        HeatScale("nodes", 5.0, 5.0)


@pytest.mark.parametrize(("vmin", "vmax"), [(1, 1000), (3, 17), (1, 10**7), (12.5, 13.0)])
def test_ticks_inside_range_sorted_with_ends(vmin, vmax):
    scale = HeatScale("nodes", vmin, vmax)
    ticks = scale.ticks()
    assert ticks[0] == vmin
    assert ticks[-1] == vmax
    assert all(a < b for a, b in itertools.pairwise(ticks))
    assert len(ticks) <= 9


def test_format_value():
    assert format_value(3.0) == "3"
    assert format_value(2500.0) == "2.5k"
    assert format_value(1.5e6) == "1.5M"


def test_legend_image_shows_the_gradient():
    scale = HeatScale("nodes", 2.0, 400.0)
    legend = legend_image(scale, width=400, height=120)
    assert legend.shape == (120, 400, 3)
    assert legend.dtype == np.uint8
    pixels = legend.reshape(-1, 3).astype(int)
    for colour in ((255, 0, 0), (0, 255, 0), (0, 0, 255)):
        assert (np.abs(pixels - colour).sum(axis=1) < 40).any(), colour


def test_write_png_is_atomic_and_exact(tmp_path):
    image = np.random.default_rng(0).integers(0, 256, (7, 5, 3), dtype=np.uint8)
    path = tmp_path / "img.png"
    assert write_png(path, image) == path
    with Image.open(path) as loaded:
        assert loaded.size == (5, 7)
        np.testing.assert_array_equal(np.asarray(loaded.convert("RGB")), image)
    with pytest.raises(InvalidInputError):
        write_png(path, image.astype(np.float32))
    assert path.exists()  # the failed write left the old file alone
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img.png"]


def test_check_metric():
    assert check_metric("nodes") == "nodes"
    with pytest.raises(InvalidInputError, match="nodes"):
        check_metric("node")


def test_trace_counters_is_the_row_major_stats_image(box):
    accel, camera = box
    values = trace_counters(accel, camera, "nodes")
    assert values.shape == (16, 24)
    # The reference traversal's counters (bvh2.stack), not the fastest one's.
    hits = accel.trace(camera.rays(), traversal="bvh2.stack", stats=True)
    np.testing.assert_array_equal(values, hits.stats["nodes"].reshape(16, 24))
    assert values.min() >= 1


def test_shade_with_and_without_ambient_occlusion(box):
    accel, camera = box
    plain = shade(accel, camera)
    assert plain.shape == (16, 24, 3)
    assert plain.dtype == np.uint8
    occluded = shade(accel, camera, ao_samples=1, seed=1)
    # Occlusion only darkens (up to rounding)
    assert (occluded.astype(int) <= plain.astype(int) + 1).all()
    assert occluded.astype(int).sum() < plain.astype(int).sum()
    with pytest.raises(InvalidInputError):
        shade(accel, camera, ao_samples=-1)
