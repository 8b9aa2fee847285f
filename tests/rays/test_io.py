import os
import pathlib
import re

import numpy as np
import pytest

from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.rays import RayBatch, load_ray_metadata, load_rays, save_rays
from rayaccel.validation import COORDINATE_LIMIT


def _rays(n=257, seed=0):
    rng = np.random.default_rng(seed)
    origin = rng.normal(size=(n, 3)).astype(np.float32)
    direction = rng.normal(size=(n, 3)).astype(np.float32)
    origin[0] = [-0.0, np.float32(1e-45), COORDINATE_LIMIT["float32"]]  # the largest in range
    direction[1] = [0.0, -0.0, 1.0]
    tmin = rng.uniform(0, 1e-3, n).astype(np.float32)
    tmax = np.where(rng.random(n) < 0.5, np.inf, rng.uniform(1, 10, n)).astype(np.float32)
    return RayBatch(origin, direction, tmin, tmax)


def _assert_bit_identical(a, b):
    for name in ("origin", "direction", "tmin", "tmax"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == np.float32
        assert x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def test_round_trip_is_bit_exact(tmp_path):
    rays = _rays()
    path = tmp_path / "rays.npz"
    written = save_rays(path, rays)
    assert written == path
    loaded = load_rays(path)
    _assert_bit_identical(rays, loaded)
    assert loaded.origin.flags.c_contiguous
    assert load_ray_metadata(path) == {}


def test_round_trip_with_str_path_and_empty_batch(tmp_path):
    rays = RayBatch(np.zeros((0, 3)), np.zeros((0, 3)))
    path = str(tmp_path / "empty.npz")
    save_rays(path, rays, kind="primary")
    loaded = load_rays(path)
    assert loaded.n_rays == 0
    _assert_bit_identical(rays, loaded)


def test_metadata_round_trip(tmp_path):
    path = tmp_path / "rays.npz"
    save_rays(
        path,
        _rays(5),
        scene="sponza",
        seed=np.int64(3),
        camera={"eye": (0.0, 1.0, 2.0), "fov_deg": np.float32(45.0)},
        sizes=np.arange(3),
        source=pathlib.Path("a/b.obj"),
        nothing=None,
    )
    assert load_ray_metadata(path) == {
        "scene": "sponza",
        "seed": 3,
        "camera": {"eye": [0.0, 1.0, 2.0], "fov_deg": 45.0},
        "sizes": [0, 1, 2],
        "source": os.fspath(pathlib.Path("a/b.obj")),
        "nothing": None,
    }


def test_save_leaves_no_temporary_file_and_overwrites(tmp_path):
    path = tmp_path / "rays.npz"
    save_rays(path, _rays(seed=1), version=1)
    save_rays(path, _rays(seed=2), version=2)
    assert sorted(os.listdir(tmp_path)) == ["rays.npz"]
    _assert_bit_identical(load_rays(path), _rays(seed=2))
    assert load_ray_metadata(path) == {"version": 2}


def test_failed_save_keeps_previous_file(tmp_path, monkeypatch):
    path = tmp_path / "rays.npz"
    save_rays(path, _rays(seed=1), version=1)
    before = path.read_bytes()

    def broken_savez(file, **arrays):
        file.write(b"PK\x03\x04 partial archive")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        save_rays(path, _rays(seed=2), version=2)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["rays.npz"]
    _assert_bit_identical(load_rays(path), _rays(seed=1))


def test_failed_first_save_creates_nothing(tmp_path, monkeypatch):
    def broken_savez(file, **arrays):
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(KeyboardInterrupt):
        save_rays(tmp_path / "rays.npz", _rays())
    assert os.listdir(tmp_path) == []


def test_save_rejects_bad_arguments(tmp_path):
    path = tmp_path / "rays.npz"
    with pytest.raises(InvalidInputError, match="rays"):
        save_rays(path, np.zeros((3, 3)))
    with pytest.raises(InvalidInputError, match="metadata"):
        save_rays(path, _rays(), callback=print)
    assert os.listdir(tmp_path) == []
    with pytest.raises(FileNotFoundError):
        save_rays(tmp_path / "missing" / "rays.npz", _rays())


def _members(n=4, **overrides):
    members = {
        "origin": np.zeros((n, 3), np.float32),
        "direction": np.ones((n, 3), np.float32),
        "tmin": np.zeros(n, np.float32),
        "tmax": np.full(n, np.inf, np.float32),
        "metadata": np.array("{}"),
    }
    members.update(overrides)
    return {key: value for key, value in members.items() if value is not None}


BAD_ARCHIVES = {
    "missing_member": _members(tmax=None),
    "missing_metadata": _members(metadata=None),
    "extra_member": _members(prim=np.zeros(4, np.int32)),
    "float64_origin": _members(origin=np.zeros((4, 3))),
    "int_tmin": _members(tmin=np.zeros(4, np.int32)),
    "flat_direction": _members(direction=np.ones(12, np.float32)),
    "two_columns": _members(origin=np.zeros((4, 2), np.float32)),
    "tmax_2d": _members(tmax=np.zeros((4, 1), np.float32)),
    "row_mismatch": _members(tmin=np.zeros(5, np.float32)),
    "nan_tmin": _members(tmin=np.full(4, np.nan, np.float32)),
    "metadata_not_json": _members(metadata=np.array("{not json")),
    "metadata_not_object": _members(metadata=np.array("[1, 2]")),
    "metadata_bytes": _members(metadata=np.array(b"{}")),
    "metadata_array": _members(metadata=np.array(["{}", "{}"])),
    "object_member": _members(origin=np.array([None, 1], dtype=object)),
}


@pytest.mark.parametrize("case", sorted(BAD_ARCHIVES))
def test_load_rejects_malformed_archives(tmp_path, case):
    path = tmp_path / f"{case}.npz"
    np.savez(path, **BAD_ARCHIVES[case])
    with pytest.raises(SceneFileError, match=case):
        load_rays(path)


@pytest.mark.parametrize("case", ["metadata_not_json", "metadata_not_object", "missing_member"])
def test_load_metadata_rejects_malformed_archives(tmp_path, case):
    path = tmp_path / f"{case}.npz"
    np.savez(path, **BAD_ARCHIVES[case])
    with pytest.raises(SceneFileError, match=case):
        load_ray_metadata(path)


def test_load_rejects_missing_and_unreadable_files(tmp_path):
    missing = tmp_path / "nowhere.npz"
    with pytest.raises(SceneFileError, match=re.escape("nowhere.npz")):
        load_rays(missing)
    with pytest.raises(SceneFileError, match=re.escape("nowhere.npz")):
        load_ray_metadata(missing)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not an archive")
    with pytest.raises(SceneFileError, match=re.escape("garbage.npz")):
        load_rays(garbage)
    truncated = tmp_path / "truncated.npz"
    save_rays(truncated, _rays())
    truncated.write_bytes(truncated.read_bytes()[:200])
    with pytest.raises(SceneFileError, match=re.escape("truncated.npz")):
        load_rays(truncated)
    single = tmp_path / "single.npy"
    np.save(single, np.zeros((3, 3), np.float32))
    with pytest.raises(SceneFileError, match=re.escape("single.npy")):
        load_rays(single)
    with pytest.raises(SceneFileError, match=re.escape(tmp_path.name)):
        load_rays(tmp_path)


def test_scene_file_error_is_an_invalid_input_error(tmp_path):
    with pytest.raises(InvalidInputError):
        load_rays(tmp_path / "nowhere.npz")
