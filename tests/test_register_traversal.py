"""Every registered CPU traversal has the public form ``register_traversal`` gives it."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from rayaccel import registry
from rayaccel._variant import annotated_options, docstring_reference, docstring_summary

TRAVERSALS = [v for v in registry.variants("traversal") if v.backend == "cpu"]


@pytest.mark.parametrize("variant", TRAVERSALS, ids=lambda v: v.key)
def test_public_signature_and_docstring(variant):
    signature = inspect.signature(variant.func)
    names = list(signature.parameters)
    assert names[1:] == ["mesh", "rays", "query", "stats", "options", "cache"]
    keyword = [p.name for p in signature.parameters.values() if p.kind is p.KEYWORD_ONLY]
    assert keyword == ["query", "stats", "options", "cache"]
    assert signature.parameters["query"].default == "closest"
    assert signature.parameters["options"].annotation == f"{variant.options.__name__} | None"
    assert signature.return_annotation == "HitBatch"
    assert variant.func.__name__ == "trace_" + variant.key.replace(".", "_")
    doc = variant.func.__doc__
    assert "Parameters\n----------" in doc
    assert f"options : {variant.options.__name__}" in doc
    assert "Returns\n-------\nHitBatch" in doc


@pytest.mark.parametrize("variant", registry.variants(), ids=lambda v: v.key)
def test_options_are_the_annotated_dataclass(variant):
    # Every variant states its options type once, in its signature; the registry reads it.
    annotation = inspect.signature(variant.func).parameters["options"].annotation
    assert annotation.split(" | ")[0] == variant.options.__name__
    assert dataclasses.is_dataclass(variant.options)


def test_a_variant_without_an_options_dataclass_is_refused():
    def plan(structure, mesh, options: int, cache):  # an int is not an options dataclass
        return None

    with pytest.raises(TypeError, match="annotate 'options'"):
        annotated_options(plan)
    with pytest.raises(TypeError, match="annotate 'options'"):
        annotated_options(lambda mesh: None)


@pytest.mark.parametrize("variant", registry.variants(), ids=lambda v: v.key)
def test_summary_and_reference_come_from_the_docstring(variant):
    # A variant describes itself once: `rayaccel list` shows its docstring's first line
    # and its References section.
    doc = inspect.cleandoc(variant.func.__doc__)
    assert doc.startswith(variant.summary)
    if variant.reference:
        section = doc.split("References\n----------\n", 1)[1]
        assert " ".join(section.split()).startswith(variant.reference)


def test_docstring_summary_and_reference_are_parsed():
    def build(mesh, options=None):
        """Build something quickly.

        More text.

        Parameters
        ----------
        mesh : TriangleMesh

        References
        ----------
        A & B 2001, First Paper;
        C 2002, Second Paper.

        Examples
        --------
        >>> build(mesh)
        """

    assert docstring_summary(build) == "Build something quickly"
    assert docstring_reference(build) == "A & B 2001, First Paper; C 2002, Second Paper"

    def bare(mesh, options=None):
        pass

    assert docstring_reference(bare) == ""
    with pytest.raises(ValueError, match="needs a docstring"):
        docstring_summary(bare)
