"""Every registered CPU traversal has the public form ``register_traversal`` gives it."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from rayaccel import registry
from rayaccel._variant import annotated_options

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
