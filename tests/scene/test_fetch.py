"""rayaccel.scenes.fetch and ``rayaccel scenes``: downloads served from a loopback HTTP server.

No test touches the internet: every catalog entry used here points at a server on
127.0.0.1 started by the ``server`` fixture, which counts the requests it answers.
"""

import gzip
import hashlib
import http.server
import io
import json
import re
import socket
import tarfile
import threading
import zipfile
from collections import Counter
from typing import ClassVar

import numpy as np
import pytest

import rayaccel as ra
from rayaccel.cli import load_scene, main
from rayaccel.errors import SceneFileError, UnknownVariantError
from rayaccel.scene import catalog, procedural
from rayaccel.scene import fetch as fetch_module
from rayaccel.scene.fetch import CACHE_DIR_VAR, fetch, ply_bytes
from rayaccel.scene.io import load_mesh
from rayaccel.scene.mesh import TriangleMesh
from rayaccel.scene.remote import REMOTE_SCENES, RemoteScene

TET_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class _Handler(http.server.BaseHTTPRequestHandler):
    files: ClassVar[dict[str, bytes]] = {}
    counts: ClassVar[Counter[str]] = Counter()

    def do_GET(self):
        type(self).counts[self.path] += 1
        body = type(self).files.get(self.path)
        if body is None:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    handler = type("Handler", (_Handler,), {"files": {}, "counts": Counter()})
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(
        target=httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
    )
    thread.start()
    base = f"http://127.0.0.1:{httpd.server_address[1]}"
    try:
        yield base, handler.files, handler.counts
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(5)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv(CACHE_DIR_VAR, str(folder))
    for var in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY", "all_proxy", "ALL_PROXY"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.setenv("no_proxy", "127.0.0.1,localhost")
    catalog.clear_cache()
    yield folder
    catalog.clear_cache()


def add_entry(monkeypatch, name, url, data, **fields):
    fields.setdefault("sha256", sha256(data))
    fields.setdefault("archive", None)
    fields.setdefault("member", None)
    entry = RemoteScene(
        name=name,
        title=f"test scene {name}",
        url=url,
        size=len(data),
        licence="CC0 (test)",
        credit="the rayaccel tests",
        **fields,
    )
    monkeypatch.setitem(REMOTE_SCENES, name, entry)
    return entry


def zip_bytes(members):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as bundle:
        for name, data in members.items():
            bundle.writestr(name, data)
    return buffer.getvalue()


def tar_gz_bytes(members):
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as bundle:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            bundle.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def files_under(folder):
    return sorted(p for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


# -- downloads -------------------------------------------------------------------------------


def test_plain_file_is_downloaded_verified_cached_and_found_by_the_catalog(
    server, cache, monkeypatch
):
    base, files, counts = server
    files["/tet.obj"] = TET_OBJ
    add_entry(monkeypatch, "test-tet", f"{base}/tet.obj", TET_OBJ)
    with pytest.raises(UnknownVariantError, match="not fetched yet"):
        catalog.get("test-tet")

    path = fetch("test-tet")
    assert path.read_bytes() == TET_OBJ
    assert cache in path.parents
    assert counts["/tet.obj"] == 1
    assert fetch("test-tet") == path  # cached: no second request
    assert counts["/tet.obj"] == 1

    mesh = catalog.get("test-tet")
    assert mesh.n_triangles == 4
    assert catalog.resolve("test_tet") == path  # case, '-' and '_' ignored as for files
    assert "test-tet" in catalog.names()
    info = next(i for i in catalog.describe() if i.name == "test-tet")
    assert info.path == path
    assert "fetched" in info.summary


def test_zip_archive_is_unpacked_and_its_member_loaded(server, cache, monkeypatch):
    base, files, counts = server
    archive = zip_bytes({"tet/tet.obj": TET_OBJ, "tet/textures/wood.png": b"not a png"})
    files["/tet.zip"] = archive
    add_entry(monkeypatch, "test-zip", f"{base}/tet.zip", archive, archive="zip",
              member="tet/tet.obj")  # fmt: skip

    path = ra.scenes.fetch("test-zip")
    assert path.name == "tet.obj"
    assert path.read_bytes() == TET_OBJ
    assert (path.parent / "textures" / "wood.png").is_file()  # the whole archive is unpacked
    assert fetch("test-zip") == path
    assert counts["/tet.zip"] == 1
    assert catalog.get("test-zip").n_triangles == 4


def test_member_is_found_by_name_when_the_archive_layout_differs(server, cache, monkeypatch):
    base, files, _ = server
    archive = zip_bytes({"Some Folder/tet.obj": TET_OBJ, "Some Folder/readme.txt": b"hi"})
    files["/moved.zip"] = archive
    add_entry(monkeypatch, "test-moved", f"{base}/moved.zip", archive, archive="zip",
              member="tet.obj")  # fmt: skip
    path = fetch("test-moved")
    assert path.relative_to(path.parents[1]).as_posix() == "Some Folder/tet.obj"
    assert catalog.get("test-moved").n_triangles == 4


def test_missing_member_names_the_scene_files_of_the_archive(server, cache, monkeypatch):
    base, files, _ = server
    archive = zip_bytes({"a/other.obj": TET_OBJ})
    files["/wrong.zip"] = archive
    add_entry(monkeypatch, "test-wrong-member", f"{base}/wrong.zip", archive, archive="zip",
              member="a/tet.obj")  # fmt: skip
    with pytest.raises(SceneFileError, match=r"a/tet\.obj is not in wrong\.zip.*a/other\.obj"):
        fetch("test-wrong-member")


def test_tar_gz_archive_with_a_ply_member(server, cache, monkeypatch):
    base, files, counts = server
    mesh = procedural.cornell_box()
    archive = tar_gz_bytes({"box/reconstruction/box.ply": ply_bytes([mesh])})
    files["/box.tar.gz"] = archive
    add_entry(monkeypatch, "test-tar", f"{base}/box.tar.gz", archive, archive="tar",
              member="box/reconstruction/box.ply")  # fmt: skip
    path = fetch("test-tar")
    loaded = catalog.get("test-tar")
    assert path.name == "box.ply"
    np.testing.assert_array_equal(loaded.vertices, mesh.vertices)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    fetch("test-tar")
    assert counts["/box.tar.gz"] == 1


def test_gzipped_ply_is_used_as_it_is(server, cache, monkeypatch):
    base, files, _ = server
    mesh = procedural.sphereflake(level=1)
    data = gzip.compress(ply_bytes([mesh]))
    files["/flake.ply.gz"] = data
    add_entry(monkeypatch, "test-gz", f"{base}/flake.ply.gz", data)
    path = fetch("test-gz")
    assert path.name == "flake.ply.gz"
    assert catalog.get("test-gz").n_triangles == mesh.n_triangles


def test_parts_matching_a_glob_are_concatenated_into_one_ply(server, cache, monkeypatch):
    base, files, counts = server
    first = procedural.cornell_box()
    second = TriangleMesh(np.array([[5, 5, 5], [6, 5, 5], [5, 6, 5]], np.float32),
                          np.array([[0, 1, 2]], np.int32))  # fmt: skip
    archive = zip_bytes({
        "room/scene.pbrt": b"# not a mesh",
        "room/models/Mesh000.ply": ply_bytes([first]),
        "room/models/Mesh001.ply": ply_bytes([second]),
        "room/textures/Mesh999.ply.txt": b"not matched",
    })  # fmt: skip
    files["/room.zip"] = archive
    add_entry(monkeypatch, "test-room", f"{base}/room.zip", archive, archive="zip",
              member="*models/*.ply")  # fmt: skip

    path = fetch("test-room")
    assert path == cache / "scenes" / "test-room.ply"
    loaded = catalog.get("test-room")
    assert loaded.n_triangles == first.n_triangles + 1
    np.testing.assert_array_equal(loaded.vertices, np.vstack([first.vertices, second.vertices]))
    np.testing.assert_array_equal(loaded.faces[-1], [first.n_vertices + i for i in range(3)])
    assert fetch("test-room") == path
    assert counts["/room.zip"] == 1


def test_entries_sharing_a_url_share_one_download(server, cache, monkeypatch):
    base, files, counts = server
    archive = zip_bytes({"full.obj": TET_OBJ, "low.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"})
    files["/pair.zip"] = archive
    add_entry(
        monkeypatch, "test-full", f"{base}/pair.zip", archive, archive="zip", member="full.obj"
    )
    add_entry(monkeypatch, "test-low", f"{base}/pair.zip", archive, archive="zip", member="low.obj")
    fetch("test-full")
    assert catalog.get("test-full").n_triangles == 4
    fetch("test-low")
    assert catalog.get("test-low").n_triangles == 1
    assert counts["/pair.zip"] == 1


def test_force_downloads_again_and_a_damaged_cache_is_repaired(server, cache, monkeypatch):
    base, files, counts = server
    files["/tet.obj"] = TET_OBJ
    add_entry(monkeypatch, "test-tet", f"{base}/tet.obj", TET_OBJ)
    path = fetch("test-tet")
    fetch("test-tet", force=True)
    assert counts["/tet.obj"] == 2
    path.write_bytes(b"v 0 0 0\n")  # damaged or tampered with in the cache
    assert fetch("test-tet").read_bytes() == TET_OBJ
    assert counts["/tet.obj"] == 3


# -- refusals --------------------------------------------------------------------------------


def test_wrong_hash_is_refused_and_leaves_no_file(server, cache, monkeypatch):
    base, files, counts = server
    files["/tet.obj"] = TET_OBJ
    add_entry(monkeypatch, "test-bad", f"{base}/tet.obj", TET_OBJ, sha256=sha256(b"other"))
    with pytest.raises(SceneFileError, match=r"does not have the known SHA-256 [0-9a-f]{64}"):
        fetch("test-bad")
    assert counts["/tet.obj"] == 1
    assert files_under(cache) == []
    with pytest.raises(UnknownVariantError, match="not fetched yet"):
        catalog.get("test-bad")


def test_wrong_hash_of_an_archive_unpacks_nothing(server, cache, monkeypatch):
    base, files, _ = server
    archive = zip_bytes({"tet.obj": TET_OBJ})
    files["/tet.zip"] = archive
    add_entry(monkeypatch, "test-bad-zip", f"{base}/tet.zip", archive, archive="zip",
              member="tet.obj", sha256="0" * 64)  # fmt: skip
    with pytest.raises(SceneFileError, match="SHA-256"):
        fetch("test-bad-zip")
    assert files_under(cache) == []


def test_http_404_is_a_clear_error(server, cache, monkeypatch):
    base, _, counts = server
    add_entry(monkeypatch, "test-missing", f"{base}/gone.obj", TET_OBJ)
    with pytest.raises(SceneFileError, match=r"test-missing.*gone\.obj failed with HTTP 404"):
        fetch("test-missing")
    assert counts["/gone.obj"] == 1
    assert files_under(cache) == []


def test_refused_connection_is_a_clear_error(cache, monkeypatch):
    with socket.socket() as probe:  # a port nothing listens on once the probe closes
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    add_entry(monkeypatch, "test-refused", f"http://127.0.0.1:{port}/tet.obj", TET_OBJ)
    with pytest.raises(SceneFileError, match=r"could not download http://127\.0\.0\.1:\d+/tet"):
        fetch("test-refused")
    assert files_under(cache) == []


def test_entry_without_hash_needs_verify_false(server, cache, monkeypatch):
    base, files, counts = server
    files["/tet.obj"] = TET_OBJ
    add_entry(monkeypatch, "test-nohash", f"{base}/tet.obj", TET_OBJ, sha256=None)
    with pytest.raises(SceneFileError, match=r"no published SHA-256.*verify=False.*--no-verify"):
        fetch("test-nohash")
    assert counts["/tet.obj"] == 0
    assert files_under(cache) == []
    path = fetch("test-nohash", verify=False)
    assert path.read_bytes() == TET_OBJ
    assert fetch("test-nohash", verify=False) == path
    assert counts["/tet.obj"] == 1
    assert catalog.get("test-nohash").n_triangles == 4


def test_archive_member_escaping_the_cache_is_refused(server, cache, monkeypatch, tmp_path):
    base, files, _ = server
    archive = zip_bytes({"../../escaped.obj": TET_OBJ, "tet.obj": TET_OBJ})
    files["/evil.zip"] = archive
    add_entry(monkeypatch, "test-evil", f"{base}/evil.zip", archive, archive="zip",
              member="tet.obj")  # fmt: skip
    with pytest.raises(SceneFileError, match="would unpack outside the cache"):
        fetch("test-evil")
    assert not list(tmp_path.rglob("escaped.obj"))


def test_unknown_name_gets_a_suggestion(cache):
    with pytest.raises(UnknownVariantError, match=r"did you mean 'stanford-bunny'"):
        fetch("stanford-buny")
    with pytest.raises(UnknownVariantError, match=r"did you mean 'crytek-sponza'"):
        fetch("crytek_sponsa")


def test_catalog_suggests_fetching_a_downloadable_scene(cache):
    with pytest.raises(UnknownVariantError, match=r"not fetched yet.*scenes fetch happy-buddha"):
        catalog.get("happy-buddha", search_path=[])


# -- the catalog of downloadable scenes ------------------------------------------------------


def test_catalog_entries_are_well_formed():
    assert ra.scenes.fetch is fetch
    assert {"crytek-sponza", "san-miguel", "stanford-bunny", "stanford-dragon", "happy-buddha",
            "lucy", "staircase", "living-room", "kitchen"} <= set(REMOTE_SCENES)  # fmt: skip
    for name, entry in REMOTE_SCENES.items():
        assert entry.name == name
        assert name not in catalog._PROCEDURAL
        assert entry.url.startswith("https://")
        assert entry.sha256 is None or re.fullmatch(r"[0-9a-f]{64}", entry.sha256)
        assert (entry.sha256 is None) == (entry.source_of_hash == "")
        assert entry.archive in (None, "zip", "tar")
        assert (entry.archive is None) == (entry.member is None)
        if entry.archive is None:
            assert entry.url.lower().endswith((".ply.gz", ".obj", ".ply"))
        assert entry.licence
        assert entry.credit


def test_ply_bytes_round_trips_through_the_loader(tmp_path):
    mesh = procedural.teapot()
    path = tmp_path / "teapot.ply"
    path.write_bytes(ply_bytes([mesh, mesh]))
    loaded = load_mesh(path)
    assert loaded.n_triangles == 2 * mesh.n_triangles
    np.testing.assert_array_equal(loaded.faces[mesh.n_triangles :], mesh.faces + mesh.n_vertices)


def test_cache_dir_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_DIR_VAR, str(tmp_path / "elsewhere"))
    assert fetch_module.cache_dir() == tmp_path / "elsewhere"
    monkeypatch.delenv(CACHE_DIR_VAR)
    assert fetch_module.cache_dir().name == "rayaccel"


# -- command line ----------------------------------------------------------------------------


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_fetch_then_list_remote(server, cache, monkeypatch, capsys):
    base, files, counts = server
    files["/tet.obj"] = TET_OBJ
    add_entry(monkeypatch, "test-tet", f"{base}/tet.obj", TET_OBJ)

    code, out, _ = run(capsys, "scenes", "list", "--remote")
    assert code == 0
    line = next(line for line in out.splitlines() if line.strip().startswith("test-tet"))
    assert "not fetched" in line
    assert "sha256 known" in line
    assert "licence: CC0 (test)" in out
    assert "credit: the rayaccel tests" in out
    assert re.search(r"staircase .*NO published sha256", out)

    code, out, _ = run(capsys, "scenes", "fetch", "test-tet")
    assert code == 0
    assert out.strip().endswith("tet.obj")
    assert counts["/tet.obj"] == 1

    code, out, _ = run(capsys, "scenes", "list", "--remote", "--json")
    row = next(r for r in json.loads(out) if r["name"] == "test-tet")
    assert row["cached"] is True
    assert row["sha256"] == sha256(TET_OBJ)
    assert row["path"].endswith("tet.obj")

    code, out, _ = run(capsys, "scenes", "list")
    assert code == 0
    assert re.search(r"test-tet .*fetched: tet\.obj", out)
    assert "teapot" in out

    assert load_scene("test-tet").n_triangles == 4  # what 'info', 'render', 'bench' use


def test_cli_refusals(server, cache, monkeypatch, capsys):
    base, files, counts = server
    files["/tet.obj"] = TET_OBJ
    add_entry(monkeypatch, "test-nohash", f"{base}/tet.obj", TET_OBJ, sha256=None)

    code, _, err = run(capsys, "scenes", "fetch", "test-nohash")
    assert code == 1
    assert "no published SHA-256" in err
    assert "--no-verify" in err
    assert counts["/tet.obj"] == 0

    code, out, err = run(capsys, "scenes", "fetch", "test-nohash", "--no-verify")
    assert code == 0
    assert out.strip().endswith("tet.obj")
    assert (
        f"downloaded unchecked (no published SHA-256); its download has SHA-256 {sha256(TET_OBJ)}"
        in err
    )
    assert counts["/tet.obj"] == 1

    code, _, err = run(capsys, "scenes", "fetch", "stanford-buny")
    assert code == 1
    assert "did you mean 'stanford-bunny'" in err

    code, _, err = run(capsys, "scenes", "fetch")
    assert code == 1
    assert "name at least one scene" in err
