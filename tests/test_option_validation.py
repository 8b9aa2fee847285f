"""Options and arguments of the wrong type are refused by one check, naming what is wrong.

Issue 20's "options and arguments" class: before this check a float leaf size was
truncated, ``stats="no"`` turned statistics on, a string ``tmin`` was parsed and a
masked array's hidden values were traced.
"""

from __future__ import annotations

import dataclasses
import re
import typing

import numpy as np
import pytest

import rayaccel
from rayaccel import registry
from rayaccel.errors import InvalidInputError
from rayaccel.scene import catalog

#: A value of the wrong type for each annotated option type, and what the error says.
WRONG = {
    int: (2.5, "an integer"),
    float: ("1.0", "a number"),
    bool: ("no", "True or False"),
    str: (3, "a string"),
}


def _fields():
    out = []
    for role in ("builder", "traversal", "step"):
        for key in registry.keys(role):
            options = registry.get(key, role).options
            hints = typing.get_type_hints(options)
            out += [(role, key, f.name, hints[f.name]) for f in dataclasses.fields(options)]
    return out


FIELDS = _fields()


def test_every_option_has_a_checked_type():
    assert FIELDS
    assert {kind for *_, kind in FIELDS} <= set(WRONG)


@pytest.mark.parametrize(("role", "key", "name", "kind"), FIELDS,
                         ids=[f"{k}.{n}" for _, k, n, _ in FIELDS])  # fmt: skip
def test_wrong_type_is_refused_naming_the_option(role, key, name, kind):
    variant = registry.get(key, role)
    value, expected = WRONG[kind]
    with pytest.raises(
        InvalidInputError, match=re.escape(f"{key}: option '{name}' expects {expected}")
    ):
        variant.make_options({name: value})
    if kind in (int, float):
        with pytest.raises(InvalidInputError, match=f"option '{name}'"):
            variant.make_options({name: True})  # a bool is not a number here
    default = getattr(variant.make_options(), name)
    # The default, given explicitly (numpy scalars included), is taken as it is
    given = np.int64(default) if kind is int else default
    assert getattr(variant.make_options({name: given}), name) == default


def test_float_options_take_ints_and_refuse_nan():
    opts = registry.get("bvh2.binned_sah", "builder").make_options({"traversal_cost": 2})
    assert opts.traversal_cost == 2.0
    assert isinstance(opts.traversal_cost, float)
    with pytest.raises(InvalidInputError, match="not NaN"):
        registry.get("bvh2.binned_sah", "builder").make_options({"traversal_cost": float("nan")})


@pytest.fixture(scope="module")
def accel():
    return rayaccel.build(catalog.get("cornell-box"), "bvh2.binned_sah")


def test_build_refuses_a_float_leaf_size():
    with pytest.raises(InvalidInputError, match=r"max_leaf_size' expects an integer, got 4\.5"):
        rayaccel.build(catalog.get("cornell-box"), "bvh2.binned_sah", max_leaf_size=4.5)
    with pytest.raises(InvalidInputError, match="reinsert: option 'max_iterations'"):
        rayaccel.build(catalog.get("cornell-box"), "bvh2.binned_sah+reinsert",
                       reinsert={"max_iterations": "3"})  # fmt: skip


def test_query_arguments_are_checked(accel):
    origins = np.zeros((4, 3))
    directions = np.tile([0.0, 0.0, 1.0], (4, 1))
    with pytest.raises(InvalidInputError, match="stats: expected True or False, got 'no'"):
        accel.intersect(origins, directions, stats="no")
    with pytest.raises(InvalidInputError, match="tmin: expected a float scalar"):
        accel.intersect(origins, directions, tmin="0.1")
    with pytest.raises(InvalidInputError, match="tmax: expected a float scalar"):
        accel.intersect(origins, directions, tmax=np.array([True, False, True, True]))
    with pytest.raises(InvalidInputError, match="traversal: expected a registry key"):
        accel.intersect(origins, directions, traversal=3)
    with pytest.raises(InvalidInputError, match="option 'short_stack' expects an integer"):
        accel.intersect(origins, directions, traversal="bvh2.restart_trail", short_stack=2.0)


def test_masked_arrays_with_hidden_values_are_refused(accel):
    origins = np.ma.masked_array(np.zeros((4, 3)), mask=np.zeros((4, 3), dtype=bool))
    directions = np.tile([0.0, 0.0, 1.0], (4, 1))
    clean = accel.intersect(origins, directions)  # nothing masked: used as it is
    np.testing.assert_array_equal(clean.prim, accel.intersect(origins.data, directions).prim)
    origins[1, 2] = np.ma.masked
    with pytest.raises(InvalidInputError, match="origins: a masked array with 1 masked"):
        accel.intersect(origins, directions)
    tmax = np.ma.masked_invalid([1.0, np.nan, 2.0, 3.0])
    with pytest.raises(InvalidInputError, match="tmax: a masked array"):
        accel.intersect(origins.data, directions, tmax=tmax)
    points = np.ma.masked_array(np.zeros((2, 3)), mask=[[0, 0, 0], [0, 0, 1]])
    for query in (accel.compute_closest_points, accel.compute_occupancy):
        with pytest.raises(InvalidInputError, match="points: a masked array with 1 masked"):
            query(points)
    vertices = np.ma.masked_array(np.eye(3), mask=[[0, 0, 0], [0, 1, 0], [0, 0, 0]])
    with pytest.raises(InvalidInputError, match="vertices: a masked array"):
        rayaccel.TriangleMesh(vertices, [[0, 1, 2]])
