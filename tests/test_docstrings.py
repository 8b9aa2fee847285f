"""Shared numpydoc sections are added once, before a docstring's own sections."""

from __future__ import annotations

from rayaccel._docstrings import with_sections
from rayaccel.bvh.traverse.all_hits import BVH_QUERY_PARAMETERS, count_all_hits
from rayaccel.scene.polygons import READER_PARAMETERS
from rayaccel.scene.stl import parse_stl

SHARED = "Parameters\n----------\nx : int\n    The value.\n"


def test_sections_go_before_the_own_sections():
    @with_sections(SHARED)
    def f(x):
        """Do a thing.

        More words.

        Returns
        -------
        int
        """

    doc = f.__doc__
    assert doc.index("More words.") < doc.index("Parameters") < doc.index("Returns")
    assert doc.count("Parameters") == 1


def test_a_docstring_without_sections_ends_with_the_shared_ones():
    @with_sections(SHARED)
    def f(x):
        """Do a thing."""

    assert f.__doc__.startswith("Do a thing.\n\nParameters\n----------\nx : int")


def test_own_parameters_and_missing_docstrings_are_left_alone():
    @with_sections(SHARED)
    def own(x):
        """Do a thing.

        Parameters
        ----------
        x : float
        """

    @with_sections(SHARED)
    def bare(x):
        pass

    assert "x : int" not in own.__doc__
    assert bare.__doc__ is None


def test_the_package_functions_carry_their_shared_sections():
    assert BVH_QUERY_PARAMETERS.strip() in count_all_hits.__doc__
    assert READER_PARAMETERS.strip() in parse_stl.__doc__
