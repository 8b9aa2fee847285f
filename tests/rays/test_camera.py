import dataclasses
import itertools
import math

import numpy as np
import pytest

from rayaccel.errors import InvalidInputError
from rayaccel.rays import PinholeCamera, RayBatch, frame_bounds, from_preset


def _camera(width=8, height=6, fov_deg=60.0):
    return PinholeCamera(
        eye=(0.0, 0.0, 5.0),
        target=(0.0, 0.0, 0.0),
        up=(0, 1, 0),
        fov_deg=fov_deg,
        width=width,
        height=height,
    )


def test_rays_shape_dtype_and_interval():
    camera = _camera()
    rays = camera.rays()
    assert isinstance(rays, RayBatch)
    assert rays.n_rays == camera.n_pixels == 48
    assert camera.shape == (6, 8)
    for array in (rays.origin, rays.direction, rays.tmin, rays.tmax):
        assert array.dtype == np.float32
        assert array.flags.c_contiguous
    np.testing.assert_array_equal(rays.origin, np.tile([0.0, 0.0, 5.0], (48, 1)))
    assert (rays.tmin == 0).all()
    assert np.isposinf(rays.tmax).all()


def test_directions_are_normalised():
    rays = PinholeCamera((1, 2, 3), (-4, 0.5, 7), (0, 0, 1), 75.0, 33, 17).rays()
    np.testing.assert_allclose(np.linalg.norm(rays.direction, axis=1), 1.0, atol=1e-6)


def test_row_major_from_top_left():
    camera = _camera(width=8, height=6)
    image = camera.rays().direction.reshape(6, 8, 3)
    # Looking down -Z with +Y up: +X is right
    top_left, top_right = image[0, 0], image[0, -1]
    bottom_left, bottom_right = image[-1, 0], image[-1, -1]
    assert top_left[0] < 0
    assert top_left[1] > 0
    assert top_right[0] > 0
    assert top_right[1] > 0
    assert bottom_left[0] < 0
    assert bottom_left[1] < 0
    assert bottom_right[0] > 0
    assert bottom_right[1] < 0
    assert (image[..., 2] < 0).all()
    # x grows along a row, y falls down a column
    assert (np.diff(image[..., 0], axis=1) > 0).all()
    assert (np.diff(image[..., 1], axis=0) < 0).all()
    # Ray k is pixel divmod(k, width)
    flat = camera.rays().direction
    np.testing.assert_array_equal(flat[1 * 8 + 5], image[1, 5])


def test_centre_pixel_looks_along_the_view_direction():
    camera = PinholeCamera((1, 1, 1), (4, 5, 1), (0, 0, 1), 50.0, 5, 7)
    centre = camera.rays().direction.reshape(7, 5, 3)[3, 2]
    np.testing.assert_allclose(centre, [0.6, 0.8, 0.0], atol=1e-6)


def test_fov_is_vertical_and_aspect_scales_horizontal():
    fov = 60.0
    camera = _camera(width=9, height=5, fov_deg=fov)
    image = camera.rays().direction.reshape(5, 9, 3).astype(np.float64)
    half = math.tan(math.radians(fov) / 2)
    # Top-centre pixel centre sits (1 - 1/h) of the half height above the axis
    top = image[0, 4]
    np.testing.assert_allclose(top[1] / -top[2], (1 - 1 / 5) * half, rtol=1e-6)
    right = image[2, -1]
    np.testing.assert_allclose(right[0] / -right[2], (1 - 1 / 9) * half * 9 / 5, rtol=1e-6)


def test_project_returns_pixel_centres():
    camera = PinholeCamera((0.5, -2, 1), (0, 0, 0), (0, 0, 1), 40.0, 12, 7)
    rays = camera.rays()
    points = rays.origin.astype(np.float64) + 3.0 * rays.direction
    pixels, depth = camera.project(points)
    rows, cols = np.divmod(np.arange(rays.n_rays), 12)
    np.testing.assert_allclose(pixels[:, 0], cols + 0.5, atol=1e-4)
    np.testing.assert_allclose(pixels[:, 1], rows + 0.5, atol=1e-4)
    assert (depth > 0).all()
    behind, _ = camera.project([[1.0, -5.0, 1.0]])
    assert np.isnan(behind).all()


BOXES = [
    ((0, 0, 0), (1, 1, 1)),
    ((-10, 2, 3), (30, 2.5, 4)),
    ((-1e3, -1e3, -1), (1e3, 1e3, 1)),
    ((5, 5, 5), (5, 5, 50)),
]
VIEWS = [
    {},
    {"direction": (0, 0, -1)},
    {"direction": (1, -1, 0.3)},
    {"up": (0, 0, 1)},
    {"up": (1, 0, 0), "fov_deg": 20.0},
    {"up": (0, 0, 1), "direction": (-1, 2, -3), "fov_deg": 120.0},
]


@pytest.mark.parametrize(("lo", "hi"), BOXES)
@pytest.mark.parametrize("view", VIEWS)
@pytest.mark.parametrize(("width", "height"), [(64, 64), (200, 50), (30, 160)])
def test_frame_bounds_sees_every_corner(lo, hi, view, width, height):
    camera = frame_bounds(lo, hi, width=width, height=height, **view)
    assert (camera.width, camera.height) == (width, height)
    corners = np.array(list(itertools.product(*zip(lo, hi, strict=True))), dtype=np.float64)
    pixels, depth = camera.project(corners)
    assert (depth > 0).all()
    assert (pixels[:, 0] >= 0).all()
    assert (pixels[:, 0] <= width).all()
    assert (pixels[:, 1] >= 0).all()
    assert (pixels[:, 1] <= height).all()
    # The eye is outside the box
    eye = np.array(camera.eye)
    assert ((eye < np.array(lo)) | (eye > np.array(hi))).any()
    np.testing.assert_allclose(camera.target, 0.5 * (np.array(lo) + np.array(hi)))


def test_frame_bounds_default_view_is_front_right_above():
    camera = frame_bounds((0, 0, 0), (1, 1, 1), width=32, height=32)
    offset = np.array(camera.eye) - 0.5
    assert (offset > 0).all()
    assert camera.up == (0.0, 1.0, 0.0)
    camera_z = frame_bounds((0, 0, 0), (1, 1, 1), width=32, height=32, up=(0, 0, 2))
    offset_z = np.array(camera_z.eye) - 0.5
    assert (offset_z > 0).all()
    assert camera_z.up == (0.0, 0.0, 1.0)
    # The up axis projects upwards on screen
    _, _, up = camera_z.frame()
    assert up[2] > 0.5


def test_frame_bounds_fits_tightly():
    # Sphere radius sqrt(3)/2 must touch the frustum at margin 1: distance r / sin(fov/2)
    camera = frame_bounds((-1, -1, -1), (1, 1, 1), width=10, height=10, fov_deg=90, margin=1.0)
    distance = np.linalg.norm(np.array(camera.eye))
    np.testing.assert_allclose(distance, math.sqrt(3) / math.sin(math.pi / 4))


def test_frame_bounds_point_box():
    camera = frame_bounds((2, 2, 2), (2, 2, 2), width=4, height=4)
    assert camera.target == (2.0, 2.0, 2.0)
    assert camera.eye != camera.target


@pytest.mark.parametrize(
    "kwargs",
    [
        {"lo": (1, 0, 0), "hi": (0, 1, 1)},
        {"lo": (0, 0, np.nan), "hi": (1, 1, 1)},
        {"lo": (0, 0), "hi": (1, 1)},
        {"direction": (0, -1, 0)},
        {"direction": (0, 0, 0)},
        {"up": (0, 0, 0)},
        {"margin": 0.5},
        {"fov_deg": 180.0},
        {"width": 0},
    ],
)
def test_frame_bounds_rejects_bad_input(kwargs):
    arguments = {"lo": (0, 0, 0), "hi": (1, 1, 1), "width": 8, "height": 8, **kwargs}
    with pytest.raises(InvalidInputError):
        frame_bounds(**arguments)


def test_from_preset():
    preset = {"eye": [0, 1, 5], "target": [0, 1, 0], "up": [0, 1, 0], "fov_deg": 30}
    camera = from_preset(preset, 16, 9)
    assert camera == PinholeCamera((0, 1, 5), (0, 1, 0), (0, 1, 0), 30.0, 16, 9)
    defaults = from_preset({"eye": (1, 0, 0), "target": (0, 0, 0)}, 4, 4)
    assert defaults.up == (0.0, 1.0, 0.0)
    assert defaults.fov_deg == 45.0


@pytest.mark.parametrize(
    "preset",
    [
        {"eye": (1, 0, 0)},
        {"eye": (1, 0, 0), "target": (0, 0, 0), "fov": 30},
        {"eye": (1, 0, 0), "target": (0, 0, 0), "fov_deg": -1},
        [("eye", (1, 0, 0))],
    ],
)
def test_from_preset_rejects_bad_presets(preset):
    with pytest.raises(InvalidInputError):
        from_preset(preset, 4, 4)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"target": (0, 0, 5)},
        {"up": (0, 0, 1)},
        {"up": (0, 0, 0)},
        {"eye": (0, 0, np.inf)},
        {"eye": (0, 0)},
        {"fov_deg": 0.0},
        {"fov_deg": "wide"},
        {"width": 0},
        {"width": 2.0},
        {"height": True},
    ],
)
def test_camera_rejects_bad_input(kwargs):
    arguments = {"eye": (0, 0, 5), "target": (0, 0, 0), "width": 4, "height": 4, **kwargs}
    with pytest.raises(InvalidInputError):
        PinholeCamera(**arguments)


def test_camera_is_frozen_and_hashable():
    camera = PinholeCamera(np.array([0, 0, 5]), [0, 0, 0], width=np.int64(4), height=4)
    assert camera.eye == (0.0, 0.0, 5.0)
    assert isinstance(camera.width, int)
    assert hash(camera) == hash(PinholeCamera((0, 0, 5), (0, 0, 0), width=4, height=4))
    with pytest.raises(dataclasses.FrozenInstanceError):
        camera.width = 8  # type: ignore[misc]
