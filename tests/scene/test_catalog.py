import gzip
import os
import time
from pathlib import Path

import numpy as np
import pytest

from rayaccel.config import SCENE_PATH_VAR
from rayaccel.errors import InvalidInputError, SceneFileError, UnknownVariantError
from rayaccel.scene import catalog
from rayaccel.scene.mesh import TriangleMesh

SCENES = Path(__file__).parents[2].parent / "shared" / "scenes"
PROCEDURAL = ["cornell-box", "soup", "sphereflake", "teapot", "teapot-in-stadium"]
TRIANGLE_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
QUAD_OBJ = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n"


@pytest.fixture(autouse=True)
def _isolated_catalog(monkeypatch):
    monkeypatch.delenv(SCENE_PATH_VAR, raising=False)
    catalog.clear_cache()
    yield
    catalog.clear_cache()


@pytest.fixture
def scene_dir(tmp_path):
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "tri.obj").write_text(TRIANGLE_OBJ)
    (folder / "living_room.obj").write_text(QUAD_OBJ)
    (folder / "stanford-bunny.obj.gz").write_bytes(gzip.compress(QUAD_OBJ.encode()))
    (folder / "notes.txt").write_text("not a scene")
    return folder


# ------------------------------------------------------------------ procedural


def test_procedural_names_and_default():
    assert catalog.names()[:5] == PROCEDURAL
    assert catalog.DEFAULT_SCENE in PROCEDURAL
    default = catalog.get()
    assert default.name == catalog.DEFAULT_SCENE
    assert default.n_triangles >= 2000


@pytest.mark.parametrize("name", PROCEDURAL)
def test_get_procedural(name):
    mesh = catalog.get(name)
    assert isinstance(mesh, TriangleMesh)
    assert mesh.name == name
    assert catalog.get(name) is mesh  # cached


def test_parameters_pass_through_and_key_the_cache():
    big = catalog.get("sphereflake", level=1, sphere_subdivisions=1)
    assert big.n_triangles == 10 * 80 + 2
    assert catalog.get("sphereflake", sphere_subdivisions=1, level=1) is big
    assert catalog.get("sphereflake", level=0).n_triangles == 320 + 2
    assert catalog.get("soup", n_triangles=50, seed=3).n_triangles == 50


def test_names_are_normalised():
    assert catalog.get("Cornell_Box").name == "cornell-box"
    assert catalog.get(" teapot_in_stadium ").name == "teapot-in-stadium"


def test_unknown_parameter():
    with pytest.raises(UnknownVariantError, match=r"no parameter 'levl'.*did you mean 'level'"):
        catalog.get("sphereflake", levl=3)


def test_bad_parameter_value():
    with pytest.raises(InvalidInputError):
        catalog.get("teapot", subdivisions=0)


def test_unknown_scene_suggests_and_mentions_the_search_path():
    with pytest.raises(UnknownVariantError) as info:
        catalog.get("teapt")
    message = str(info.value)
    assert "unknown scene 'teapt'" in message
    assert "'teapot'" in message
    assert SCENE_PATH_VAR in message
    assert isinstance(info.value, KeyError)


def test_non_string_name():
    with pytest.raises(InvalidInputError):
        catalog.get(3)  # type: ignore[arg-type]


# ------------------------------------------------------------------ file scenes


def test_file_scenes_from_env_and_argument(monkeypatch, scene_dir, tmp_path):
    assert catalog.file_scenes() == {}
    monkeypatch.setenv(
        SCENE_PATH_VAR, os.pathsep.join(["", str(tmp_path / "missing"), str(scene_dir)])
    )
    found = catalog.file_scenes()
    assert sorted(found) == ["living_room", "stanford-bunny", "tri"]
    assert found["stanford-bunny"].name == "stanford-bunny.obj.gz"
    monkeypatch.delenv(SCENE_PATH_VAR)
    assert sorted(catalog.file_scenes(scene_dir)) == sorted(found)
    assert sorted(catalog.file_scenes([str(scene_dir)])) == sorted(found)
    assert catalog.names(scene_dir) == [*PROCEDURAL, "living_room", "stanford-bunny", "tri"]


def test_get_file_scene_by_name_alias_and_normalised_name(scene_dir):
    assert catalog.get("tri", search_path=scene_dir).n_triangles == 1
    assert catalog.get("bunny", search_path=scene_dir).name == "stanford-bunny"
    assert catalog.get("living-room", search_path=scene_dir).name == "living_room"
    assert catalog.get("LIVING_ROOM", search_path=scene_dir).name == "living_room"
    assert catalog.get("tri.obj", search_path=scene_dir).name == "tri"


def test_environment_comes_first(monkeypatch, scene_dir, tmp_path):
    other = tmp_path / "other"
    other.mkdir()
    (other / "tri.obj").write_text(QUAD_OBJ)
    monkeypatch.setenv(SCENE_PATH_VAR, str(other))
    assert catalog.get("tri", search_path=scene_dir).n_triangles == 2
    monkeypatch.setenv(SCENE_PATH_VAR, str(scene_dir))
    catalog.clear_cache()
    assert catalog.get("tri", search_path=other).n_triangles == 1


def test_suffix_preference_within_a_folder(tmp_path):
    (tmp_path / "shape.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    )
    (tmp_path / "shape.obj").write_text(QUAD_OBJ)
    assert catalog.file_scenes(tmp_path)["shape"].name == "shape.obj"


def test_path_names_load_the_file(scene_dir, monkeypatch):
    mesh = catalog.get(str(scene_dir / "tri.obj"))
    assert mesh.name == "tri"
    monkeypatch.chdir(scene_dir)
    assert catalog.get("living_room.obj").n_triangles == 2
    with pytest.raises(SceneFileError, match="no such file"):
        catalog.get(str(scene_dir / "absent.obj"))


def test_file_scene_rejects_parameters(scene_dir):
    with pytest.raises(InvalidInputError, match="takes no parameters"):
        catalog.get("tri", search_path=scene_dir, level=2)


def test_unknown_file_scene_hint_lists_the_folders(scene_dir):
    with pytest.raises(UnknownVariantError) as info:
        catalog.get("tri2", search_path=scene_dir)
    assert "'tri'" in str(info.value)
    assert str(scene_dir) in str(info.value)


def test_cache_follows_mtime(scene_dir):
    first = catalog.get("tri", search_path=scene_dir)
    assert catalog.get("tri", search_path=scene_dir) is first
    path = scene_dir / "tri.obj"
    path.write_text(QUAD_OBJ)
    stamp = time.time() + 5
    os.utime(path, (stamp, stamp))
    second = catalog.get("tri", search_path=scene_dir)
    assert second is not first
    assert second.n_triangles == 2


def test_malformed_file_scene(scene_dir):
    (scene_dir / "broken.obj").write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(SceneFileError, match=r"broken\.obj:2: face index 2 out of range"):
        catalog.get("broken", search_path=scene_dir)


def test_describe(scene_dir):
    infos = catalog.describe(scene_dir)
    assert [info.name for info in infos] == catalog.names(scene_dir)
    by_name = {info.name: info for info in infos}
    assert by_name["teapot"].kind == "procedural"
    assert by_name["teapot"].up == "+z"
    assert by_name["teapot"].summary.startswith("Return the Utah teapot")
    assert by_name["tri"].kind == "file"
    assert by_name["tri"].path == scene_dir / "tri.obj"
    assert by_name["living_room"].up == "+y"


# ------------------------------------------------------------------ camera presets

INTERIOR = ["staircase", "living_room", "kitchen", "salle_de_bain", "sponza_dabrovic",
            "cornell-box", "CornellBox-Original"]  # fmt: skip


@pytest.mark.parametrize("name", [*INTERIOR, "teapot", "sphereflake", "teapot-in-stadium"])
def test_camera_preset_shape(name):
    preset = catalog.camera_preset(name)
    assert set(preset) == {"eye", "target", "up", "fov_deg"}
    assert len(preset["eye"]) == len(preset["target"]) == len(preset["up"]) == 3
    assert 0 < preset["fov_deg"] < 180
    preset["fov_deg"] = -1.0  # a copy: the table is not modified
    assert catalog.camera_preset(name)["fov_deg"] > 0


def test_camera_preset_aliases_and_unknown():
    assert catalog.camera_preset("bathroom") == catalog.camera_preset("salle_de_bain")
    assert catalog.camera_preset("sponza") == catalog.camera_preset("sponza_dabrovic")
    assert catalog.camera_preset("living-room") == catalog.camera_preset("living_room")
    assert catalog.camera_preset("kitchen.ply.gz") == catalog.camera_preset("kitchen")
    assert catalog.camera_preset("stanford-bunny") is None
    assert catalog.camera_preset("no-such-scene") is None


def _pinhole_rays(preset, size=64):
    """Unit directions through pixel centres, vertical field of view, row-major from top-left."""
    eye = np.asarray(preset["eye"], dtype=np.float64)
    forward = np.asarray(preset["target"], dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, preset["up"])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = np.tan(np.radians(preset["fov_deg"]) / 2)
    steps = (2 * (np.arange(size) + 0.5) / size - 1) * half
    x, y = np.meshgrid(steps, -steps)
    directions = forward + x[..., None] * right + y[..., None] * up
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    origins = np.broadcast_to(eye, directions.shape)
    return origins.reshape(-1, 3).astype(np.float32), directions.reshape(-1, 3).astype(np.float32)


def _hit_fraction(mesh, preset):
    rtcore_scene = pytest.importorskip("embreex.rtcore_scene")
    mesh_construction = pytest.importorskip("embreex.mesh_construction")
    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, mesh.triangles())
    origins, directions = _pinhole_rays(preset)
    return float((scene.run(origins, directions) >= 0).mean())


@pytest.mark.scenes
@pytest.mark.parametrize("name", INTERIOR)
def test_interior_presets_are_inside_and_see_geometry(name):
    if name in PROCEDURAL:
        mesh = catalog.get(name)
    else:
        if not SCENES.is_dir() or name not in catalog.file_scenes(SCENES):
            pytest.skip(f"{name} not in {SCENES}")
        mesh = catalog.get(name, search_path=SCENES)
    preset = catalog.camera_preset(name)
    lo, hi = mesh.bounds()
    assert (np.asarray(preset["eye"]) > lo).all()
    assert (np.asarray(preset["eye"]) < hi).all()
    assert _hit_fraction(mesh, preset) >= 0.95


@pytest.mark.scenes
def test_shared_scene_names_and_aliases():
    if not SCENES.is_dir():
        pytest.skip(f"{SCENES} not available")
    found = catalog.file_scenes(SCENES)
    for stem in ("kitchen", "staircase", "stanford-bunny", "CornellBox-Original", "living_room",
                 "salle_de_bain", "sponza_dabrovic"):  # fmt: skip
        assert stem in found
    assert catalog.resolve("kitchen", SCENES).name == "kitchen.ply.gz"
    for alias, stem in [("bunny", "stanford-bunny"), ("sponza", "sponza_dabrovic"),
                        ("living-room", "living_room"), ("salle-de-bain", "salle_de_bain"),
                        ("bathroom", "salle_de_bain")]:  # fmt: skip
        assert catalog.resolve(alias, SCENES) == found[stem]
    assert catalog.get("bunny", search_path=SCENES).n_triangles == 69_451
