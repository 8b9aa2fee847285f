"""Malformed and hostile scene files: each gets a SceneFileError naming the file and the fault.

Every case here is a file a user could hand to :func:`rayaccel.scene.io.load_mesh`:
headers whose counts disagree with the data, truncated or padded binary bodies,
declared counts far beyond the data (which must fail before anything of the
declared size is allocated), decompression bombs, empty files of every format,
indices out of range, non-finite vertices. The contract is written down in
``docs/reliability.md`` ("Files").
"""

from __future__ import annotations

import gzip
import json
import re
import struct
import time
import tracemalloc

import numpy as np
import pytest

from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.scene.io import load_mesh

MAX_SCENE_BYTES_VAR = "RAYACCEL_MAX_SCENE_BYTES"

SQUARE = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (0.0, 1.0, 0.0), (0.5, 0.5, 1.0)]
#: A triangle, a quad and a pentagon over SQUARE: 1 + 2 + 3 triangles.
MIXED = [(0, 1, 4), (0, 1, 2, 3), (0, 1, 2, 3, 4)]
TRIS = [(0, 1, 2), (0, 2, 3), (0, 1, 4), (1, 2, 4)]
PLY_TYPES = {"uchar": "B", "int": "i", "uint": "I", "float": "f", "double": "d", "short": "h"}


def ply_bytes(
    vertices=SQUARE,
    faces=TRIS,
    *,
    fmt="binary_little_endian",
    n_vertices=None,
    n_faces=None,
    coord="float",
    count_type="uchar",
    index_type="int",
    extra_elements="",
    tail=b"",
):
    """A PLY file; ``n_vertices``/``n_faces`` override the counts the header declares."""
    header = (
        f"ply\nformat {fmt} 1.0\ncomment hostile\n"
        f"element vertex {len(vertices) if n_vertices is None else n_vertices}\n"
        f"property {coord} x\nproperty {coord} y\nproperty {coord} z\n"
        f"element face {len(faces) if n_faces is None else n_faces}\n"
        f"property list {count_type} {index_type} vertex_indices\n{extra_elements}end_header\n"
    ).encode()
    if fmt == "ascii":
        rows = [" ".join(repr(float(c)) for c in v) for v in vertices]
        rows += [" ".join(str(i) for i in (len(f), *f)) for f in faces]
        return header + ("\n".join(rows) + "\n").encode() + tail
    order = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(struct.pack(order + PLY_TYPES[coord] * 3, *v) for v in vertices)
    for face in faces:
        body += struct.pack(order + PLY_TYPES[count_type], len(face))
        body += struct.pack(order + PLY_TYPES[index_type] * len(face), *face)
    return header + body + tail


def stl_binary(triangles, *, n_declared=None, header=b"binary stl"):
    head = header.ljust(80, b" ")[:80]
    count = len(triangles) if n_declared is None else n_declared
    body = b"".join(
        struct.pack("<12fH", 0, 0, 1, *np.asarray(t, dtype=np.float32).ravel(), 0)
        for t in triangles
    )
    return head + struct.pack("<I", count) + body


STL_TRIANGLES = [[SQUARE[a], SQUARE[b], SQUARE[c]] for a, b, c in TRIS]

STL_ASCII = """solid square
facet normal 0 0 1
 outer loop
  vertex 0 0 0
  vertex 1 0 0
  vertex 1 1 0
 endloop
endfacet
facet normal 0 0 1
 outer loop
  vertex 0 0 0
  vertex 1 1 0
  vertex 0 1 0
 endloop
endfacet
endsolid square
"""


def write(tmp_path, name, data):
    path = tmp_path / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def refused(path, *patterns, **kwargs):
    """Assert load_mesh refuses ``path`` with a message naming it and matching ``patterns``."""
    with pytest.raises(SceneFileError) as info:
        load_mesh(path, **kwargs)
    message = str(info.value)
    assert str(path) in message, message
    reason = message.replace(str(path), "<path>")  # patterns must match the reason, not the name
    for pattern in patterns:
        assert re.search(pattern, reason), f"{pattern!r} not in {message!r}"
    return message


# ------------------------------------------------------------------ PLY: counts vs data


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_vertex_count_smaller_than_data(tmp_path, fmt):
    # One vertex row fewer than written: the last vertex would be read as a face.
    path = write(tmp_path, "fewer.ply", ply_bytes(fmt=fmt, n_vertices=4))
    refused(path, r"line \d+" if fmt == "ascii" else r"byte \d+")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_face_count_smaller_than_data(tmp_path, fmt):
    path = write(tmp_path, "trailing.ply", ply_bytes(fmt=fmt, n_faces=2))
    refused(path, r"unexpected data after the last element", r"(line|byte) \d+")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_face_count_larger_than_data(tmp_path, fmt):
    path = write(tmp_path, "short.ply", ply_bytes(fmt=fmt, n_faces=9))
    refused(path, r"(9 face|face.*9|ends|truncated|short)")


def test_truncated_binary_ply_names_the_byte_offset(tmp_path):
    data = ply_bytes()
    path = write(tmp_path, "cut.ply", data[:-7])
    refused(path, r"byte \d+", r"(ends|truncated)")


def test_ply_ascii_trailing_tokens_on_a_row(tmp_path):
    data = ply_bytes(fmt="ascii").replace(b"\n3 0 1 2\n", b"\n3 0 1 2 7\n")
    refused(write(tmp_path, "extra.ply", data), r"line \d+")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_negative_count(tmp_path, fmt):
    path = write(tmp_path, "negative.ply", ply_bytes(fmt=fmt, n_vertices=-5))
    refused(path, r"-5", r"(count|negative)")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("which", ["vertices", "faces", "both"])
def test_ply_huge_declared_counts_fail_fast_without_allocating(tmp_path, fmt, which):
    huge = 2_000_000_000
    data = ply_bytes(
        fmt=fmt,
        n_vertices=huge if which in ("vertices", "both") else None,
        n_faces=huge if which in ("faces", "both") else None,
    )
    path = write(tmp_path, "huge.ply", data)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        refused(path, r"(declare|ends|truncated|byte|line|2000000000)")
        elapsed = time.perf_counter() - start
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert elapsed < 2.0
    assert peak < 16 * 2**20  # the declared size would be gigabytes


def test_ply_list_count_of_huge_value_in_binary(tmp_path):
    # A face row declaring 2**31 - 1 indices (int count type) in a tiny file.
    data = ply_bytes(count_type="int")
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    first_face = header_end + 5 * 12
    data = data[:first_face] + struct.pack("<i", 2**31 - 1) + data[first_face + 4 :]
    refused(write(tmp_path, "list.ply", data), r"byte \d+")


def test_ply_negative_list_count(tmp_path):
    data = ply_bytes(count_type="int")
    first_face = data.index(b"end_header\n") + len(b"end_header\n") + 5 * 12
    data = data[:first_face] + struct.pack("<i", -3) + data[first_face + 4 :]
    refused(write(tmp_path, "neglist.ply", data), r"negative list count \(-3\)", r"byte \d+")


# ------------------------------------------------------------------ PLY: valid but unusual


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_ply_mixed_polygons_are_fan_triangulated(tmp_path, fmt):
    mesh = load_mesh(write(tmp_path, "mixed.ply", ply_bytes(faces=MIXED, fmt=fmt)))
    assert mesh.n_triangles == 6
    assert mesh.faces.tolist() == [
        [0, 1, 4],
        [0, 1, 2],
        [0, 2, 3],
        [0, 1, 2],
        [0, 2, 3],
        [0, 3, 4],
    ]
    np.testing.assert_array_equal(mesh.vertices, np.asarray(SQUARE, dtype=np.float32))


def test_ply_other_elements_and_properties_are_skipped(tmp_path):
    extra = "element edge 2\nproperty int vertex1\nproperty int vertex2\n"
    data = ply_bytes(faces=MIXED, extra_elements=extra, tail=struct.pack("<4i", 0, 1, 1, 2))
    mesh = load_mesh(write(tmp_path, "edges.ply", data))
    assert mesh.n_triangles == 6


# ------------------------------------------------------------------ PLY: bad content


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_face_index_out_of_range(tmp_path, fmt):
    faces = [(0, 1, 2), (0, 2, 5)]
    path = write(tmp_path, "range.ply", ply_bytes(faces=faces, fmt=fmt))
    refused(path, r"face 1", r"\b5\b", r"(range|5 vertices)", r"at (line|byte) \d+")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_negative_face_index(tmp_path, fmt):
    path = write(tmp_path, "negindex.ply", ply_bytes(faces=[(0, 1, 2), (0, -1, 2)], fmt=fmt))
    refused(path, r"face 1", r"-1", r"at (line|byte) \d+")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_ply_non_finite_vertex(tmp_path, fmt, value):
    vertices = [*SQUARE[:2], (1.0, value, 0.0), *SQUARE[3:]]
    path = write(tmp_path, "nonfinite.ply", ply_bytes(vertices=vertices, fmt=fmt))
    refused(path, r"vertex 2 is not finite", r"at (line|byte) \d+")


def test_ply_double_beyond_float32_range(tmp_path):
    vertices = [*SQUARE[:2], (1.0, 1e300, 0.0), *SQUARE[3:]]
    path = write(tmp_path, "wide.ply", ply_bytes(vertices=vertices, coord="double"))
    refused(path, r"vertex 2", r"float32")


def test_ply_face_with_two_corners(tmp_path):
    path = write(tmp_path, "edge.ply", ply_bytes(faces=[(0, 1, 2), (0, 1)]))
    refused(path, r"face 1", r"2 vertices|at least 3")


def test_ply_non_integer_index_type(tmp_path):
    path = write(tmp_path, "floatidx.ply", ply_bytes(index_type="float"))
    refused(path, r"float", r"vertex_indices")


@pytest.mark.parametrize(
    ("header", "pattern"),
    [
        (b"ply\nformat ascii 1.0\nelement vertex 3\n", r"end_header"),
        (b"ply\nformat binary_middle_endian 1.0\nend_header\n", r"format"),
        (b"ply\nformat ascii 1.0\nelement vertex three\nend_header\n", r"line 3"),
        (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", r"line 3"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n",
            r"float128",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nelement face 1\n"
            b"property list uchar int vertex_indices\nend_header\n0\n3 0 0 0\n",
            r"no property y, z",
        ),
        (b"plx\nformat ascii 1.0\nend_header\n", r"not a PLY"),
    ],
)
def test_ply_bad_headers(tmp_path, header, pattern):
    refused(write(tmp_path, "header.ply", header), pattern)


@pytest.mark.parametrize("faces", [TRIS, MIXED])
def test_ascii_ply_unparsable_number_names_the_line(tmp_path, faces):
    data = ply_bytes(faces=faces, fmt="ascii")
    lines = data.split(b"\n")
    row = lines.index(b"end_header") + 7  # the second face row
    lines[row] = lines[row][:-1] + b"x"
    refused(write(tmp_path, "token.ply", b"\n".join(lines)), rf"line {row + 1}: cannot parse")


def test_ascii_ply_non_ascii_byte_names_the_line(tmp_path):
    data = ply_bytes(fmt="ascii").replace(b"\n3 0 1 2\n", b"\n3 0 1 2\xe9\n")
    refused(write(tmp_path, "accent.ply", data), r"line \d+: non-ASCII")


def test_ply_header_at_the_end_of_the_file_without_a_newline(tmp_path):
    data = ply_bytes(n_faces=0, n_vertices=0)
    data = data[: data.index(b"end_header") + len(b"end_header")]
    refused(write(tmp_path, "bare.ply", data), r"no triangles")


def test_ply_without_faces(tmp_path):
    text = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    text += "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    refused(write(tmp_path, "points.ply", text), r"no (faces|triangles)")


# ------------------------------------------------------------------ STL


@pytest.mark.parametrize("n_declared", [0, 3, 5, 1000, 2**32 - 1])
def test_binary_stl_count_disagrees_with_size(tmp_path, n_declared):
    path = write(tmp_path, "count.stl", stl_binary(STL_TRIANGLES, n_declared=n_declared))
    message = refused(path, str(n_declared), r"\b284 bytes")
    assert "module" not in message
    assert "install" not in message


def test_binary_stl_header_starting_with_solid(tmp_path):
    # Many exporters write "solid" into the binary header; the size decides.
    path = write(tmp_path, "solidhead.stl", stl_binary(STL_TRIANGLES, header=b"solid exported"))
    mesh = load_mesh(path)
    assert mesh.n_triangles == 4
    np.testing.assert_array_equal(mesh.triangles(), np.asarray(STL_TRIANGLES, dtype=np.float32))


def test_binary_stl_truncated(tmp_path):
    path = write(tmp_path, "cut.stl", stl_binary(STL_TRIANGLES)[:-10])
    refused(path, r"4 triangles|declares")


def test_binary_stl_non_finite(tmp_path):
    triangles = [list(t) for t in STL_TRIANGLES]
    triangles[2] = [SQUARE[0], (float("nan"), 0.0, 0.0), SQUARE[4]]
    refused(write(tmp_path, "nan.stl", stl_binary(triangles)), r"vertex 7 is not finite")


def test_ascii_stl_loads_and_counts(tmp_path):
    mesh = load_mesh(write(tmp_path, "ascii.stl", STL_ASCII))
    assert mesh.n_triangles == 2


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        (
            STL_ASCII.replace(
                "  vertex 1 1 0\n endloop\nendfacet\nfacet", " endloop\nendfacet\nfacet", 1
            ),
            r"line \d+",
        ),
        (STL_ASCII.replace("vertex 0 1 0", "vertex 0 1"), r"line 13"),
        (STL_ASCII.replace("vertex 0 1 0", "vertex 0 one 0"), r"line 13"),
        (STL_ASCII[: STL_ASCII.index(" endloop")], r"(ends|truncated|endloop)"),
        ("solid nothing\nendsolid nothing\n", r"no (faces|triangles)"),
    ],
)
def test_ascii_stl_errors(tmp_path, text, pattern):
    refused(write(tmp_path, "bad.stl", text), pattern)


# ------------------------------------------------------------------ empty files, odd paths


@pytest.mark.parametrize(
    "suffix", [".obj", ".ply", ".stl", ".glb", ".gltf", ".obj.gz", ".ply.gz", ".stl.gz", ".glb.gz"]
)
def test_empty_file_of_each_format(tmp_path, suffix):
    refused(write(tmp_path, f"empty{suffix}", b""), r"empty")


@pytest.mark.parametrize("suffix", [".ply.gz", ".stl.gz", ".glb.gz", ".obj.gz"])
def test_gzip_of_nothing(tmp_path, suffix):
    refused(write(tmp_path, f"nothing{suffix}", gzip.compress(b"")), r"empty")


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".glb", ".gltf", ".ply.gz"])
def test_directory_instead_of_file(tmp_path, suffix):
    folder = tmp_path / f"folder{suffix}"
    folder.mkdir()
    refused(folder, r"not a regular file")


@pytest.mark.parametrize("name", ["scene.xyz", "scene", "scene.ply.bz2", "scene.gltf.gz"])
def test_unknown_suffix(tmp_path, name):
    refused(write(tmp_path, name, b"ply\n"), r"unsupported scene format")


# ------------------------------------------------------------------ GLB / glTF


def test_glb_wrong_magic_and_lengths(tmp_path):
    refused(write(tmp_path, "magic.glb", b"gLTF" + bytes(16)), r"magic|not a GLB")
    header = struct.pack("<4sII", b"glTF", 2, 4000)
    refused(write(tmp_path, "length.glb", header + bytes(20)), r"4000")
    chunk = struct.pack("<I4s", 999, b"JSON") + b"{}  "
    blob = struct.pack("<4sII", b"glTF", 2, 12 + len(chunk)) + chunk
    refused(write(tmp_path, "chunk.glb", blob), r"999")


@pytest.mark.parametrize("text", ["{", "[]", "null", '{"asset": {"version": "2.0"}}'])
def test_gltf_without_geometry(tmp_path, text):
    refused(
        write(tmp_path, "bad.gltf", text), r"(invalid JSON|expected a JSON object|no triangles)"
    )


def test_gltf_external_buffer_missing_or_outside(tmp_path):
    doc = {"asset": {"version": "2.0"}, "buffers": [{"uri": "missing.bin", "byteLength": 12}]}
    refused(write(tmp_path, "missing.gltf", json.dumps(doc)), r"missing\.bin")
    doc["buffers"][0]["uri"] = "/dev/zero"
    refused(write(tmp_path, "devzero.gltf", json.dumps(doc)), r"/dev/zero")


def gltf_files(tmp_path, name, edit):
    """Export a small glTF, let ``edit`` change its JSON, write it; return the .gltf path."""
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.Trimesh(np.asarray(SQUARE), np.asarray(TRIS), process=False)
    files = mesh.export(file_type="gltf")
    doc = json.loads(files["model.gltf"])
    edit(doc)
    for file_name, blob in files.items():
        if file_name != "model.gltf":
            (tmp_path / file_name).write_bytes(blob)
    return write(tmp_path, name, json.dumps(doc))


def test_gltf_round_trip_through_the_checks(tmp_path):
    assert load_mesh(gltf_files(tmp_path, "plain.gltf", lambda doc: None)).n_triangles == 4


def test_gltf_accessor_count_beyond_buffer(tmp_path):
    def edit(doc):
        for accessor in doc["accessors"]:
            accessor["count"] = 2_000_000_000

    refused(gltf_files(tmp_path, "big.gltf", edit), r"accessor 0 declares 2000000000")


def test_gltf_accessor_without_buffer_view_and_huge_count(tmp_path):
    def edit(doc):
        doc["accessors"][0].pop("bufferView")
        doc["accessors"][0]["count"] = 2_000_000_000

    refused(gltf_files(tmp_path, "zeros.gltf", edit), r"no bufferView")


def test_gltf_buffer_view_past_its_buffer(tmp_path):
    def edit(doc):
        doc["bufferViews"][0]["byteLength"] = 10**9

    refused(gltf_files(tmp_path, "view.gltf", edit), r"bufferView 0 ends at byte")


@pytest.mark.parametrize(
    ("key", "value"), [("componentType", [5126]), ("type", {"a": 1}), ("count", -1)]
)
def test_gltf_accessor_fields_of_the_wrong_type(tmp_path, key, value):
    def edit(doc):
        doc["accessors"][0][key] = value

    refused(gltf_files(tmp_path, "types.gltf", edit), r"accessor 0")


def _chain(doc, n):
    doc["nodes"] = [{"mesh": 0, "children": [i + 1]} for i in range(n)] + [{"mesh": 0}]
    doc["scenes"][0]["nodes"] = [0]


@pytest.mark.parametrize(
    ("edit", "pattern"),
    [
        (lambda doc: doc["nodes"][0].update(children=[0]), r"own child"),
        (
            lambda doc: _chain(doc, 2) or doc["nodes"][2].update(children=[0]),
            r"cycle",
        ),
        (lambda doc: doc["nodes"].append({"children": [0, 0]}), r"more than one parent"),
        (lambda doc: doc["nodes"][0].update(children=[7]), r"child 7"),
        (lambda doc: _chain(doc, 2000), r"levels deep"),
    ],
)
def test_gltf_node_hierarchy_must_be_shallow_disjoint_trees(tmp_path, edit, pattern):
    start = time.perf_counter()
    refused(gltf_files(tmp_path, "nodes.gltf", edit), pattern)
    assert time.perf_counter() - start < 2.0  # trimesh takes minutes on a 2000-node chain


def test_gltf_moderately_deep_hierarchy_loads(tmp_path):
    mesh = load_mesh(gltf_files(tmp_path, "chain.gltf", lambda doc: _chain(doc, 40)))
    assert mesh.n_triangles == 41 * 4


@pytest.mark.parametrize("uri", ["a\u0000b.bin", "x" * 5000 + ".bin", "../outside.bin"])
def test_gltf_buffer_uri_that_cannot_be_read(tmp_path, uri):
    def edit(doc):
        doc["buffers"][0]["uri"] = uri

    refused(gltf_files(tmp_path, "uri.gltf", edit), r"buffer 0 refers to")


# ------------------------------------------------------------------ size limits, gzip


def test_gzip_bomb_fails_fast_naming_the_limit(tmp_path):
    # 64 MiB of zeros compress to about 64 KiB; the limit is 1 MiB.
    data = ply_bytes(n_vertices=2**24, n_faces=0) + bytes(64 * 2**20)
    path = write(tmp_path, "bomb.ply.gz", gzip.compress(data, compresslevel=1))
    tracemalloc.start()
    try:
        refused(
            path, r"1048576 bytes|1 MiB", r"max_bytes|RAYACCEL_MAX_SCENE_BYTES", max_bytes=2**20
        )
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20


def test_size_limit_from_the_environment(tmp_path, monkeypatch):
    path = write(tmp_path, "plain.ply", ply_bytes())
    assert load_mesh(path).n_triangles == 4
    monkeypatch.setenv(MAX_SCENE_BYTES_VAR, "100")
    refused(path, r"100 bytes", MAX_SCENE_BYTES_VAR)
    monkeypatch.setenv(MAX_SCENE_BYTES_VAR, "lots")
    with pytest.raises(InvalidInputError, match=MAX_SCENE_BYTES_VAR):
        load_mesh(path)


def test_size_limit_argument_is_validated(tmp_path):
    path = write(tmp_path, "plain.ply", ply_bytes())
    for bad in (0, -1, 1.5, "10"):
        with pytest.raises(InvalidInputError, match="max_bytes"):
            load_mesh(path, max_bytes=bad)


def test_truncated_gzip(tmp_path):
    blob = gzip.compress(ply_bytes())
    refused(write(tmp_path, "cut.ply.gz", blob[: len(blob) // 2]), r"(gzip|compressed|ends)")


def test_gzip_with_trailing_garbage(tmp_path):
    blob = gzip.compress(ply_bytes()) + b"garbage!"
    refused(write(tmp_path, "tail.ply.gz", blob), r"gzip|compressed")


def test_gzip_ply_loads(tmp_path):
    path = write(tmp_path, "mixed.ply.gz", gzip.compress(ply_bytes(faces=MIXED)))
    assert load_mesh(path).n_triangles == 6


# ------------------------------------------------------------------ OBJ


def test_obj_non_utf8_names_load(tmp_path):
    text = b"o caf\xe9\ng d\xfcrer\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    assert load_mesh(write(tmp_path, "latin1.obj", text)).n_triangles == 1


def test_obj_non_utf8_in_a_number(tmp_path):
    text = b"v 0 0 0\nv 1 0 0\nv 0 1\xff 0\nf 1 2 3\n"
    refused(write(tmp_path, "latin1.obj", text), r":3: cannot parse number")


def test_obj_binary_garbage(tmp_path):
    refused(write(tmp_path, "garbage.obj", bytes(range(256)) * 4), r":\d+: ")
