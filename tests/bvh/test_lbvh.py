"""LBVH pieces: Morton codes, the parallel radix sort, Karras and Apetrei emission, depth bound."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
from rayaccel.bvh.builders.lbvh import LbvhOptions
from rayaccel.bvh.layouts.bvh2 import MAX_DEPTH
from rayaccel.errors import InvalidInputError
from rayaccel.kernels.morton import morton_codes
from rayaccel.kernels.radix_sort import digit_bits, radix_sort


def _mesh(tri):
    tri = np.ascontiguousarray(tri, dtype=np.float64)
    return rayaccel.TriangleMesh(tri.reshape(-1, 3), np.arange(tri.shape[0] * 3).reshape(-1, 3))


@pytest.mark.parametrize(
    ("n_bits", "key_type"),
    [(1, np.int64), (12, np.int64), (13, np.int32), (23, np.int32), (30, np.int64),
     (31, np.int32), (36, np.int64), (63, np.int64)],
)  # fmt: skip
def test_radix_sort_is_a_stable_sort(threads, n_bits, key_type):
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2**n_bits, size=100_000, dtype=np.int64).astype(key_type)
    keys[::7] = keys[3]  # many duplicates: stability matters
    values = np.arange(keys.size, dtype=np.int32)
    order = np.argsort(keys, kind="stable")
    for n in (1, 2):
        threads(n)
        sorted_keys, sorted_values = radix_sort(keys, values, n_bits)
        assert sorted_keys.dtype == key_type
        assert np.array_equal(sorted_keys, keys[order])
        assert np.array_equal(sorted_values, order)


def test_radix_digits_split_the_key_evenly():
    assert [digit_bits(b) for b in (1, 12, 13, 23, 24, 30, 63)] == [1, 12, 7, 12, 12, 10, 11]


def test_morton_codes_interleave_bits():
    lo = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], np.float32)
    codes = morton_codes(lo, lo, 10)
    top = (1 << 10) - 1
    spread = int("".join("001" * 10), 2)  # bit 0 of every triple
    assert codes[0] == 0
    assert codes[1] == spread & ((1 << 30) - 1) or codes[1] > 0
    assert codes[4] == (1 << 30) - 1
    assert codes[1] < codes[2] < codes[3]  # x, then y, then z in each triple
    assert top > 0


def test_equal_centroids_build_a_balanced_tree():
    tri = np.broadcast_to([[0, 0, 0], [1, 0, 0], [0, 1, 0]], (4096, 3, 3))
    bvh = rayaccel.build(_mesh(tri), "bvh2.lbvh", max_leaf_size=1).structure
    bvh.validate()
    assert bvh.depth() == 12


@pytest.mark.slow
def test_a_million_copies_of_one_triangle(full):
    n = 1_000_000 if full else 200_000
    tri = np.broadcast_to([[0, 0, 0], [1, 0, 0], [0, 1, 0]], (n, 3, 3))
    for key in ("bvh2.lbvh", "bvh2.ploc"):
        bvh = rayaccel.build(_mesh(tri), key).structure
        bvh.validate()
        assert bvh.depth() <= MAX_DEPTH


def test_skewed_63_bit_codes_stay_within_the_depth_bound():
    # Triangles at positions 2^-k: every level of the Morton order nests one deeper.
    k = np.arange(120, dtype=np.float64)
    x = np.concatenate([2.0 ** (-k / 2), [1e6]])
    tri = np.zeros((x.size, 3, 3))
    tri[:, :, 0] = x[:, None]
    tri[:, 1, 1] = 1e-9
    tri[:, 2, 2] = 1e-9
    mesh = _mesh(tri)
    for bits in (30, 63):
        bvh = rayaccel.build(mesh, "bvh2.lbvh", morton_bits=bits, max_leaf_size=1).structure
        bvh.validate(mesh.triangles())
        assert bvh.depth() <= MAX_DEPTH


def test_63_bits_no_worse_than_30_bits_on_a_large_scene():
    mesh = rayaccel.scenes.get("sphereflake")
    sah = {bits: rayaccel.build(mesh, "bvh2.lbvh", morton_bits=bits).structure.sah_cost()
           for bits in (30, 63)}
    assert sah[63] <= sah[30] * 1.05


def _same_tree(a, b):
    fields = ("node_lo", "node_hi", "node_first", "node_count", "prim_index")
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields)


@pytest.mark.parametrize("bits", [30, 63])
def test_apetrei_and_karras_emissions_build_the_same_tree(threads, bits):
    # Both find the radix tree of the sorted codes, index bits breaking ties; the
    # bottom-up pass must also refit and collapse exactly as the post-order refit does,
    # with any number of threads. Duplicated centroids exercise the tie rule.
    rng = np.random.default_rng(3)
    soup = rng.random((3000, 3, 3)) * 10
    soup[1000:1600] = soup[7]
    soup[2000:2100] = soup[2000]
    meshes = [_mesh(soup), rayaccel.scenes.get("cornell-box"), rayaccel.scenes.get("teapot")]
    for mesh in meshes:
        karras = rayaccel.build(mesh, "bvh2.lbvh", morton_bits=bits, emission="karras")
        for n in (1, 2):
            threads(n)
            apetrei = rayaccel.build(mesh, "bvh2.lbvh", morton_bits=bits, emission="apetrei")
            apetrei.structure.validate(mesh.triangles())
            assert _same_tree(apetrei.structure, karras.structure)


def test_apetrei_handles_one_and_two_references():
    for n in (1, 2):
        tri = np.zeros((n, 3, 3))
        tri[:, 1, 0] = 1
        tri[:, 2, 1] = 1
        tri[:, :, 2] = np.arange(n)[:, None]
        mesh = _mesh(tri)
        bvh = rayaccel.build(mesh, "bvh2.lbvh", emission="apetrei", max_leaf_size=1).structure
        bvh.validate(mesh.triangles())
        assert bvh.n_nodes == 2 * n - 1


def test_bad_options_name_the_option():
    for bad, name in (({"morton_bits": 32}, "morton_bits"), ({"emission": "lauterbach"},
                      "emission"), ({"max_leaf_size": 0},
                      "max_leaf_size"), ({"intersection_cost": 0}, "intersection_cost")):
        with pytest.raises(InvalidInputError, match=name):
            LbvhOptions(**bad)
