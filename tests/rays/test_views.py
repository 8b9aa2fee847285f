"""Named views of a scene's camera (rayaccel.rays.views) and their use in the bench."""

from __future__ import annotations

import numpy as np
import pytest

from rayaccel import registry
from rayaccel.bench import harness
from rayaccel.bench.raysets import standard_raysets
from rayaccel.errors import InvalidInputError
from rayaccel.rays.camera import PinholeCamera
from rayaccel.rays.views import parse_view, split_view, turned
from rayaccel.scene import catalog

CAMERA = PinholeCamera((1.0, 2.0, 3.0), (1.0, 2.0, -1.0), (0.0, 1.0, 0.0), 50.0, 16, 8)


def test_view_names():
    assert parse_view("preset") == []
    assert parse_view("yaw120") == [("yaw", 120.0)]
    assert parse_view("orbit-37.5") == [("orbit", -37.5)]
    assert parse_view("walk0.5+yaw180") == [("walk", 0.5), ("yaw", 180.0)]
    for bad in ("yaw", "turn90", "yaw1e400", "orbit 90", "", "YAW90", "yaw90+", "preset+yaw9"):
        with pytest.raises(InvalidInputError, match="view"):
            parse_view(bad)


def test_a_view_is_split_off_a_scene_spec_only_when_it_names_one():
    assert split_view("living_room@yaw120") == ("living_room", "yaw120")
    assert split_view("a@b/room.obj@orbit90") == ("a@b/room.obj", "orbit90")
    assert split_view("living_room") == ("living_room", None)
    assert split_view("shots@home/room.obj") == ("shots@home/room.obj", None)
    assert split_view("@yaw90") == ("@yaw90", None)
    assert split_view("kitchen@walk0.3+yaw180") == ("kitchen", "walk0.3+yaw180")


def test_yaw_turns_in_place_and_orbit_keeps_the_target():
    eye, target = np.array(CAMERA.eye), np.array(CAMERA.target)
    yawed = turned(CAMERA, "yaw90")
    assert np.allclose(yawed.eye, eye)
    # Looking down -Z, a quarter turn counter-clockwise about +Y looks down -X.
    assert np.allclose(np.subtract(yawed.target, yawed.eye), [-4.0, 0.0, 0.0])
    orbited = turned(CAMERA, "orbit180")
    assert np.allclose(orbited.target, target)
    assert np.allclose(orbited.eye, [1.0, 2.0, -5.0])
    for view in (yawed, orbited):
        assert (view.up, view.fov_deg, view.width, view.height) == (
            CAMERA.up, CAMERA.fov_deg, CAMERA.width, CAMERA.height)
    assert turned(CAMERA, "preset") is CAMERA
    back = turned(CAMERA, "walk0.5+yaw180")
    assert np.allclose(back.eye, [1.0, 2.0, 1.0])
    assert np.allclose(back.target, [1.0, 2.0, 5.0])
    assert np.allclose(turned(CAMERA, "yaw360").target, target)


def test_standard_raysets_of_a_view_keep_the_light():
    mesh = catalog.get("cornell-box")
    preset = standard_raysets(mesh, "cornell-box", width=12, height=10)
    side = standard_raysets(mesh, "cornell-box", width=12, height=10, view="yaw60")
    assert not np.array_equal(preset["primary"].rays.direction, side["primary"].rays.direction)
    assert np.array_equal(preset["primary"].rays.origin, side["primary"].rays.origin)

    def lights(rays):
        return rays.origin + rays.direction * (1.0 / (1.0 - 1e-4)) * rays.tmax[:, None]

    for sets in (preset, side):
        shadow = sets["shadow"].rays
        assert shadow.n_rays > 0
        assert np.allclose(lights(shadow), lights(preset["shadow"].rays)[0], atol=1e-3)


def test_the_bench_reports_each_view_as_a_scene():
    config = harness.BenchConfig(
        scenes=["cornell-box", "cornell-box@yaw90"], builders=registry.keys("builder")[:1],
        traversals=["bvh2.stack"], ray_kinds=["primary"], threads=[1], width=8, height=8,
        repeats=1, build_repeats=1, validate=16, warmup_triangles=600,
    )  # fmt: skip
    result = harness.run_bench(config)
    scenes = {r["scene"] for r in harness.iter_trace_records(result.records)}
    assert scenes == {"cornell-box", "cornell-box@yaw90"}
