import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rayaccel.errors import InvalidInputError
from rayaccel.scene import procedural
from rayaccel.scene.procedural import (
    CORNELL_BOX_PARTS,
    cornell_box,
    sphereflake,
    sphereflake_spheres,
    teapot,
    teapot_in_stadium,
    triangle_soup,
)
from rayaccel.scene.teapot_data import NEWELL_PATCHES, NEWELL_VERTICES

BUILDERS = [cornell_box, triangle_soup, sphereflake, teapot, teapot_in_stadium]


def _signed_volume(mesh):
    tri = mesh.triangles().astype(np.float64)
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("builder", BUILDERS, ids=lambda f: f.__name__)
def test_builders_are_deterministic_and_well_formed(builder):
    a, b = builder(), builder()
    assert a.vertices.tobytes() == b.vertices.tobytes()
    assert a.faces.tobytes() == b.faces.tobytes()
    assert a.vertices.dtype == np.float32
    assert a.faces.dtype == np.int32
    assert a.vertices.flags.c_contiguous
    assert a.faces.flags.c_contiguous
    assert a.name
    assert a.n_triangles >= 12
    # Every vertex is used by some triangle.
    assert np.unique(a.faces).shape[0] == a.n_vertices


# ------------------------------------------------------------------ Cornell box


def test_cornell_box_layout():
    mesh = cornell_box()
    assert mesh.name == "cornell-box"
    assert mesh.n_triangles == 32
    lo, hi = mesh.bounds()
    np.testing.assert_allclose(lo, [0, 0, 0])
    np.testing.assert_allclose(hi, [556.0, 548.8, 559.2])
    covered = sorted(i for part in CORNELL_BOX_PARTS.values() for i in range(32)[part])
    assert covered == list(range(32))
    assert (mesh.areas() > 0).all()


def test_cornell_box_orientation():
    mesh = cornell_box()
    normals, centroids = mesh.normals(), mesh.triangles().mean(axis=1)
    room_centre = np.array([278.0, 274.4, 279.6])
    for part in ("floor", "light", "ceiling", "back_wall", "left_wall", "right_wall"):
        part_slice = CORNELL_BOX_PARTS[part]
        inward = np.sum(normals[part_slice] * (room_centre - centroids[part_slice]), axis=1)
        assert (inward > 0).all(), part
    for part in ("short_block", "tall_block"):
        part_slice = CORNELL_BOX_PARTS[part]
        centre = centroids[part_slice].mean(axis=0)
        outward = np.sum(normals[part_slice] * (centroids[part_slice] - centre), axis=1)
        assert (outward > 0).all(), part


def test_cornell_light_is_below_the_ceiling():
    tri = cornell_box().triangles()
    light_y = tri[CORNELL_BOX_PARTS["light"]][..., 1]
    ceiling_y = tri[CORNELL_BOX_PARTS["ceiling"]][..., 1]
    assert light_y.max() < ceiling_y.min()


# ------------------------------------------------------------------ triangle soup


def test_soup_defaults():
    mesh = triangle_soup()
    assert mesh.name == "soup"
    assert mesh.n_triangles == 10_000
    assert (mesh.vertices >= 0).all()
    assert (mesh.vertices <= 1).all()
    extent = mesh.triangles().max(axis=1) - mesh.triangles().min(axis=1)
    assert extent.max() <= 10_000 ** (-1 / 3) + 1e-6


@given(st.integers(1, 500), st.integers(0, 2**32), st.floats(0.001, 1.0))
def test_soup_properties(n, seed, size):
    mesh = triangle_soup(n, seed=seed, size=size)
    assert mesh.n_triangles == n
    assert mesh.n_vertices == 3 * n
    assert (mesh.vertices >= 0).all()
    assert (mesh.vertices <= 1).all()
    extent = mesh.triangles().max(axis=1) - mesh.triangles().min(axis=1)
    assert extent.max() <= size * (1 + 1e-6) + 1e-7
    again = triangle_soup(n, seed=seed, size=size)
    assert mesh.vertices.tobytes() == again.vertices.tobytes()


def test_soup_seed_changes_the_mesh_and_the_name():
    a, b = triangle_soup(100, seed=1), triangle_soup(100, seed=2)
    assert a.vertices.tobytes() != b.vertices.tobytes()
    assert a.name == "soup(n_triangles=100, seed=1)"


@pytest.mark.parametrize(
    "kwargs",
    [{"n_triangles": 0}, {"n_triangles": 2.5}, {"n_triangles": True}, {"size": 0.0},
     {"size": 1.5}, {"size": float("nan")}, {"size": "big"}, {"seed": -1}],
)  # fmt: skip
def test_soup_rejects_bad_arguments(kwargs):
    with pytest.raises(InvalidInputError):
        triangle_soup(**kwargs)


# ------------------------------------------------------------------ sphereflake


@pytest.mark.parametrize("level", [0, 1, 2, 3, 4])
def test_sphereflake_sphere_counts_match_spd(level):
    centres, radii = sphereflake_spheres(level)
    assert centres.shape == ((9 ** (level + 1) - 1) // 8, 3)
    assert radii.shape == (centres.shape[0],)
    # SPD balls.c: the whole flake fits in the unit sphere; the root rests on z = -0.5.
    assert (np.linalg.norm(centres, axis=1) + radii).max() <= 1.0
    assert (centres[:, 2] - radii).min() == pytest.approx(-0.5)


def test_sphereflake_children_touch_their_parent_and_not_each_other():
    centres, radii = sphereflake_spheres(2)
    # Level by level: parent p of sphere i (i >= 1) is (i - 1) // 9.
    for i in range(1, centres.shape[0]):
        parent = (i - 1) // 9
        assert radii[i] == pytest.approx(radii[parent] / 3)
        distance = np.linalg.norm(centres[i] - centres[parent])
        assert distance == pytest.approx(radii[i] + radii[parent])
    for first in range(1, centres.shape[0], 9):
        group = slice(first, first + 9)
        gaps = np.linalg.norm(centres[group, None] - centres[None, group], axis=2)
        np.fill_diagonal(gaps, np.inf)
        assert (gaps >= 2 * radii[first] - 1e-12).all()


def test_sphereflake_first_generation_layout():
    centres, radii = sphereflake_spheres(1)
    offsets = (centres[1:] - centres[0]) / (radii[0] + radii[1])
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=1), 1.0)
    elevation = np.degrees(np.arcsin(offsets[:, 2]))
    assert np.sum(np.isclose(elevation, 0.0, atol=1e-9)) == 6
    assert np.sum(np.isclose(elevation, np.degrees(np.arcsin(math.sqrt(2 / 3))))) == 3
    equator = np.sort(
        np.degrees(np.arctan2(offsets[:, 1], offsets[:, 0]))[np.isclose(elevation, 0)]
    )
    np.testing.assert_allclose(np.diff(equator), 60.0)


def test_sphereflake_triangle_counts_and_ground():
    mesh = sphereflake()
    assert mesh.name == "sphereflake"
    assert mesh.n_triangles == 91 * 320 + 2
    bare = sphereflake(1, sphere_subdivisions=0, ground=False)
    assert bare.n_triangles == 10 * 20
    assert bare.name == "sphereflake(level=1, sphere_subdivisions=0, ground=False)"
    lo, hi = mesh.bounds()
    np.testing.assert_allclose(lo, [-12, -12, -0.5])
    assert hi[2] < 1.0


def test_sphereflake_spheres_face_outwards():
    mesh = sphereflake(0, sphere_subdivisions=3, ground=False)
    assert mesh.n_triangles == 20 * 4**3
    outward = np.sum(mesh.normals() * mesh.triangles().mean(axis=1), axis=1)
    assert (outward > 0).all()
    assert _signed_volume(mesh) == pytest.approx(4 / 3 * math.pi * 0.5**3, rel=0.02)


@pytest.mark.parametrize(
    "kwargs", [{"level": -1}, {"level": 8}, {"level": 1.0}, {"sphere_subdivisions": 7}]
)
def test_sphereflake_rejects_bad_arguments(kwargs):
    with pytest.raises(InvalidInputError):
        sphereflake(**kwargs)


# ------------------------------------------------------------------ teapot


def test_teapot_data_tables():
    assert len(NEWELL_VERTICES) == 306
    assert len(NEWELL_PATCHES) == 32
    indices = {i for patch in NEWELL_PATCHES for i in patch}
    assert all(len(patch) == 16 for patch in NEWELL_PATCHES)
    assert min(indices) == 1
    assert max(indices) == 306
    # Four published points are referenced by no patch.
    assert sorted(set(range(1, 307)) - indices) == [205, 206, 216, 223]


@pytest.mark.parametrize("s", [1, 2, 4, 8])
def test_teapot_counts_and_bounds(s):
    mesh = teapot(s)
    assert mesh.n_triangles == 64 * s * s
    assert mesh.n_vertices < 32 * (s + 1) ** 2  # seams are welded
    lo, hi = mesh.bounds()
    np.testing.assert_allclose(lo, [-3.0, -2.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(hi[1:], [2.0, 3.15], atol=1e-6)
    assert 3.3 <= hi[0] < 3.44  # the spout tip (3.434 on the limit surface)
    if s >= 4:
        assert hi[0] > 3.42


def test_teapot_default_and_degenerate_poles():
    mesh = teapot()
    assert mesh.name == "teapot"
    assert mesh.n_triangles == 4096
    # Lid and bottom patches collapse one edge to a point: s zero-area triangles each.
    assert int((mesh.areas() == 0).sum()) == 8 * 8


def test_teapot_faces_outwards_and_converges():
    coarse, fine = teapot(8), teapot(24)
    assert _signed_volume(coarse) > 0
    body = slice(4 * 128, 12 * 128)  # patches 4..11, 2 s^2 = 128 triangles each
    centroids = coarse.triangles()[body].mean(axis=1)
    radial = centroids * np.array([1, 1, 0], dtype=np.float32)
    assert (np.sum(coarse.normals()[body] * radial, axis=1) > 0).all()
    assert coarse.areas().sum() == pytest.approx(fine.areas().sum(), rel=0.01)


def test_teapot_is_mirror_symmetric():
    vertices = teapot(6).vertices.astype(np.float64)
    mirrored = vertices * [1, -1, 1]
    key = np.round(vertices, 4)
    mirrored_key = np.round(mirrored, 4)
    as_set = {tuple(v) for v in key.tolist()}
    missing = [v for v in mirrored_key.tolist() if tuple(v) not in as_set]
    # Allow rounding-boundary stragglers, never a real asymmetry.
    assert len(missing) <= 0.01 * len(key)


def test_teapot_rejects_bad_subdivisions():
    for bad in (0, 65, 2.0, None):
        with pytest.raises(InvalidInputError):
            teapot(bad)


def test_teapot_in_stadium():
    pot, scene = teapot(), teapot_in_stadium()
    assert scene.name == "teapot-in-stadium"
    assert scene.n_triangles == pot.n_triangles + 12
    np.testing.assert_array_equal(scene.vertices[: pot.n_vertices], pot.vertices)
    np.testing.assert_array_equal(scene.faces[: pot.n_triangles], pot.faces)
    pot_lo, pot_hi = pot.bounds()
    lo, hi = scene.bounds()
    width = float((pot_hi - pot_lo)[:2].max())
    assert (hi - lo)[0] == pytest.approx(1000 * width, rel=1e-6)
    assert (hi - lo)[2] == pytest.approx(500 * width + 0.01, rel=1e-4)
    assert lo[2] == pytest.approx(pot_lo[2] - 0.01)
    # The room is closed and faces inwards: its signed volume is minus the box volume.
    room = scene.triangles()[pot.n_triangles :].astype(np.float64)
    volume = np.einsum("ij,ij->i", room[:, 0], np.cross(room[:, 1], room[:, 2])).sum() / 6
    assert volume == pytest.approx(-np.prod((hi - lo).astype(np.float64)), rel=1e-5)
    small = teapot_in_stadium(2, stadium_scale=10.0)
    assert small.name == "teapot-in-stadium(subdivisions=2, stadium_scale=10.0)"
    with pytest.raises(InvalidInputError):
        teapot_in_stadium(stadium_scale=-1.0)


def test_icosphere_is_a_closed_unit_sphere():
    vertices, faces = procedural._icosphere(2)
    np.testing.assert_allclose(np.linalg.norm(vertices, axis=1), 1.0)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # every edge shared by exactly two triangles
    assert vertices.shape[0] - counts.shape[0] + faces.shape[0] == 2  # Euler characteristic
