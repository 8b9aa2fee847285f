"""Saving and loading an Accel (``accel.save``, ``rayaccel.load_accel``), pickle and copies.

A round trip gives back the same structure, mesh, builder and options, and the same hits;
files from another format version, with a changed byte or header, truncated, foreign or
missing are refused with :class:`rayaccel.AccelFileError`, and nothing is unpickled.
"""

from __future__ import annotations

import copy
import json
import pickle
import threading

import numpy as np
import pytest

import rayaccel
import reference
from rayaccel import persist
from rayaccel.errors import AccelFileError, SceneFileError

#: One builder of each family, with steps and nested or dict-holding structures.
ROUND_TRIP = (
    "bvh2.binned_sah",
    "bvh2.lbvh+reinsert",
    "kdtree.sah",
    "grid.mipmap",
    "grid.two_level",
    "grid.irregular",
)


@pytest.fixture(scope="module")
def sphere() -> rayaccel.TriangleMesh:
    return reference.icosphere(2)


@pytest.fixture(scope="module")
def rays(sphere):
    return reference.mixed_rays(sphere, 200)


@pytest.fixture
def saved(tmp_path, sphere):
    accel = rayaccel.build(sphere, "bvh2.binned_sah", max_leaf_size=3)
    path = tmp_path / "sphere.accel"
    accel.save(path)
    return accel, path


def read_members(path) -> dict:
    with np.load(path, allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def header_of(members: dict) -> dict:
    return json.loads(members[persist.HEADER].tobytes().decode())


def write_members(path, members: dict, header: dict | None = None) -> None:
    if header is not None:
        text = json.dumps(header).encode()
        members = {**members, persist.HEADER: np.frombuffer(text, dtype=np.uint8)}
    with open(path, "wb") as handle:
        np.savez(handle, **members)


def assert_same_structure(a, b) -> None:
    assert type(a) is type(b)
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype, name
            assert np.array_equal(x, y), name
        elif hasattr(x, "__dataclass_fields__"):
            assert_same_structure(x, y)
        else:
            assert x == y, name


@pytest.mark.parametrize("builder", ROUND_TRIP)
def test_round_trip_same_structure_and_hits(tmp_path, sphere, rays, builder):
    options = {"reinsert": {"max_iterations": 3}} if "reinsert" in builder else {}
    accel = rayaccel.build(sphere, builder, **options)
    path = tmp_path / "a.accel"
    assert accel.save(path) == path
    loaded = rayaccel.load_accel(path)
    assert loaded.key == accel.key
    assert loaded.structure_name == accel.structure_name
    assert loaded.options == accel.options
    assert loaded.step_options == accel.step_options
    assert loaded.build_options() == accel.build_options()
    assert loaded.build_ms == accel.build_ms
    assert loaded.step_ms == accel.step_ms
    assert loaded.mesh.digest() == accel.mesh.digest()
    assert loaded.mesh.name == accel.mesh.name
    assert_same_structure(accel.structure, loaded.structure)
    tri = reference.tri9(sphere)
    ref = reference.oracle(sphere, rays)
    for query in ("closest", "any"):
        ours = loaded.trace(rays, query=query)
        reference.assert_hits_identical(accel.trace(rays, query=query), ours, builder)
        if query == "closest":
            reference.assert_closest_matches(tri, rays, ours, ref, builder)


def test_loaded_accel_keeps_its_build_sah_after_refit(tmp_path, sphere):
    accel = rayaccel.build(sphere, "bvh2.sbvh")
    first = accel.refit(sphere.vertices * np.float32([1.0, 2.0, 0.5]))
    accel.save(tmp_path / "a.accel")
    loaded = rayaccel.load_accel(tmp_path / "a.accel")
    assert loaded.build_sah == first["sah_build"]
    again = loaded.refit(loaded.mesh.vertices)
    assert again["ratio"] == pytest.approx(first["ratio"], rel=1e-12)
    loaded.validate()


def test_pickle_and_copies(sphere, rays):
    accel = rayaccel.build(sphere, "bvh2.binned_sah")
    before = accel.intersect(rays.origin, rays.direction)  # fills the layout cache
    assert accel.derived("bvh2.packed") is not None
    clone = pickle.loads(pickle.dumps(accel))
    assert clone.derived("bvh2.packed") is None  # derived layouts are not shipped
    assert isinstance(clone._lock, type(threading.RLock()))
    assert clone._lock is not accel._lock
    assert_same_structure(accel.structure, clone.structure)
    reference.assert_hits_identical(before, clone.intersect(rays.origin, rays.direction))
    shallow = copy.copy(accel)
    assert shallow.structure is accel.structure
    assert shallow.mesh is accel.mesh
    assert shallow._lock is not accel._lock
    assert shallow._cache is not accel._cache
    deep = copy.deepcopy(accel)
    assert deep.structure is not accel.structure
    assert_same_structure(accel.structure, deep.structure)
    # A copy refits on its own: the original keeps its geometry.
    shallow.refit(sphere.vertices * np.float32(2.0))
    reference.assert_hits_identical(before, accel.intersect(rays.origin, rays.direction))
    reference.assert_hits_identical(before, deep.intersect(rays.origin, rays.direction))


def test_file_from_another_version_is_refused(tmp_path, saved):
    _, path = saved
    members = read_members(path)
    header = header_of(members)
    header["format_version"] = persist.FORMAT_VERSION + 1
    header["rayaccel_version"] = "99.0"
    write_members(path, members, header)
    with pytest.raises(AccelFileError, match=r"format 2 .*rayaccel 99\.0.*reads format 1"):
        rayaccel.load_accel(path)


def test_structure_layout_of_another_version_is_refused(tmp_path, saved):
    _, path = saved
    members = read_members(path)
    header = header_of(members)
    del header["layout"]["fields"]["n_prims"]
    header["sha256"] = persist.content_digest(
        header, {k: v for k, v in members.items() if k != persist.HEADER}
    )
    write_members(path, members, header)
    with pytest.raises(AccelFileError, match=r"has fields .*\(written by another version\)"):
        rayaccel.load_accel(path)


def test_unknown_structure_class_is_refused(tmp_path, saved):
    _, path = saved
    members = read_members(path)
    header = header_of(members)
    header["layout"]["class"] = "Popen"
    arrays = {k: v for k, v in members.items() if k != persist.HEADER}
    header["sha256"] = persist.content_digest(header, arrays)
    write_members(path, members, header)
    with pytest.raises(AccelFileError, match="unknown structure class 'Popen'"):
        rayaccel.load_accel(path)


def test_unknown_builder_is_refused(tmp_path, saved):
    _, path = saved
    members = read_members(path)
    header = header_of(members)
    header["options"]["no_such_option"] = 1
    arrays = {k: v for k, v in members.items() if k != persist.HEADER}
    header["sha256"] = persist.content_digest(header, arrays)
    write_members(path, members, header)
    with pytest.raises(AccelFileError, match="no_such_option"):
        rayaccel.load_accel(path)


@pytest.mark.parametrize("name", ["structure.node_lo", "structure.prim_index", "mesh.vertices"])
def test_tampered_array_is_refused(tmp_path, saved, name):
    _, path = saved
    members = read_members(path)
    array = members[name].copy()
    array.reshape(-1).view(np.uint8)[5] ^= 1  # one flipped bit
    members[name] = array
    write_members(path, members)
    with pytest.raises(AccelFileError, match="content hash mismatch"):
        rayaccel.load_accel(path)


def test_tampered_header_is_refused(tmp_path, saved):
    _, path = saved
    members = read_members(path)
    header = header_of(members)
    header["options"]["max_leaf_size"] = 8
    write_members(path, members, header)
    with pytest.raises(AccelFileError, match="content hash mismatch"):
        rayaccel.load_accel(path)


def test_swapped_or_extra_arrays_are_refused(tmp_path, saved):
    _, path = saved
    members = read_members(path)
    swapped = dict(members)
    swapped["structure.node_lo"] = members["structure.node_hi"]
    swapped["structure.node_hi"] = members["structure.node_lo"]
    write_members(path, swapped)
    with pytest.raises(AccelFileError, match="content hash mismatch"):
        rayaccel.load_accel(path)
    write_members(path, {**members, "extra": np.zeros(3)})
    with pytest.raises(AccelFileError, match="not listed in the header"):
        rayaccel.load_accel(path)
    resized = dict(members)
    resized["structure.node_count"] = members["structure.node_count"][:-1]
    write_members(path, resized)
    with pytest.raises(AccelFileError, match="but the header says"):
        rayaccel.load_accel(path)


@pytest.mark.parametrize("fraction", [0.0, 0.1, 0.5, 0.9, 0.999])
def test_truncated_file_is_refused(tmp_path, saved, fraction):
    _, path = saved
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(AccelFileError):
        rayaccel.load_accel(path)


def test_foreign_files_are_refused(tmp_path):
    npz = tmp_path / "other.npz"
    np.savez(npz, x=np.arange(4))
    with pytest.raises(AccelFileError, match="not a rayaccel accel file"):
        rayaccel.load_accel(npz)
    npy = tmp_path / "one.npy"
    np.save(npy, np.arange(4))
    with pytest.raises(AccelFileError, match="not an npz archive"):
        rayaccel.load_accel(npy)
    text = tmp_path / "text.accel"
    text.write_text("hello")
    with pytest.raises(AccelFileError, match="not a rayaccel accel file"):
        rayaccel.load_accel(text)
    json_header = tmp_path / "json.npz"
    write_members(json_header, {}, {"format": "something else"})
    with pytest.raises(AccelFileError, match="names no rayaccel format"):
        rayaccel.load_accel(json_header)


def test_pickled_objects_in_the_file_are_never_loaded(tmp_path, saved):
    _, path = saved
    members = read_members(path)
    members[persist.HEADER] = np.array([{"format": persist.FORMAT}], dtype=object)
    with open(path, "wb") as handle:
        np.savez(handle, allow_pickle=True, **members)
    with pytest.raises(AccelFileError, match="unreadable header"):
        rayaccel.load_accel(path)


def test_missing_file_and_unwritable_destination(tmp_path, saved):
    accel, _ = saved
    with pytest.raises(AccelFileError, match="no such accel file") as info:
        rayaccel.load_accel(tmp_path / "absent.accel")
    assert isinstance(info.value, SceneFileError)
    with pytest.raises(FileNotFoundError):
        accel.save(tmp_path / "no" / "such" / "dir" / "a.accel")


def test_save_replaces_atomically(tmp_path, sphere):
    path = tmp_path / "a.accel"
    rayaccel.build(sphere, "kdtree.sah").save(path)
    rayaccel.build(sphere, "grid.uniform").save(path)
    assert rayaccel.load_accel(path).key == "grid.uniform"
    assert [p.name for p in tmp_path.iterdir()] == ["a.accel"]  # no temporary left behind
