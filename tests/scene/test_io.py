import gzip
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rayaccel.errors import InvalidInputError, SceneFileError
from rayaccel.scene import io as scene_io
from rayaccel.scene.io import load_mesh, parse_obj, scene_stem
from rayaccel.scene.mesh import TriangleMesh

SCENES = Path(__file__).parents[2].parent / "shared" / "scenes"

CUBE_OBJ = """\
# a unit cube
mtllib cube.mtl
o cube
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
vt 0 0
vn 0 0 1
g sides
usemtl white
s off
f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 2 3 7 6
f 3 4 8 7
f 4 1 5 8
l 1 2
"""


def _write(tmp_path, text, name="scene.obj", newline="\n"):
    path = tmp_path / name
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def _sorted_triangles(triangles):
    """Triangles as a canonical sorted array, independent of order and corner rotation."""
    tri = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
    keys = np.sort(tri.reshape(-1, 3).view([("", tri.dtype)] * 3).reshape(-1, 3), axis=1)
    flat = keys.view(tri.dtype).reshape(-1, 9)
    return flat[np.lexsort(flat.T[::-1])]


# ----------------------------------------------------------------- OBJ: accepted forms


def test_cube_quads_are_fan_triangulated():
    vertices, faces = parse_obj(CUBE_OBJ)
    assert vertices.shape == (8, 3)
    assert vertices.dtype == np.float64
    assert faces.shape == (12, 3)
    assert faces.dtype == np.int64
    assert faces[:2].tolist() == [[0, 3, 2], [0, 2, 1]]
    mesh = TriangleMesh(vertices, faces)
    assert mesh.areas().sum() == pytest.approx(6.0)


def test_tabs_crlf_comments_and_leading_whitespace():
    text = "# c\r\nv\t0\t0\t0\r\n  v 1\t 0  0\r\n\tv 0 1 0 # inline\r\n\r\nf\t1\t2\t3\r\n"
    vertices, faces = parse_obj(text)
    assert vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    assert faces.tolist() == [[0, 1, 2]]


def test_old_mac_line_endings_and_bom():
    _vertices, faces = parse_obj("\ufeffv 0 0 0\rv 1 0 0\rv 0 1 0\rf 1 2 3\r")
    assert faces.tolist() == [[0, 1, 2]]
    assert parse_obj(b"\xef\xbb\xbfv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3")[1].tolist() == [[0, 1, 2]]


@pytest.mark.parametrize(
    "face",
    ["f 1 2 3 4", "f 1/1 2/2 3/3 4/4", "f 1//1 2//2 3//3 4//4", "f 1/1/1 2/2/2 3/3/3 4/4/4",
     "f 1/1 2//2 3/3/3 4", "f -4 -3 -2 -1", "f -4/1/1 2/-2 -2//3 4"],
)  # fmt: skip
def test_face_reference_forms(face):
    text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
    _, faces = parse_obj(text + face + "\n")
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3]]


def test_negative_indices_are_relative_to_the_face_line():
    text = (
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 5 5\nv 6 5 5\nv 5 6 5\nf -3 -2 -1\nf 1 -1 2\n"
    )
    _, faces = parse_obj(text)
    assert faces.tolist() == [[0, 1, 2], [3, 4, 5], [0, 5, 1]]


def test_ngon_fan_and_mixed_sizes():
    text = "".join(f"v {i} {i * i} 0\n" for i in range(7)) + "f 1 2 3 4 5 6 7\nf 1 2 3\n"
    _, faces = parse_obj(text)
    assert faces.tolist() == [[0, k, k + 1] for k in range(1, 6)] + [[0, 1, 2]]


def test_line_continuation():
    text = "v 0 0 \\\n 0\nv 1 0 0\nv 0 1 0\nf 1 \\\n2 \\\n3\nf 1 2 x\n"
    with pytest.raises(SceneFileError, match=r"<obj>:8: cannot parse index 'x'"):
        parse_obj(text)
    vertices, faces = parse_obj(text.rsplit("f 1 2 x", 1)[0])
    assert vertices.shape == (3, 3)
    assert faces.tolist() == [[0, 1, 2]]


def test_w_coordinate_and_vertex_colours_are_ignored():
    text = "v 0 0 0 1\nv 1 0 0 0.5\nv 0 1 0 1 0 0\nv 0 0 1 0.2 0.3 0.4 1\nf 1 2 3 4\n"
    vertices, faces = parse_obj(text)
    assert vertices.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    assert faces.shape == (2, 3)


def test_unreferenced_vertices_are_kept_and_forward_references_allowed():
    vertices, faces = parse_obj("f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 9 9 9\n")
    assert vertices.shape == (4, 3)
    assert faces.tolist() == [[0, 1, 2]]


def test_ignored_statements():
    text = "mtllib a.mtl\no obj\ng grp\ns 1\nusemtl m\nvt 0 0\nvn 0 0 1\nvp 0.5\nl 1 2\np 1\n"
    text += "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    assert parse_obj(text)[1].shape == (1, 3)


def test_many_lines_take_the_fast_path(monkeypatch):
    rng = np.random.default_rng(3)
    vertices = rng.uniform(-1, 1, (2000, 3)).round(5)
    faces = rng.integers(0, 2000, (5000, 3))
    text = "".join(f"v {x} {y} {z}\n" for x, y, z in vertices)
    text += "".join(f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}\n" for a, b, c in faces)
    bodies = [line[2:] for line in text.splitlines() if line.startswith("f ")]
    assert scene_io._parse_faces_fast(bodies) is not None
    parsed_v, parsed_f = parse_obj(text)
    np.testing.assert_array_equal(parsed_v, vertices)
    np.testing.assert_array_equal(parsed_f, faces)
    # The same result must come out of the line-by-line parser.
    monkeypatch.setattr(scene_io, "_parse_faces_fast", lambda bodies: None)
    monkeypatch.setattr(scene_io, "_loadtxt", lambda body, dtype: None)
    slow_v, slow_f = parse_obj(text)
    np.testing.assert_array_equal(slow_v, vertices)
    np.testing.assert_array_equal(slow_f, faces)


# ----------------------------------------------------------------- OBJ: errors


def _error(text, source="scene.obj"):
    with pytest.raises(SceneFileError) as info:
        parse_obj(text, source=source)
    return str(info.value)


def test_out_of_range_names_path_line_and_count():
    text = "".join(f"v {i} 0 {i % 2}\n" for i in range(31)) + "f 1 2 3\nf 1 2 40\n"
    assert _error(text) == "scene.obj:33: face index 40 out of range (31 vertices)"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"^scene\.obj:4: face index 0 is invalid"),
        ("v 0 0 0\nv 1 0 0\nf -3 -2 -1\nv 0 1 0\n",
         r"^scene\.obj:3: relative face index -3 out of range \(2 vertices defined"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"^scene\.obj:4: face needs at least 3 vertices"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3.5\n", r"^scene\.obj:4: cannot parse index '3\.5'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 /3\n", r"^scene\.obj:4: malformed face vertex '/3'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3/1/1/1\n", r"^scene\.obj:4: malformed face vertex"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/x 2 3\n", r"^scene\.obj:4: cannot parse index 'x'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n",
         r"^scene\.obj:4: face index 99999999999999999999 out of range"),
        ("v 0 0 0\nv 1,0 0 0\nv 0 1 0\nf 1 2 3\n", r"^scene\.obj:2: cannot parse number '1,0'"),
        ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", r"^scene\.obj:2: vertex needs 3 coordinates, got 2"),
        ("v 0 0 0 1 1\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", r"^scene\.obj:1: vertex has 5 values"),
        ("v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n", r"^scene\.obj:2: vertex 2 is not a finite"),
        ("v 0 0 0\nv 1 0 0\nv 0 1e39 0\nf 1 2 3\n", r"^scene\.obj:3: vertex 3 is not a finite"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf\nf 1 2 3\n", r"^scene\.obj:4: face statement without"),
        ("v 0 0 0\nv\n", r"^scene\.obj:2: vertex statement without data"),
        ("v 0 0 0\ncurv 0 1 1 2\n", r"^scene\.obj:2: free-form geometry \('curv'\)"),
        ("v 0 0 0\nfoo 1 2\n", r"^scene\.obj:2: unknown OBJ statement 'foo'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"^scene\.obj: the file holds no faces"),
        ("", r"^scene\.obj: the file holds no faces"),
        ("# only a comment\n", r"^scene\.obj: the file holds no faces"),
    ],
)  # fmt: skip
def test_malformed_obj_names_the_line(text, message):
    assert re.search(message, _error(text)), _error(text)


def test_error_line_numbers_survive_crlf_and_continuations():
    text = "v 0 0 0\r\nv 1 0 \\\r\n 0\r\nv 0 1 0\r\nf 1 2 3\r\nf 1 2 9\r\n"
    assert _error(text).startswith("scene.obj:6: face index 9 out of range (3 vertices)")


def test_malformed_line_among_many_uniform_ones():
    good = "".join(f"v {i} {i} {i % 3}\n" for i in range(100))
    faces = [f"f {i + 1}/{i + 1} {i + 2}/{i + 2} {i + 3}/{i + 3}" for i in range(97)]
    faces[50] = "f 51/51 52 53/53/53 54"  # valid, but not uniform: slow path
    _vertices, parsed = parse_obj(good + "\n".join(faces))
    assert parsed.shape == (98, 3)
    faces[70] = "f 71/71 72/72/72/1 73/73"
    assert "scene.obj:171: malformed face vertex '72/72/72/1'" in _error(good + "\n".join(faces))


# ----------------------------------------------------------------- OBJ: properties


@st.composite
def obj_documents(draw):
    """A random mesh written in a random OBJ style, and the triangles it must parse to."""
    n_vertices = draw(st.integers(3, 12))
    coords = draw(st.lists(st.integers(-64, 64), min_size=3 * n_vertices, max_size=3 * n_vertices))
    vertices = np.array(coords, dtype=np.float64).reshape(-1, 3) / 8.0
    sep = st.sampled_from([" ", "\t", "  ", " \t "])
    newline = draw(st.sampled_from(["\n", "\r\n"]))
    form = draw(st.sampled_from(["a", "a/b", "a//c", "a/b/c", "mixed"]))
    relative = draw(st.booleans())
    lines = [draw(st.sampled_from(["# header", "o thing", "mtllib x.mtl", "g g1"]))]
    for x, y, z in vertices:
        w = draw(st.sampled_from(["", " 1.0"]))
        x, y, z = (repr(float(value)) for value in (x, y, z))
        lines.append(f"v{draw(sep)}{x}{draw(sep)}{y}{draw(sep)}{z}{w}")
    lines.append("vt 0 0")
    expected = []
    for _ in range(draw(st.integers(1, 8))):
        polygon = draw(st.lists(st.integers(0, n_vertices - 1), min_size=3, max_size=6))
        tokens = []
        for index in polygon:
            ref = index - n_vertices if relative else index + 1
            kind = draw(st.sampled_from(["a", "a/b", "a//c", "a/b/c"])) if form == "mixed" else form
            tokens.append(kind.replace("a", str(ref)).replace("b", "1").replace("c", "1"))
        lines.append("f" + "".join(draw(sep) + token for token in tokens))
        expected += [[polygon[0], polygon[k], polygon[k + 1]] for k in range(1, len(polygon) - 1)]
        if draw(st.booleans()):
            lines.append(draw(st.sampled_from(["s off", "usemtl m", "# note", "", "vn 0 0 1"])))
    return newline.join(lines) + newline, vertices, np.array(expected)


@given(obj_documents())
def test_random_obj_documents_parse_to_their_mesh(document):
    text, vertices, expected = document
    parsed_v, parsed_f = parse_obj(text)
    np.testing.assert_array_equal(parsed_v, vertices)
    np.testing.assert_array_equal(parsed_f, expected)
    # Inline comments force the line-by-line path; the result must not change.
    commented = "\n".join(
        line + (" # c" if line[:1] in ("v", "f") else "") for line in text.split("\n")
    )
    slow_v, slow_f = parse_obj(commented)
    np.testing.assert_array_equal(slow_v, vertices)
    np.testing.assert_array_equal(slow_f, expected)


@given(st.text(alphabet="vf 0123456789/-.#\n\t\\e+", max_size=120))
def test_arbitrary_text_either_parses_or_raises_scene_file_error(text):
    try:
        vertices, faces = parse_obj(text)
    except SceneFileError as exc:
        message = str(exc)
        assert message.startswith("<obj>"), message
        return
    assert faces.shape[1] == 3
    assert faces.shape[0] >= 1
    assert ((faces >= 0) & (faces < vertices.shape[0])).all()
    assert np.isfinite(vertices).all()


# ----------------------------------------------------------------- load_mesh


def test_load_obj_file(tmp_path):
    path = _write(tmp_path, CUBE_OBJ, "cube.obj", newline="\r\n")
    mesh = load_mesh(path)
    assert mesh.name == "cube"
    assert mesh.n_triangles == 12
    assert mesh.vertices.dtype == np.float32
    assert load_mesh(str(path), name="box").name == "box"


def test_load_gzipped_obj(tmp_path):
    path = tmp_path / "cube.obj.gz"
    path.write_bytes(gzip.compress(CUBE_OBJ.encode()))
    assert load_mesh(path).n_triangles == 12
    assert load_mesh(path).name == "cube"


def test_error_message_names_the_path(tmp_path):
    path = _write(tmp_path, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n")
    with pytest.raises(SceneFileError, match=re.escape(f"{path}:4: face index 4 out of range")):
        load_mesh(path)


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(SceneFileError, match=re.escape(f"{tmp_path / 'nope.obj'}: no such file")):
        load_mesh(tmp_path / "nope.obj")
    with pytest.raises(SceneFileError, match="not a regular file"):
        load_mesh(_dir_obj(tmp_path))
    bad = _write(tmp_path, "solid", "thing.xyz")
    with pytest.raises(SceneFileError, match=r"unsupported scene format '\.xyz'"):
        load_mesh(bad)
    assert issubclass(SceneFileError, InvalidInputError)


def _dir_obj(tmp_path):
    folder = tmp_path / "folder.obj"
    folder.mkdir()
    return folder


def test_bad_gzip_is_a_scene_file_error(tmp_path):
    path = tmp_path / "broken.ply.gz"
    path.write_bytes(b"not gzip at all")
    with pytest.raises(SceneFileError, match=r"broken\.ply\.gz"):
        load_mesh(path)


@pytest.fixture
def small_trimesh():
    trimesh = pytest.importorskip("trimesh")
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4], [1, 2, 4]])
    return trimesh.Trimesh(vertices, faces, process=False)


@pytest.mark.parametrize(
    "suffix", [".ply", ".stl", ".glb", ".gltf", ".ply.gz", ".stl.gz", ".glb.gz"]
)
def test_trimesh_formats_round_trip(tmp_path, small_trimesh, suffix):
    plain = suffix.removesuffix(".gz")
    path = tmp_path / f"shape{suffix}"
    if plain == ".gltf":
        for name, blob in small_trimesh.export(file_type="gltf").items():
            (tmp_path / ("shape.gltf" if name == "model.gltf" else name)).write_bytes(blob)
    else:
        blob = small_trimesh.export(file_type=plain.lstrip("."))
        blob = blob.encode() if isinstance(blob, str) else blob
        path.write_bytes(gzip.compress(blob) if suffix.endswith(".gz") else blob)
    mesh = load_mesh(path)
    assert mesh.name == "shape"
    assert mesh.n_triangles == 4
    np.testing.assert_array_equal(
        _sorted_triangles(mesh.triangles()),
        _sorted_triangles(small_trimesh.triangles.astype(np.float32)),
    )


def test_trimesh_file_without_triangles(tmp_path):
    header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    header += "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    path = _write(tmp_path, header, "points.ply")
    with pytest.raises(SceneFileError, match=r"points\.ply: .*(no triangles|cannot read)"):
        load_mesh(path)


def test_trimesh_non_finite_vertex_is_a_scene_file_error(tmp_path):
    text = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    text += "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
    text += "end_header\n0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n"
    path = _write(tmp_path, text, "nan.ply")
    with pytest.raises(SceneFileError, match=r"nan\.ply: vertices: vertex 1 is not finite"):
        load_mesh(path)


def test_corrupt_binary_ply(tmp_path):
    path = tmp_path / "corrupt.ply"
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\n"
                     b"property float x\nproperty float y\nproperty float z\n"
                     b"element face 10\nproperty list uchar int vertex_indices\nend_header\n"
                     b"\x00\x01")  # fmt: skip
    with pytest.raises(SceneFileError, match=r"corrupt\.ply"):
        load_mesh(path)


def test_scene_stem():
    assert scene_stem("a/b/kitchen.ply.gz") == "kitchen"
    assert scene_stem("CornellBox-Original.OBJ") == "CornellBox-Original"
    assert scene_stem("x.tar") == "x"
    assert scene_stem(".obj") == ".obj"  # a dot file has no suffix


# ----------------------------------------------------------------- shared scene files

# name -> (triangles, bbox lo, bbox hi) from scenes/README.md
SHARED = {
    "CornellBox-Original.obj": (36, [-1.02, 0, -1.04], [1, 1.99, 0.99]),
    "stanford-bunny.obj": (69_451, [-0.09469, 0.032987, -0.061874], [0.061009, 0.187321, 0.0588]),
    "sponza_dabrovic.ply": (66_450, [-17.409, -7.799, -0.999001], [17.411, 7.801, 15.561]),
    "living_room.ply": (143_163, [-0.513428, -0.003062, -3.63538], [5.12268, 2.87914, 0.592839]),
    "staircase.ply": (262_663, [-4.10702, -0.16345, -5.20437], [2.50292, 7.15841, 5.13401]),
    "salle_de_bain.ply": (653_694, [-13.7496, -6.41258, -11.6392], [12.642, 16.1097, 17.6197]),
    "kitchen.ply.gz": (1_443_517, [-3.1387, -0.020776, -3.18371], [3.77741, 3.3639, 5.47059]),
}


@pytest.mark.scenes
@pytest.mark.parametrize("file_name", list(SHARED))
def test_shared_scene_counts_and_bounds(file_name):
    path = SCENES / file_name
    if not path.is_file():
        pytest.skip(f"{path} not available")
    n_triangles, lo, hi = SHARED[file_name]
    mesh = load_mesh(path)
    assert mesh.n_triangles == n_triangles
    bounds = mesh.bounds()
    np.testing.assert_allclose(bounds[0], lo, atol=1e-4)
    np.testing.assert_allclose(bounds[1], hi, atol=1e-4)


@pytest.mark.scenes
@pytest.mark.parametrize("file_name", ["CornellBox-Original.obj", "stanford-bunny.obj"])
def test_obj_reader_matches_trimesh_on_shared_files(file_name):
    trimesh = pytest.importorskip("trimesh")
    path = SCENES / file_name
    if not path.is_file():
        pytest.skip(f"{path} not available")
    ours = load_mesh(path)
    theirs = trimesh.load(str(path), force="mesh", process=False)
    np.testing.assert_array_equal(
        _sorted_triangles(ours.triangles()),
        _sorted_triangles(np.asarray(theirs.triangles, dtype=np.float32)),
    )


@pytest.mark.scenes
def test_cornell_obj_is_crlf_and_tab_variant_still_parses(tmp_path):
    path = SCENES / "CornellBox-Original.obj"
    if not path.is_file():
        pytest.skip(f"{path} not available")
    raw = path.read_bytes()
    assert b"\r\n" in raw
    # The original McGuire file separates 'v' with tabs and uses relative indices.
    tabbed = raw.replace(b"v ", b"v\t")
    copy = tmp_path / "tabbed.obj"
    copy.write_bytes(tabbed)
    np.testing.assert_array_equal(load_mesh(copy).triangles(), load_mesh(path).triangles())
