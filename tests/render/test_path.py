"""The path tracer: an analytic furnace, independence of structure and threads, materials,
lights, and the recorded ray sets."""

from __future__ import annotations

import json

import numba
import numpy as np
import pytest

import rayaccel
import reference
from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.rays.camera import PinholeCamera
from rayaccel.rays.io import load_ray_metadata, load_rays
from rayaccel.rays.record import RayRecorder, load_ray_set, read_manifest
from rayaccel.render.lights import AreaLights, default_virtual_light
from rayaccel.render.materials import Materials, obj_materials, scene_materials
from rayaccel.render.path import PathOptions, path_trace
from rayaccel.scene import catalog
from rayaccel.study.recording import render_scene


@pytest.fixture(scope="module")
def sphere():
    return reference.icosphere(3)


@pytest.fixture(scope="module")
def sphere_accel(sphere):
    return rayaccel.build(sphere)


def _furnace(sphere, albedo):
    """Every triangle emits 1 and reflects ``albedo``."""
    n = sphere.n_triangles
    materials = Materials(np.full((n, 3), albedo), np.ones((n, 3)))
    return materials, AreaLights.from_materials(sphere, materials)


def _inside_camera(size=48):
    return PinholeCamera(eye=(0.1, -0.05, 0.02), target=(1.0, 0.3, 0.2), up=(0, 0, 1),
                         fov_deg=70.0, width=size, height=size)


@pytest.mark.parametrize("rr_depth", [64, 1])
def test_furnace_inside_a_closed_emitting_sphere(sphere, sphere_accel, rr_depth):
    """Inside a closed enclosure that emits ``L = 1`` everywhere, the irradiance at every
    point of the wall is ``π`` whatever its shape, so next-event estimation returns
    ``albedo · L`` in expectation at every hit, and a path of ``D`` bounces sees
    ``1 + a + a² + … + a^(D+1)``. Russian roulette must not change the mean."""
    albedo, depth = 0.5, 3
    materials, lights = _furnace(sphere, albedo)
    image = path_trace(sphere_accel, _inside_camera(), materials=materials, lights=lights,
                       options=PathOptions(spp=4, max_depth=depth, rr_depth=rr_depth))
    expected = sum(albedo**k for k in range(depth + 2))
    assert image.radiance.shape == (48, 48, 3)
    assert image.radiance.mean() == pytest.approx(expected, rel=0.01)
    if rr_depth > depth:
        # On a sphere cos·cos/d² is constant, so most pixels are nearly noise-free
        # (not all: the facets are flat, and the kernel diverges near their edges).
        assert np.percentile(np.abs(image.radiance - expected), 90) < 0.05 * expected
    assert image.counts["primary"] == 4 * 48 * 48
    assert image.counts["shadow0"] > 0.9 * image.counts["primary"]


def test_image_independent_of_structure_traversal_and_threads(sphere_accel):
    mesh = catalog.get("cornell-box")
    materials = scene_materials(mesh)
    lights = AreaLights.from_materials(mesh, materials)
    camera = PinholeCamera(eye=(278, 273, -800), target=(278, 273, 0), up=(0, 1, 0),
                           fov_deg=39.3, width=32, height=32)
    options = PathOptions(spp=2, max_depth=2, seed=7)
    images = []
    threads = numba.get_num_threads()
    for key, traversal, count in [("bvh2.binned_sah", "bvh2.stack", threads),
                                  ("bvh2.binned_sah", "bvh2.stack", 1),
                                  ("kdtree.sah", "kdtree.stack", threads),
                                  ("grid.uniform", "grid.dda", threads)]:
        numba.set_num_threads(count)
        try:
            accel = rayaccel.build(mesh, key)
            images.append(path_trace(accel, camera, materials=materials, lights=lights,
                                     options=options, traversal=traversal))
        finally:
            numba.set_num_threads(threads)
    for other in images[1:]:
        np.testing.assert_allclose(other.radiance, images[0].radiance, rtol=1e-5, atol=1e-6)
        assert other.counts == images[0].counts
    assert images[0].radiance.mean() > 0.05
    # Another seed gives another image.
    accel = rayaccel.build(mesh)
    again = path_trace(accel, camera, materials=materials, lights=lights,
                       options=PathOptions(spp=2, max_depth=2, seed=8))
    assert not np.array_equal(again.radiance, images[0].radiance)


def test_cornell_box_colours_bleed_from_the_walls():
    """The red (left) and green (right) walls are told apart under the warm light."""
    mesh = catalog.get("cornell-box")
    materials = scene_materials(mesh)
    camera = PinholeCamera(eye=(278, 273, -800), target=(278, 273, 0), up=(0, 1, 0),
                           fov_deg=39.3, width=48, height=48)
    image = path_trace(rayaccel.build(mesh), camera, materials=materials,
                       lights=AreaLights.from_materials(mesh, materials),
                       options=PathOptions(spp=8, max_depth=3))
    left = image.radiance[:, 2:8].mean(axis=(0, 1))
    right = image.radiance[:, -8:-2].mean(axis=(0, 1))
    assert left[0] / left[1] > 3 * right[0] / right[1]
    assert np.isfinite(image.radiance).all()
    assert (image.radiance >= 0).all()
    # The light quad seen directly is the brightest spot: its emission, 17.
    assert image.radiance[..., 0].max() == pytest.approx(17.0, rel=0.05)


def test_virtual_light_lights_a_scene_without_emitters():
    mesh = catalog.get("teapot")
    materials = scene_materials(mesh)
    assert materials.source == "default"
    assert materials.emissive().size == 0
    assert AreaLights.from_materials(mesh, materials) is None
    image = render_scene(mesh, "teapot", width=32, height=24, options=PathOptions(spp=1))
    assert image.radiance.mean() > 0.01
    lo, hi = mesh.bounds()
    light = default_virtual_light(mesh, (hi + lo) / 2 + [0, 0, 10], (0, 0, 1))
    assert light.virtual
    assert light.n_lights == 2
    assert light.area.sum() == pytest.approx((0.05 * np.linalg.norm(hi - lo)) ** 2, rel=1e-6)


def test_recorded_sets_are_the_traced_rays(tmp_path):
    mesh = catalog.get("cornell-box")
    accel = rayaccel.build(mesh)
    options = PathOptions(spp=2, max_depth=2, seed=3)
    whole = render_scene(mesh, "cornell-box", accel=accel, width=24, height=16, options=options,
                         record_to=tmp_path / "one")
    chunked = render_scene(mesh, "cornell-box", accel=accel, width=24, height=16,
                           options=options, record_to=tmp_path / "many", chunk_rays=100)
    np.testing.assert_array_equal(whole.radiance, chunked.radiance)
    manifest = read_manifest(tmp_path / "one")
    assert manifest["scene_digest"] == mesh.digest()
    assert manifest["camera"]["width"] == 24
    assert manifest["spp"] == 2
    assert {name: s["n_rays"] for name, s in manifest["sets"].items()} == whole.counts
    many = read_manifest(tmp_path / "many")
    assert len(many["sets"]["primary"]["files"]) == -(-whole.counts["primary"] // 100)
    for name in whole.counts:
        one = load_ray_set(tmp_path / "one", name, mesh.digest())
        split = load_ray_set(tmp_path / "many", name, mesh.digest())
        for field in ("origin", "direction", "tmin", "tmax"):
            np.testing.assert_array_equal(getattr(one, field), getattr(split, field))
    first = tmp_path / "many" / many["sets"]["primary"]["files"][0]
    assert load_rays(first).n_rays == 100
    meta = load_ray_metadata(first)
    assert meta["set"] == "primary"
    assert meta["chunk"] == 0
    assert meta["seed"] == 3
    # Replaying the recorded primary rays reproduces the render's first hits.
    primary = load_ray_set(tmp_path / "one", "primary")
    assert accel.trace(primary).hit.mean() > 0.9
    with pytest.raises(SceneFileError, match="another scene"):
        load_ray_set(tmp_path / "one", "primary", catalog.get("teapot").digest())
    with pytest.raises(SceneFileError, match="no ray set"):
        load_ray_set(tmp_path / "one", "bounce9")


def test_interrupted_recording_writes_no_manifest(tmp_path):
    mesh = reference.icosphere(1)
    rays = rayaccel.RayBatch(np.zeros((10, 3)), np.ones((10, 3)))
    recorder = RayRecorder(tmp_path, scene="s", scene_digest=mesh.digest(), chunk_rays=4)

    def interrupted() -> None:
        with recorder:
            recorder.add("primary", rays)
            raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        interrupted()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["primary-0000.npz", "primary-0001.npz"]
    with pytest.raises(SceneFileError, match="manifest"):
        read_manifest(tmp_path)
    with pytest.raises(InvalidInputError, match="ray set name"):
        RayRecorder(tmp_path, scene="s", scene_digest="0").add("../x", rays)


def test_obj_materials_from_the_mtl(tmp_path):
    (tmp_path / "m.mtl").write_text(
        "newmtl red\nKd 0.8 0.1 0.1\nnewmtl lamp\nKd 0.5 0.5 0.5\nKe 4 4 2 # warm\n"
    )
    (tmp_path / "s.obj").write_text(
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\n"
        "usemtl red\nf 1 2 3 4\nusemtl lamp\nf 1 2 5\nusemtl missing\nf 2 3 5\n"
    )
    mesh = rayaccel.load_mesh(tmp_path / "s.obj")
    found = scene_materials(mesh, tmp_path / "s.obj")
    assert found.source == "m.mtl"
    np.testing.assert_allclose(found.albedo, [[0.8, 0.1, 0.1]] * 2 + [[0.5] * 3] + [[0.7] * 3])
    np.testing.assert_allclose(found.emission[2], [4, 4, 2])
    assert found.emissive().tolist() == [2]
    other = rayaccel.TriangleMesh(np.eye(3), [[0, 1, 2]])
    with pytest.raises(SceneFileError, match="triangles in the file"):
        obj_materials(tmp_path / "s.obj", other)
    (tmp_path / "bad.mtl").write_text("newmtl x\nKd 1 nope 0\n")
    (tmp_path / "b.obj").write_text(
        "mtllib bad.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl x\nf 1 2 3\n"
    )
    with pytest.raises(SceneFileError, match=r"bad\.mtl:2"):
        scene_materials(rayaccel.load_mesh(tmp_path / "b.obj"), tmp_path / "b.obj")


@pytest.mark.scenes
def test_cornell_box_obj_has_its_light():
    path = catalog.resolve("CornellBox-Original")
    mesh = catalog.get("CornellBox-Original")
    found = scene_materials(mesh, path)
    lights = AreaLights.from_materials(mesh, found)
    assert lights is not None
    assert not lights.virtual
    np.testing.assert_allclose(lights.emission[0], [17, 12, 4])


def test_bad_options_and_inputs(sphere, sphere_accel):
    for bad in ({"spp": 0}, {"max_depth": -1}, {"rr_depth": 0}, {"epsilon": float("nan")}):
        with pytest.raises(InvalidInputError):
            PathOptions(**bad)
    with pytest.raises(InvalidInputError, match="albedo must be <= 1"):
        Materials(np.full((2, 3), 1.5), np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match="finite"):
        Materials(np.full((2, 3), np.nan), np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match="no light"):
        AreaLights.from_triangles(np.zeros((1, 3, 3)), np.ones((1, 3)))
    materials, lights = _furnace(reference.icosphere(1), 0.5)
    with pytest.raises(InvalidInputError, match="describe"):
        path_trace(sphere_accel, _inside_camera(8), materials=materials, lights=lights)


def test_cli_renders_records_and_writes_exr(tmp_path, capsys):
    from rayaccel.cli import main

    png, exr, folder = tmp_path / "c.png", tmp_path / "c.exr", tmp_path / "rays"
    assert main(["render", "cornell-box", "--view", "path", "-o", str(png), "--width", "24",
                 "--height", "16", "--spp", "2", "--exr", str(exr), "--record",
                 str(folder)]) == 0
    out = capsys.readouterr().out
    assert "primary 768" in out
    from PIL import Image

    assert Image.open(png).size == (24, 16)
    import OpenEXR

    with OpenEXR.File(str(exr)) as image:
        assert image.channels()["RGB"].pixels.shape == (16, 24, 3)
    assert json.loads((folder / "rays.json").read_text())["sets"]["primary"]["n_rays"] == 768
    assert main(["render", "cornell-box", "--record", str(folder), "-o", str(png)]) == 1
    assert "--view path" in capsys.readouterr().err
